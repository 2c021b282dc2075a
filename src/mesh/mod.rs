//! Indexed triangle mesh, exactly as in the input file (contract: "Indices").
//!
//! Vertex `i` is the i-th vertex of the file, face `f` the f-th triangle after fan
//! triangulation in file order. Nothing is ever re-ordered, merged or split.

pub mod io;
pub mod topology;
pub mod validate;

use glam::DVec3;

/// Twice a face's area at or below this times the squared bbox diagonal counts as
/// zero ([`Mesh::degenerate_faces`]).
pub const DEGENERATE_AREA: f64 = 1e-12;

/// A face with an angle whose cotangent exceeds this in magnitude is a needle or a
/// cap ([`Mesh::degenerate_faces`]): its cotangent weights would be clamped.
pub const COT_CAP: f64 = 1e5;

/// A named set of faces (OBJ `g`/`o` statement).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FaceGroup {
    pub name: String,
    pub faces: Vec<usize>,
}

/// Triangle mesh with positions in f64.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub positions: Vec<DVec3>,
    pub faces: Vec<[u32; 3]>,
    /// OBJ groups/objects (empty for PLY/STL). A face may be in several groups.
    pub groups: Vec<FaceGroup>,
}

impl Mesh {
    /// A mesh from vertex positions and triangles (0-based vertex indices), no
    /// groups. Only an index too large for 32 bits is refused here; the rest
    /// (indices in range, finite positions) is checked by
    /// [`crate::problem::Problem::new`].
    pub fn from_arrays(positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> crate::Result<Mesh> {
        let faces = triangles
            .iter()
            .enumerate()
            .map(|(f, t)| {
                let mut out = [0u32; 3];
                for k in 0..3 {
                    out[k] = u32::try_from(t[k]).map_err(|_| {
                        crate::Error::bad(format!(
                            "face {f} corner {k} refers to vertex {}, beyond the 2^32 vertices \
                             a mesh may have",
                            t[k]
                        ))
                    })?;
                }
                Ok(out)
            })
            .collect::<crate::Result<Vec<_>>>()?;
        Ok(Mesh {
            positions: positions.iter().map(|&p| DVec3::from_array(p)).collect(),
            faces,
            groups: Vec::new(),
        })
    }

    pub fn num_vertices(&self) -> usize {
        self.positions.len()
    }
    pub fn num_faces(&self) -> usize {
        self.faces.len()
    }

    /// The three corner positions of face `f` in the given position array.
    #[inline]
    pub fn corners(&self, x: &[DVec3], f: usize) -> [DVec3; 3] {
        let [a, b, c] = self.faces[f];
        [x[a as usize], x[b as usize], x[c as usize]]
    }

    /// Area of face `f` for positions `x`.
    #[inline]
    pub fn face_area(&self, x: &[DVec3], f: usize) -> f64 {
        let [a, b, c] = self.corners(x, f);
        0.5 * (b - a).cross(c - a).length()
    }

    /// Areas of all faces for positions `x`, on rayon's threads (each face
    /// apart: the same values on any thread count). Every outer iteration
    /// reads them: 1.2M faces at homer 1.2M.
    pub fn face_areas(&self, x: &[DVec3]) -> Vec<f64> {
        use rayon::prelude::*;
        (0..self.faces.len())
            .into_par_iter()
            .map(|f| self.face_area(x, f))
            .collect()
    }

    /// Signed volume (sum of signed tetrahedra to the origin) for positions `x`.
    pub fn signed_volume(&self, x: &[DVec3]) -> f64 {
        crate::ordered::sum_in_order(self.faces.len(), |f| self.signed_tetrahedron(x, f))
    }

    /// Signed volume of the tetrahedron from the origin to face `f`.
    #[inline]
    pub fn signed_tetrahedron(&self, x: &[DVec3], f: usize) -> f64 {
        let [a, b, c] = self.corners(x, f);
        a.dot(b.cross(c)) / 6.0
    }

    /// Axis-aligned bounding box diagonal length of the vertices that faces use.
    pub fn bbox_diagonal(&self, x: &[DVec3]) -> f64 {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for t in &self.faces {
            for &v in t {
                lo = lo.min(x[v as usize]);
                hi = hi.max(x[v as usize]);
            }
        }
        if lo.x > hi.x {
            return 0.0;
        }
        (hi - lo).length()
    }

    /// Faces that get no shape weight (no frame energy, no Laplacian weights):
    /// zero-area faces (twice the area at most [`DEGENERATE_AREA`] times the bbox
    /// diagonal squared, the tolerance of a robust `doublearea`) and needles or caps
    /// (an angle whose cotangent exceeds [`COT_CAP`] in magnitude, where libigl's
    /// `cotmatrix_entries` would give huge or infinite weights). A face whose corners
    /// are not all distinct counts too. Judged on the positions `x`.
    pub fn degenerate_faces(&self, x: &[DVec3]) -> Vec<bool> {
        use rayon::prelude::*;
        let diag = self.bbox_diagonal(x);
        let tol = DEGENERATE_AREA * diag * diag;
        self.faces
            .par_iter()
            .map(|t| {
                let [a, b, c] = *t;
                if a == b || b == c || a == c {
                    return true;
                }
                let p = [x[a as usize], x[b as usize], x[c as usize]];
                let cr = (p[1] - p[0]).cross(p[2] - p[0]).length();
                if cr.is_nan() || cr <= tol {
                    return true;
                }
                (0..3).any(|k| {
                    let e1 = p[(k + 1) % 3] - p[k];
                    let e2 = p[(k + 2) % 3] - p[k];
                    e1.dot(e2).abs() > COT_CAP * cr
                })
            })
            .collect()
    }

    /// Face centroid for positions `x`.
    #[inline]
    pub fn centroid(&self, x: &[DVec3], f: usize) -> DVec3 {
        let [a, b, c] = self.corners(x, f);
        (a + b + c) / 3.0
    }
}

impl Mesh {
    /// 1-to-4 midpoint subdivision (for benchmarks at larger sizes). Groups are dropped.
    pub fn subdivide_midpoint(&self) -> Mesh {
        use std::collections::HashMap;
        let mut positions = self.positions.clone();
        let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(self.faces.len() * 2);
        let mut faces = Vec::with_capacity(self.faces.len() * 4);
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<DVec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                positions.push(0.5 * (positions[a as usize] + positions[b as usize]));
                (positions.len() - 1) as u32
            })
        };
        for &[a, b, c] in &self.faces {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            faces.extend_from_slice(&[[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        Mesh {
            positions,
            faces,
            groups: Vec::new(),
        }
    }

    /// Uniform refinement: every edge cut into `n` equal segments, every face into
    /// `n^2` faces of its barycentric lattice (for benchmarks at sizes between the
    /// powers of 4 that [`Mesh::subdivide_midpoint`] gives). Groups are dropped.
    pub fn subdivide_uniform(&self, n: usize) -> Mesh {
        use std::collections::HashMap;
        assert!(n >= 1, "subdivide_uniform: n must be at least 1");
        let mut positions = self.positions.clone();
        let mut faces = Vec::with_capacity(self.faces.len() * n * n);
        // First of the n - 1 interior points of each edge, listed from its lower
        // vertex index to its higher.
        let mut edge_first: HashMap<(u32, u32), u32> =
            HashMap::with_capacity(self.faces.len() * 3 / 2);
        let mut lattice = vec![0u32; (n + 1) * (n + 1)];
        let at = |i: usize, j: usize| i * (n + 1) + j;
        for &[a, b, c] in &self.faces {
            let (pa, pb, pc) = (
                positions[a as usize],
                positions[b as usize],
                positions[c as usize],
            );
            // Point t (1..n) from u towards v on edge (u, v).
            let mut edge_point = |u: u32, v: u32, t: usize, positions: &mut Vec<DVec3>| -> u32 {
                let key = (u.min(v), u.max(v));
                let first = *edge_first.entry(key).or_insert_with(|| {
                    let (p, q) = (positions[key.0 as usize], positions[key.1 as usize]);
                    let first = positions.len() as u32;
                    for s in 1..n {
                        positions.push(p + (q - p) * (s as f64 / n as f64));
                    }
                    first
                });
                let s = if u < v { t } else { n - t };
                first + (s - 1) as u32
            };
            for i in 0..=n {
                for j in 0..=n - i {
                    let k = n - i - j;
                    lattice[at(i, j)] = match (i, j, k) {
                        (0, 0, _) => a,
                        (_, 0, 0) => b,
                        (0, _, 0) => c,
                        (_, 0, _) => edge_point(a, b, i, &mut positions),
                        (0, _, _) => edge_point(a, c, j, &mut positions),
                        (_, _, 0) => edge_point(b, c, j, &mut positions),
                        _ => {
                            let (u, v) = (i as f64 / n as f64, j as f64 / n as f64);
                            positions.push(pa + (pb - pa) * u + (pc - pa) * v);
                            (positions.len() - 1) as u32
                        }
                    };
                }
            }
            for i in 0..n {
                for j in 0..n - i {
                    faces.push([
                        lattice[at(i, j)],
                        lattice[at(i + 1, j)],
                        lattice[at(i, j + 1)],
                    ]);
                    if i + j + 1 < n {
                        faces.push([
                            lattice[at(i + 1, j)],
                            lattice[at(i + 1, j + 1)],
                            lattice[at(i, j + 1)],
                        ]);
                    }
                }
            }
        }
        Mesh {
            positions,
            faces,
            groups: Vec::new(),
        }
    }
}

/// The gradient of a triangle's area with respect to its corners `p`,
/// `d area / d p_k = 1/2 n_hat x (p_{k+2} - p_{k+1})`, with twice the area
/// (the normal's length); `None` for a degenerate triangle.
#[inline]
pub fn triangle_area_gradient(p: [DVec3; 3]) -> Option<(f64, [DVec3; 3])> {
    let n = (p[1] - p[0]).cross(p[2] - p[0]);
    let len = n.length();
    if len <= 0.0 {
        return None;
    }
    let nh = n / len;
    Some((
        len,
        std::array::from_fn(|k| 0.5 * nh.cross(p[(k + 2) % 3] - p[(k + 1) % 3])),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::topology::Topology;

    fn tetrahedron() -> Mesh {
        Mesh {
            positions: vec![
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(1.0, 0.0, 0.0),
                DVec3::new(0.0, 1.0, 0.0),
                DVec3::new(0.0, 0.0, 1.0),
            ],
            faces: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            groups: Vec::new(),
        }
    }

    /// n^2 faces per face, shared edge points (a closed mesh stays closed, with
    /// Euler characteristic 2), area and enclosed volume unchanged (flat faces).
    #[test]
    fn uniform_subdivision_keeps_a_closed_surface() {
        let m = tetrahedron();
        let area: f64 = m.face_areas(&m.positions).iter().sum();
        for n in [1, 2, 3, 5] {
            let s = m.subdivide_uniform(n);
            assert_eq!(s.num_faces(), 4 * n * n);
            assert_eq!(
                s.num_vertices(),
                4 + 6 * (n - 1) + 4 * (n - 1) * (n.max(2) - 2) / 2
            );
            let topo = Topology::build(&s);
            assert!(topo.is_closed(), "n = {n}");
            let euler = s.num_vertices() as i64 - topo.edges.len() as i64 + s.num_faces() as i64;
            assert_eq!(euler, 2, "n = {n}");
            let a: f64 = s.face_areas(&s.positions).iter().sum();
            assert!(
                (a - area).abs() < 1e-12 * area,
                "n = {n}: area {a} vs {area}"
            );
            let volume = |m: &Mesh| -> f64 {
                m.faces
                    .iter()
                    .map(|t| {
                        let [p, q, r] = t.map(|v| m.positions[v as usize]);
                        p.dot(q.cross(r)) / 6.0
                    })
                    .sum()
            };
            assert!((volume(&s) - volume(&m)).abs() < 1e-12, "n = {n}");
        }
        // n = 2 gives the midpoint subdivision's vertices.
        let mut a: Vec<[i64; 3]> = m
            .subdivide_uniform(2)
            .positions
            .iter()
            .map(|p| (*p * 1e6).round().as_i64vec3().to_array())
            .collect();
        let mut b: Vec<[i64; 3]> = m
            .subdivide_midpoint()
            .positions
            .iter()
            .map(|p| (*p * 1e6).round().as_i64vec3().to_array())
            .collect();
        a.sort();
        b.sort();
        assert_eq!(a, b);
    }
}
