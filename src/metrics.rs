//! The metrics users demand (paper Sec. 3): curve length, region area, enclosed
//! volume. Each is measured in vertex positions `x` (with its gradient, for the
//! hard constraints of Eqs. 10, 12, 14) and written as a polynomial in per-face
//! scale factors `s` (for the scale-factor estimation of Eqs. 9, 11, 13).

use crate::mesh::{triangle_area_gradient, Mesh};
use crate::ordered::{fill_at_once, sum_in_order};
use crate::selection::{FaceSet, SurfaceCurve};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::fmt;

/// Which metric a constraint demands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MetricKind {
    Length,
    Area,
    Volume,
}

impl fmt::Display for MetricKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MetricKind::Length => "length",
            MetricKind::Area => "area",
            MetricKind::Volume => "volume",
        })
    }
}

/// What a constraint measures.
#[derive(Debug, Clone)]
pub enum Selection {
    Curve(SurfaceCurve),
    Region(FaceSet),
    /// The whole (closed) mesh.
    Whole,
}

/// How each face contributes to the volume in the scale-factor step (pitfall (c)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum VolumeShare {
    /// Each face carries an area share of the current volume (origin-independent; default).
    #[default]
    Area,
    /// Each face carries its signed tetrahedron to the origin (paper Sec. 3.3, literal).
    Tetrahedra,
}

/// One demanded metric, resolved on the input mesh.
#[derive(Debug, Clone)]
pub struct Constraint {
    pub kind: MetricKind,
    pub name: String,
    pub selection: Selection,
    /// Value on the input mesh.
    pub original: f64,
    /// Demanded value.
    pub target: f64,
    /// Sign of the input's signed volume (an inward-oriented mesh has -1).
    pub orientation: f64,
    /// Faces a whole-mesh metric leaves out (duplicate faces, see
    /// [`crate::mesh::topology::Topology::duplicate_faces`]); empty: none.
    pub skip: Vec<bool>,
}

impl Constraint {
    /// The metric on positions `x` (volume as a positive number for the input's orientation).
    pub fn measure(&self, mesh: &Mesh, x: &[DVec3]) -> f64 {
        match &self.selection {
            Selection::Curve(c) => c.length(mesh, x),
            Selection::Region(r) => {
                sum_in_order(r.faces.len(), |i| mesh.face_area(x, r.faces[i] as usize))
            }
            Selection::Whole => match self.kind {
                MetricKind::Volume => {
                    self.orientation * self.sum_whole(mesh, |f| mesh.signed_tetrahedron(x, f))
                }
                _ => self.sum_whole(mesh, |f| mesh.face_area(x, f)),
            },
        }
    }

    /// `term`'s sum over the whole-mesh metric's faces, in face order (the
    /// terms on rayon's threads where no face is skipped).
    fn sum_whole(&self, mesh: &Mesh, term: impl Fn(usize) -> f64 + Sync) -> f64 {
        match self.skip.is_empty() {
            true => sum_in_order(mesh.num_faces(), term),
            false => self.whole_faces(mesh).map(term).sum(),
        }
    }

    /// `out` refilled with `term` of each of the whole-mesh metric's faces,
    /// in face order (on rayon's threads where no face is skipped).
    fn fill_whole(
        &self,
        mesh: &Mesh,
        out: &mut Vec<(u32, f64)>,
        term: impl Fn(usize) -> (u32, f64) + Sync + Send,
    ) {
        match self.skip.is_empty() {
            true => fill_at_once(out, mesh.num_faces(), term),
            false => {
                out.clear();
                out.extend(self.whole_faces(mesh).map(term));
            }
        }
    }

