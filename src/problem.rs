//! The problem a run solves, built from a mesh in memory and typed demands:
//! constraints on lengths, areas and volume (paper Sec. 3), handles (the
//! position energy E_p of Sec. 5.2) and curvature regions (Eq. 21).
//!
//! [`Problem::new`] is the one place where demands are checked against the
//! mesh; the job file ([`crate::job`]) is one front end that builds them.
//!
//! ```
//! use metricdeform::problem::{Demand, Problem};
//! use metricdeform::selection::{Curve, Region};
//! use metricdeform::Mesh;
//! // A unit cube's surface, 12 triangles.
//! let positions = [
//!     [0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.],
//!     [0., 0., 1.], [1., 0., 1.], [1., 1., 1.], [0., 1., 1.],
//! ];
//! let triangles = [
//!     [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
//!     [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
//! ];
//! let mesh = Mesh::from_arrays(&positions, &triangles).unwrap();
//! let demands = [
//!     // The girth at half height 10 % longer, the top's area kept.
//!     Demand::length(Curve::Plane { origin: [0.5, 0.5, 0.5], normal: [0., 0., 1.] })
//!         .scale(1.1)
//!         .named("girth"),
//!     Demand::area(Region::Faces(vec![2, 3])),
//! ];
//! let problem = Problem::new(mesh, "cube", &demands, &[], &[]).unwrap();
//! assert_eq!(problem.constraints.len(), 2);
//! assert!((problem.constraints[0].original - 4.0).abs() < 1e-12);
//! assert!((problem.constraints[0].target - 4.4).abs() < 1e-12);
//! ```

use crate::mesh::topology::Topology;
use crate::mesh::validate::{require_volume, validate, MeshCheck};
use crate::metrics::{Constraint, MetricKind, Selection};
use crate::selection::{build_curve, build_handle_vertices, build_region, Curve, Region};
use crate::shape::{CurvatureRegion, HandleTarget};
use crate::{Error, Mesh, Result};
use glam::DVec3;
use std::path::PathBuf;

/// What a constraint demands of which selection.
#[derive(Clone, Debug, PartialEq)]
pub enum Metric {
    /// The length of a curve on the surface (Sec. 3.1).
    Length(Curve),
    /// The area of a set of faces (Sec. 3.2).
    Area(Region),
    /// The volume the closed mesh encloses (Sec. 3.3).
    Volume,
}

impl Metric {
    pub fn kind(&self) -> MetricKind {
        match self {
            Metric::Length(_) => MetricKind::Length,
            Metric::Area(_) => MetricKind::Area,
            Metric::Volume => MetricKind::Volume,
        }
    }
}

/// The value a constraint asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Target {
    /// The input's value.
    #[default]
    Keep,
    /// The input's value times this factor (> 0).
    Scale(f64),
    /// This value (> 0), in the mesh's units (squared, cubed).
    Value(f64),
}

/// One constraint: a metric and its target.
#[derive(Clone, Debug, PartialEq)]
pub struct Demand {
    /// Shown in reports and messages; default `<kind> <number>`.
    pub name: Option<String>,
    pub metric: Metric,
    pub target: Target,
}

impl Demand {
    /// Keep a curve's length (set the target with [`Demand::scale`] or [`Demand::value`]).
    pub fn length(curve: Curve) -> Demand {
        Demand::of(Metric::Length(curve))
    }
    /// Keep a region's area.
    pub fn area(region: Region) -> Demand {
        Demand::of(Metric::Area(region))
    }
    /// Keep the enclosed volume.
    pub fn volume() -> Demand {
        Demand::of(Metric::Volume)
    }
    fn of(metric: Metric) -> Demand {
        Demand {
            name: None,
            metric,
            target: Target::Keep,
        }
    }
    /// Target = `factor` times the input's value.
    pub fn scale(mut self, factor: f64) -> Demand {
        self.target = Target::Scale(factor);
        self
    }
    /// Target = `value`.
    pub fn value(mut self, value: f64) -> Demand {
        self.target = Target::Value(value);
        self
    }
    /// A name for reports and messages.
    pub fn named(mut self, name: impl Into<String>) -> Demand {
        self.name = Some(name.into());
        self
    }

