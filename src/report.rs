//! The JSON report of the contract and the table printed on stdout.

use crate::memory::peak_memory_mb;
use crate::mesh::Mesh;
use crate::metrics::MetricKind;
use crate::metrics::Selection;
use crate::pipeline::Outcome;
use crate::problem::Problem;
use glam::DVec3;
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct MeshInfo {
    pub path: String,
    pub vertices: usize,
    pub faces: usize,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct ConstraintReport {
    pub kind: String,
    pub name: String,
    pub original: f64,
    pub target: f64,
    pub result: f64,
    pub error_percent: f64,
    pub met: bool,
    /// Region: how many faces of the input mesh it selects.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub faces: Option<usize>,
    /// Region: its area on the input mesh.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub area: Option<f64>,
    /// Region: the bounding box of its faces' vertices on the input mesh.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bbox: Option<BoundingBox>,
    /// Curve: points of the polyline ([`crate::selection::SurfaceCurve::num_points`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub points: Option<usize>,
    /// Plane curve: connected pieces the plane cut from the input mesh.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub loops: Option<usize>,
    /// Plane curve: the chosen piece, numbered from 1 by the smallest index of
    /// the faces each piece crosses ([`crate::selection::PlaneCut`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub chosen_loop: Option<usize>,
}

/// An axis-aligned box `{ "min": [x, y, z], "max": [x, y, z] }`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BoundingBox {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

#[derive(Debug, Clone, Serialize)]
pub struct Iterations {
    pub scale_driven: usize,
    pub fine_tune: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct Seconds {
    pub total: f64,
    pub load: f64,
    pub scale_driven: f64,
    pub fine_tune: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Distortion {
    pub quasi_conformal_mean: f64,
    pub quasi_conformal_max: f64,
}

pub use crate::distortion::DisplacementStats;

/// Preconditioner set-ups per system kind (numeric factorizations on the
/// CPU, AMG hierarchy builds on the GPU).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PreconditionerSetups {
    pub scale_factors: usize,
    pub scale_driven: usize,
    pub fine_tune: usize,
}

/// The report's `solver` section: the linear solvers' work split.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SolverWork {
    pub preconditioner_setups: PreconditionerSetups,
    /// Most iterations of any one solve (0 where every solve was direct).
    pub pcg_iterations_max: usize,
    /// Seconds of the deformation (scale-driven phase and fine-tune) not
    /// spent waiting for the GPU.
    pub host_seconds: f64,
    /// Seconds the GPU spent in the PCG's passes, by timestamp queries where
    /// the adapter has them, else the seconds the host waited for the GPU (0
    /// on the CPU backend).
    pub gpu_seconds: f64,
    /// How `gpu_seconds` was measured: "timestamps", "host waits" or "none".
    pub gpu_seconds_from: &'static str,
    /// Bytes moved between host and GPU, both ways.
    pub transfer_bytes: u64,
}

impl SolverWork {
    pub fn of(o: &Outcome) -> SolverWork {
        let w = &o.solver;
        let waits = w.device_seconds();
        let (gpu, from) = match w.device_timed_seconds() {
            Some(t) => (t, "timestamps"),
            None if waits > 0.0 => (waits, "host waits"),
            None => (0.0, "none"),
        };
        SolverWork {
            preconditioner_setups: PreconditionerSetups {
                scale_factors: w.scale_factors.preconditioner_setups,
                scale_driven: w.scale_driven.preconditioner_setups,
                fine_tune: w.fine_tune.preconditioner_setups,
            },
            pcg_iterations_max: w.iterations_max(),
            host_seconds: (o.seconds_scale_driven + o.seconds_fine_tune - waits).max(0.0),
            gpu_seconds: gpu,
            gpu_seconds_from: from,
            transfer_bytes: w.transfer_bytes(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub mesh: MeshInfo,
    pub output: Option<String>,
    pub backend: String,
    pub adapter: Option<String>,
    pub constraints: Vec<ConstraintReport>,
    pub satisfied: bool,
    pub iterations: Iterations,
    pub seconds: Seconds,
    pub distortion: Distortion,
    /// How far the vertices moved, in % of the input's bbox diagonal (zero for
    /// `measure`).
    pub displacement: DisplacementStats,
    /// `--preview N`: the scale-driven phase was cut after N iterations and the
    /// fine-tune skipped; constraints are not expected to be met.
    pub preview: bool,
    /// What the input check handled rather than refused (zero-area, needle
    /// or duplicate faces, ...), one line each.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Why some constraint was missed (exit 3), when known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Peak resident memory of the process, MiB (Linux; 0 elsewhere).
    pub peak_memory_mb: f64,
    /// The linear solvers' work (deform only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solver: Option<SolverWork>,
}

/// What a report says about the run beyond the problem and its result.
#[derive(Debug, Clone, Default)]
pub struct RunInfo {
    /// The output mesh's path, if one is written.
    pub output: Option<String>,
    /// The backend's name (`cpu`, `gpu`, ...; `none` for a measurement).
    pub backend: String,
    /// The GPU adapter in use.
    pub adapter: Option<String>,
    /// Seconds from the start of the run to the problem's being built.
    pub load_seconds: f64,
    /// Seconds of the whole run.
    pub total_seconds: f64,
    /// `--preview N` cut the run.
    pub preview: bool,
}

impl Report {
    /// The report of a deformation: the metrics of `x` (the positions written:
    /// the result, or its f32 rounding for STL), the distortion
    /// (`face_distortion`: [`crate::distortion::face_distortions`] of `x`) and
    /// displacement from the input, the solvers' work.
    pub fn of_deformation(
        p: &Problem,
        tolerance: f64,
        outcome: &Outcome,
        x: &[DVec3],
        face_distortion: &[f64],
        run: RunInfo,
    ) -> Report {
        let input = &p.mesh.positions;
        let rows = constraint_rows(p, x, tolerance);
        let satisfied = rows.iter().all(|r| r.met);
        let reason = if satisfied || run.preview {
            None
        } else {
            explain_miss(p, &rows, Some(outcome))
        };
        let (qc_mean, qc_max) =
            crate::distortion::distortion_summary(&p.mesh, input, face_distortion);
        Report {
            mesh: MeshInfo::of(p),
            output: run.output,
            backend: run.backend,
            adapter: run.adapter,
            constraints: rows,
            satisfied,
            iterations: Iterations {
                scale_driven: outcome.scale_driven_iterations,
                fine_tune: outcome.fine_tune_iterations,
            },
            seconds: Seconds {
                total: run.total_seconds,
                load: run.load_seconds,
                scale_driven: outcome.seconds_scale_driven,
                fine_tune: outcome.seconds_fine_tune,
            },
            distortion: Distortion {
                quasi_conformal_mean: qc_mean,
                quasi_conformal_max: qc_max,
            },
            displacement: crate::distortion::displacement_percent(
                input,
                x,
                p.mesh.bbox_diagonal(input),
            ),
            preview: run.preview,
            warnings: p.warnings.clone(),
            reason,
            peak_memory_mb: peak_memory_mb(),
            solver: Some(SolverWork::of(outcome)),
        }
    }

    /// The report of a measurement: the input's metrics, nothing moved.
    pub fn of_measurement(p: &Problem, tolerance: f64, run: RunInfo) -> Report {
        let rows = constraint_rows(p, &p.mesh.positions, tolerance);
        Report {
            mesh: MeshInfo::of(p),
            output: None,
            backend: run.backend,
            adapter: None,
            satisfied: rows.iter().all(|r| r.met),
            constraints: rows,
            iterations: Iterations {
                scale_driven: 0,
                fine_tune: 0,
            },
            seconds: Seconds {
                total: run.total_seconds,
                load: run.load_seconds,
                scale_driven: 0.0,
                fine_tune: 0.0,
            },
            distortion: Distortion {
                quasi_conformal_mean: 1.0,
                quasi_conformal_max: 1.0,
            },
            displacement: DisplacementStats::default(),
            preview: false,
            warnings: p.warnings.clone(),
            reason: None,
            peak_memory_mb: peak_memory_mb(),
            solver: None,
        }
    }
}

impl MeshInfo {
    fn of(p: &Problem) -> MeshInfo {
        MeshInfo {
            path: p.mesh_path.display().to_string(),
            vertices: p.mesh.num_vertices(),
            faces: p.mesh.num_faces(),
        }
    }
}

/// Metric rows for positions `x` (the result, or the input for `measure`), with
/// each constraint's selection facts measured on the input mesh.
pub fn constraint_rows(p: &Problem, x: &[DVec3], tolerance: f64) -> Vec<ConstraintReport> {
    p.constraints
        .iter()
        .map(|c| {
            let result = c.measure(&p.mesh, x);
            let rel = (result - c.target).abs() / c.target.abs();
            let mut row = ConstraintReport {
                kind: c.kind.to_string(),
                name: c.name.clone(),
                original: c.original,
                target: c.target,
                result,
                error_percent: rel * 100.0,
                met: rel <= tolerance,
                ..ConstraintReport::default()
            };
            let input = &p.mesh.positions;
            match &c.selection {
                Selection::Region(r) => {
                    row.faces = Some(r.faces.len());
                    row.area = Some(r.area(&p.mesh, input));
                    row.bbox = region_bbox(&p.mesh, input, &r.faces);
                }
                Selection::Curve(curve) => {
                    row.points = Some(curve.num_points());
                    if let Some(cut) = curve.plane_cut {
                        row.loops = Some(cut.loops);
                        row.chosen_loop = Some(cut.chosen);
                    }
                }
                Selection::Whole => {}
            }
            row
        })
        .collect()
}

/// Bounding box of the vertices of `faces` at positions `x`; None when empty.
fn region_bbox(mesh: &Mesh, x: &[DVec3], faces: &[u32]) -> Option<BoundingBox> {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for &f in faces {
        for v in mesh.faces[f as usize] {
            lo = lo.min(x[v as usize]);
            hi = hi.max(x[v as usize]);
        }
    }
    (lo.x <= hi.x).then(|| BoundingBox {
        min: lo.to_array(),
        max: hi.to_array(),
    })
}

/// A plain explanation for missed constraints, when one is known.
pub fn explain_miss(
    p: &Problem,
    rows: &[ConstraintReport],
    outcome: Option<&Outcome>,
) -> Option<String> {
    let missed: Vec<String> = rows
        .iter()
        .filter(|r| !r.met)
        .map(|r| format!("{} '{}' off by {:.4} %", r.kind, r.name, r.error_percent))
        .collect();
    if missed.is_empty() {
        return None;
    }
    let mut why = format!("missed: {}", missed.join(", "));
    // Isoperimetric bound: 36 pi V^2 <= A^3 for any closed surface.
    let total_area = p.constraints.iter().find(|c| {
        c.kind == MetricKind::Area
            && matches!(&c.selection, Selection::Region(r) if r.faces.len() == p.mesh.num_faces())
    });
    let volume = p.constraints.iter().find(|c| c.kind == MetricKind::Volume);
    if let (Some(a), Some(v)) = (total_area, volume) {
        let bound = (a.target.powi(3) / (36.0 * std::f64::consts::PI)).sqrt();
        if v.target > bound {
            why.push_str(&format!(
                "; contradictory demands: a closed surface of area {:.6} encloses at most {:.6} (a sphere), but the volume target is {:.6}",
                a.target, bound, v.target
            ));
            return Some(why);
        }
    }
    if let Some(o) = outcome {
        why.push_str(&format!(
            "; the demands may be contradictory or infeasible (scale-driven phase stopped on {})",
            o.stop_reason
        ));
    }
    Some(why)
}

/// The stdout table. Names are padded by hand: `format!`'s width is limited
/// to 65,535, and a name may be longer.
pub fn table(rows: &[ConstraintReport]) -> String {
    fn padded(name: &str, width: usize) -> String {
        let n = name.chars().count();
        let mut s = String::with_capacity(name.len() + width.saturating_sub(n));
        s.push_str(name);
        s.extend(std::iter::repeat_n(' ', width.saturating_sub(n)));
        s
    }
    let mut s = String::new();
    let w = rows
        .iter()
        .map(|r| r.name.chars().count())
        .max()
        .unwrap_or(4)
        .max(10);
    s.push_str(&format!(
        "{}  {:<6}  {:>14}  {:>14}  {:>14}  {:>10}  {}\n",
        padded("constraint", w),
        "kind",
        "original",
        "target",
        "result",
        "error %",
        "met"
    ));
    for r in rows {
        s.push_str(&format!(
            "{}  {:<6}  {:>14.6}  {:>14.6}  {:>14.6}  {:>10.6}  {}\n",
            padded(&r.name, w),
            r.kind,
            r.original,
            r.target,
            r.result,
            r.error_percent,
            if r.met { "yes" } else { "NO" }
        ));
    }
    // The selections, one line per constraint that has one, under the table.
    let facts: Vec<String> = rows
        .iter()
        .filter_map(|r| selection_facts(r).map(|f| format!("  {}: {f}\n", r.name)))
        .collect();
    if !facts.is_empty() {
        s.push_str("selections on the input mesh:\n");
        for f in facts {
            s.push_str(&f);
        }
    }
    s
}

/// A row's selection facts in words: `412 faces, area 0.123456, bbox [..] to
/// [..]` for a region, `96 points, piece 2 of 4 cut by the plane` for a curve;
/// None for a volume.
pub fn selection_facts(r: &ConstraintReport) -> Option<String> {
    let v = |p: [f64; 3]| format!("[{:.4}, {:.4}, {:.4}]", p[0], p[1], p[2]);
    if let Some(faces) = r.faces {
        let mut s = format!("region of {faces} faces");
        if let Some(a) = r.area {
            s.push_str(&format!(", area {a:.6}"));
        }
        if let Some(b) = &r.bbox {
            s.push_str(&format!(", bbox {} to {}", v(b.min), v(b.max)));
        }
        return Some(s);
    }
    let points = r.points?;
    let mut s = format!("curve of {points} points");
    if let (Some(loops), Some(chosen)) = (r.loops, r.chosen_loop) {
        s.push_str(&format!(
            ", the plane cut {loops} loop{}, this is loop {chosen}",
            if loops == 1 { "" } else { "s" }
        ));
    }
    Some(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(name: &str) -> ConstraintReport {
        ConstraintReport {
            kind: "length".into(),
            name: name.into(),
            original: 1.0,
            target: 1.2,
            result: 1.2,
            error_percent: 0.0,
            met: true,
            ..ConstraintReport::default()
        }
    }

    /// A name of 70,000 characters (past `format!`'s width limit of 65,535)
    /// gives a table, not a panic; columns stay aligned.
    #[test]
    fn table_takes_names_longer_than_format_widths() {
        let long = "n".repeat(70_000);
        let t = table(&[row(&long), row("short")]);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 3);
        assert!(lines[1].starts_with(&long));
        let col = |l: &str| l.find("length").unwrap_or(0);
        assert_eq!(col(lines[1]), col(lines[2]));
        assert_eq!(col(lines[1]), 70_002);
    }

    /// Selection facts go on lines of their own under the table, one per
    /// constraint that has a selection (none for a volume), and in the JSON
    /// only where they apply.
    #[test]
    fn selection_facts_are_listed_under_the_table() {
        let mut girth = row("girth");
        girth.points = Some(130);
        girth.loops = Some(4);
        girth.chosen_loop = Some(2);
        let mut head = row("head");
        head.kind = "area".into();
        head.faces = Some(870);
        head.area = Some(0.5953);
        head.bbox = Some(BoundingBox {
            min: [-1.0, 0.0, 0.5],
            max: [1.0, 2.0, 0.75],
        });
        let mut volume = row("volume");
        volume.kind = "volume".into();
        let t = table(&[girth.clone(), head.clone(), volume.clone()]);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4 + 1 + 2, "{t}");
        assert_eq!(lines[4], "selections on the input mesh:");
        assert!(
            lines[5].starts_with("  girth: ")
                && lines[5].contains("130 points")
                && lines[5].contains("4 loops")
                && lines[5].contains("loop 2"),
            "{t}"
        );
        assert!(
            lines[6].starts_with("  head: ")
                && lines[6].contains("870 faces")
                && lines[6].contains("area 0.595300")
                && lines[6].contains("[-1.0000, 0.0000, 0.5000] to [1.0000, 2.0000, 0.7500]"),
            "{t}"
        );
        let json = |r: &ConstraintReport| serde_json::to_value(r).unwrap();
        let (g, h, v) = (json(&girth), json(&head), json(&volume));
        assert_eq!(g["loops"], 4);
        assert_eq!(g["chosen_loop"], 2);
        assert!(g.get("faces").is_none() && g.get("bbox").is_none());
        assert_eq!(h["faces"], 870);
        assert_eq!(h["bbox"]["max"][2], 0.75);
        assert!(h.get("points").is_none() && h.get("loops").is_none());
        for k in ["faces", "area", "bbox", "points", "loops", "chosen_loop"] {
            assert!(v.get(k).is_none(), "{k}: {v}");
        }
    }
}