    /// The faces a whole-mesh metric runs over: all but those flagged in `skip`.
    fn whole_faces<'a>(&'a self, mesh: &Mesh) -> impl Iterator<Item = usize> + 'a {
        (0..mesh.num_faces()).filter(move |&f| !self.skip.get(f).copied().unwrap_or(false))
    }

    /// Relative residual `C = measure / target - 1` (the hard constraint of Eq. 8).
    pub fn residual(&self, mesh: &Mesh, x: &[DVec3]) -> f64 {
        self.measure(mesh, x) / self.target - 1.0
    }

    /// Adds `factor * d measure / d x` into `grad` (length 3n, dof 3v+r).
    pub fn add_gradient(&self, mesh: &Mesh, x: &[DVec3], factor: f64, grad: &mut [f64]) {
        let mut add = |v: u32, g: DVec3| {
            let i = 3 * v as usize;
            grad[i] += factor * g.x;
            grad[i + 1] += factor * g.y;
            grad[i + 2] += factor * g.z;
        };
        match &self.selection {
            Selection::Curve(c) => {
                for seg in &c.segments {
                    let t = mesh.faces[seg.face as usize];
                    let (a, b) = seg.ends(mesh, x);
                    let d = b - a;
                    let len = d.length();
                    if len <= 0.0 {
                        continue;
                    }
                    let u = d / len;
                    for k in 0..3 {
                        add(t[k], (seg.b[k] - seg.a[k]) * u);
                    }
                }
            }
            Selection::Region(r) => {
                for &f in &r.faces {
                    area_gradient(mesh, x, f as usize, &mut add);
                }
            }
            Selection::Whole => match self.kind {
                MetricKind::Volume => {
                    let s = self.orientation / 6.0;
                    for f in self.whole_faces(mesh) {
                        let t = &mesh.faces[f];
                        let [a, b, c] = [x[t[0] as usize], x[t[1] as usize], x[t[2] as usize]];
                        add(t[0], s * b.cross(c));
                        add(t[1], s * c.cross(a));
                        add(t[2], s * a.cross(b));
                    }
                }
                _ => {
                    for f in self.whole_faces(mesh) {
                        area_gradient(mesh, x, f, &mut add);
                    }
                }
            },
        }
    }

    /// Degree of the metric in the per-face scale factor (1 length, 2 area, 3 volume).
    pub fn degree(&self) -> i32 {
        match self.kind {
            MetricKind::Length => 1,
            MetricKind::Area => 2,
            MetricKind::Volume => 3,
        }
    }

    /// Per-face coefficients `c_f` so that the metric after scaling face f by `s_f`
    /// is `sum_f c_f s_f^degree` (Eqs. 9, 11, 13), on current positions `x`.
    pub fn face_coefficients(
        &self,
        mesh: &Mesh,
        x: &[DVec3],
        areas: &[f64],
        share: VolumeShare,
    ) -> Vec<(u32, f64)> {
        let mut out = Vec::new();
        self.face_coefficients_into(mesh, x, areas, share, &mut out);
        out
    }

    /// [`Self::face_coefficients`] into `out`, replacing its contents: the
    /// scale-driven iteration refills one vector per constraint (a whole
    /// mesh's are 16 bytes a face, which a fresh vector would fault in page
    /// by page at every iteration).
    pub fn face_coefficients_into(
        &self,
        mesh: &Mesh,
        x: &[DVec3],
        areas: &[f64],
        share: VolumeShare,
        out: &mut Vec<(u32, f64)>,
    ) {
        out.clear();
        match &self.selection {
            Selection::Curve(c) => {
                out.extend(c.segments.iter().map(|seg| (seg.face, seg.length(mesh, x))));
                merge(out);
            }
            Selection::Region(r) => out.extend(r.faces.iter().map(|&f| (f, areas[f as usize]))),
            Selection::Whole => match self.kind {
                MetricKind::Volume => match share {
                    VolumeShare::Area => {
                        let vol = self.measure(mesh, x);
                        let total = self.sum_whole(mesh, |f| areas[f]);
                        self.fill_whole(mesh, out, |f| (f as u32, vol * areas[f] / total));
                    }
                    VolumeShare::Tetrahedra => self.fill_whole(mesh, out, |f| {
                        (f as u32, self.orientation * mesh.signed_tetrahedron(x, f))
                    }),
                },
                _ => self.fill_whole(mesh, out, |f| (f as u32, areas[f])),
            },
        }
    }
}

/// Adds face f's area gradient (d area / d corner) to `add`.
#[inline]
fn area_gradient(mesh: &Mesh, x: &[DVec3], f: usize, add: &mut impl FnMut(u32, DVec3)) {
    let t = mesh.faces[f];
    if let Some((_, g)) = triangle_area_gradient(mesh.corners(x, f)) {
        for k in 0..3 {
            add(t[k], g[k]);
        }
    }
}

/// Sum coefficients of repeated faces.
fn merge(v: &mut Vec<(u32, f64)>) {
    v.sort_by_key(|e| e.0);
    v.dedup_by(|later, kept| {
        let same = later.0 == kept.0;
        if same {
            kept.1 += later.1;
        }
        same
    });
}