    /// The checks that need no mesh: a finite positive target, a valid
    /// selection (`Vertices` is no area region). `what` names the constraint.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        let (field, v) = match self.target {
            Target::Keep => ("", 1.0),
            Target::Scale(v) => ("scale", v),
            Target::Value(v) => ("value", v),
        };
        if !v.is_finite() || v <= 0.0 {
            return Err(format!(
                "{what}: {field} must be a finite number > 0 (got {v})"
            ));
        }
        match &self.metric {
            Metric::Length(curve) => curve.validate(what),
            Metric::Area(region) => region.validate(what, false),
            Metric::Volume => Ok(()),
        }
    }
}

/// A handle (Sec. 5.2, E_p): vertices pulled to their input position plus
/// `translate`.
#[derive(Clone, Debug, PartialEq)]
pub struct Handle {
    /// Its vertices: `Region::Vertices`, or every vertex of a region's faces.
    pub region: Region,
    pub translate: [f64; 3],
}

impl Handle {
    /// The checks that need no mesh. `what` names the handle.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        self.region.validate(what, true)?;
        if !self.translate.iter().all(|t| t.is_finite()) {
            return Err(format!("{what}: translate must be finite"));
        }
        Ok(())
    }
}

/// A curvature region (Eq. 21): the mean curvature of its vertices' E_m
/// targets multiplied by `scale`.
#[derive(Clone, Debug, PartialEq)]
pub struct Curvature {
    pub region: Region,
    pub scale: f64,
}

impl Curvature {
    /// The checks that need no mesh. `what` names the entry.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        self.region.validate(what, false)?;
        if !self.scale.is_finite() {
            return Err(format!("{what}: scale must be a finite number"));
        }
        Ok(())
    }
}

/// `constraint N ('name')`, or `constraint N (kind)` when unnamed; N = i + 1
/// is 1-based (the contract: constraints by name or 1-based number).
pub fn constraint_label(i: usize, name: Option<&str>, kind: MetricKind) -> String {
    match name {
        Some(name) => format!("constraint {} ('{name}')", i + 1),
        None => format!("constraint {} ({kind})", i + 1),
    }
}

/// `handle N` for the 0-based index `i`, N 1-based.
pub fn handle_label(i: usize) -> String {
    format!("handle {}", i + 1)
}

/// `curvature N` for the 0-based index `i`, N 1-based.
pub fn curvature_label(i: usize) -> String {
    format!("curvature {}", i + 1)
}

/// Demands resolved on their mesh: everything the solver needs.
pub struct Problem {
    /// The mesh's file, or the name a caller gave it; named in messages and
    /// reports.
    pub mesh_path: PathBuf,
    pub mesh: Mesh,
    pub topo: Topology,
    pub check: MeshCheck,
    pub constraints: Vec<Constraint>,
    pub handles: Vec<HandleTarget>,
    pub curvature: Vec<CurvatureRegion>,
    /// Tolerated defects of the input worth telling the user (zero-area, needle and
    /// duplicate faces, ...), one line each without a `warning:` prefix; they are
    /// also logged with `log::warn!` when found.
    pub warnings: Vec<String>,
}

impl Problem {
    /// Check `mesh` and resolve every demand, handle and curvature region on
    /// it. `source` names the mesh in messages (its file, or any name). Bad
    /// input is [`Error::BadInput`] naming the mesh or the demand and what to
    /// change.
    pub fn new(
        mesh: Mesh,
        source: impl Into<PathBuf>,
        demands: &[Demand],
        handles: &[Handle],
        curvature: &[Curvature],
    ) -> Result<Problem> {
        let mesh_path: PathBuf = source.into();
        let t0 = std::time::Instant::now();
        // Topology::build takes any corner index; validate refuses those out of range.
        let topo = Topology::build(&mesh);
        let t1 = std::time::Instant::now();
        let check = validate(&mesh, &topo, &mesh_path)?;
        let t2 = std::time::Instant::now();
        // Duplicate faces count once in whole-mesh metrics.
        let skip: Vec<bool> = if topo.duplicate_faces.is_empty() {
            Vec::new()
        } else {
            topo.is_duplicate.clone()
        };
        let x = &mesh.positions;
        let mut constraints = Vec::with_capacity(demands.len());
        for (i, d) in demands.iter().enumerate() {
            let kind = d.metric.kind();
            let label = constraint_label(i, d.name.as_deref(), kind);
            d.validate(&label).map_err(Error::bad)?;
            // The whole mesh's signed volume, measured once: the constraint's
            // orientation and (times it) its original value.
            let mut volume = None;
            let (selection, orientation) = match &d.metric {
                Metric::Length(curve) => (
                    Selection::Curve(build_curve(curve, &mesh, &topo, &label)?),
                    1.0,
                ),
                Metric::Area(region) => {
                    (Selection::Region(build_region(region, &mesh, &label)?), 1.0)
                }
                Metric::Volume => {
                    require_volume(&mesh, &topo, &check, &mesh_path, &label)?;
                    let v = Constraint {
                        kind,
                        name: String::new(),
                        selection: Selection::Whole,
                        original: 0.0,
                        target: 0.0,
                        orientation: 1.0,
                        skip: skip.clone(),
                    }
                    .measure(&mesh, x);
                    if v == 0.0 || !v.is_finite() {
                        return Err(Error::bad(format!(
                            "{label}: the mesh {} encloses no volume",
                            mesh_path.display()
                        )));
                    }
                    volume = Some(v);
                    (Selection::Whole, v.signum())
                }
            };
            let mut c = Constraint {
                kind,
                name: d
                    .name
                    .clone()
                    .unwrap_or_else(|| format!("{kind} {}", i + 1)),
                selection,
                original: 0.0,
                target: 0.0,
                orientation,
                skip: skip.clone(),
            };
            // `measure` is the orientation times the same sum: the same bits.
            c.original = match volume {
                Some(v) => c.orientation * v,
                None => c.measure(&mesh, x),
            };
            if c.original.is_nan() || c.original <= 0.0 || !c.original.is_finite() {
                return Err(Error::bad(format!(
                    "{label}: the {kind} measures {} on the input mesh",
                    c.original
                )));
            }
            c.target = match d.target {
                Target::Keep => c.original,
                Target::Scale(s) => s * c.original,
                Target::Value(v) => v,
            };
            constraints.push(c);
        }
        let mut targets = Vec::new();
        for (i, h) in handles.iter().enumerate() {
            let what = handle_label(i);
            h.validate(&what).map_err(Error::bad)?;
            let t = DVec3::from_array(h.translate);
            for v in build_handle_vertices(&h.region, &mesh, &what)? {
                targets.push(HandleTarget {
                    vertex: v,
                    target: x[v as usize] + t,
                });
            }
        }
        let mut regions = Vec::new();
        for (i, c) in curvature.iter().enumerate() {
            let what = curvature_label(i);
            c.validate(&what).map_err(Error::bad)?;
            let region = build_region(&c.region, &mesh, &what)?;
            regions.push(CurvatureRegion {
                vertices: region.vertices(&mesh),
                scale: c.scale,
            });
        }
        log::debug!(
            "{}: topology {:.3} s, checks {:.3} s, demands, handles and regions {:.3} s",
            mesh_path.display(),
            (t1 - t0).as_secs_f64(),
            (t2 - t1).as_secs_f64(),
            t2.elapsed().as_secs_f64()
        );
        Ok(Problem {
            mesh_path,
            mesh,
            topo,
            constraints,
            handles: targets,
            curvature: regions,
            warnings: check.warnings.clone(),
            check,
        })
    }
}

/// Largest relative metric error.
pub fn max_error(p: &Problem, x: &[DVec3]) -> f64 {
    residuals(p, x).iter().fold(0.0, |m, r| m.max(r.abs()))
}

/// Each constraint's relative residual at `x`, the constraints measured at
/// once on rayon's threads (a volume or a whole-mesh area walks every
/// face: 0.04-0.1 s at homer 4.3M).
pub fn residuals(p: &Problem, x: &[DVec3]) -> Vec<f64> {
    use rayon::prelude::*;
    p.constraints
        .par_iter()
        .map(|c| c.residual(&p.mesh, x))
        .collect()
}
