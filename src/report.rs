//! The JSON report of the contract and the table printed on stdout.

use crate::deform::{Outcome, Problem};
use crate::job::MetricKind;
use crate::metrics::Selection;
use glam::DVec3;
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct MeshInfo {
    pub path: String,
    pub vertices: usize,
    pub faces: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct ConstraintReport {
    pub kind: String,
    pub name: String,
    pub original: f64,
    pub target: f64,
    pub result: f64,
    pub error_percent: f64,
    pub met: bool,
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

/// Metric rows for positions `x` (the result, or the input for `measure`).
pub fn constraint_rows(p: &Problem, x: &[DVec3], tolerance: f64) -> Vec<ConstraintReport> {
    p.constraints
        .iter()
        .map(|c| {
            let result = c.measure(&p.mesh, x);
            let rel = (result - c.target).abs() / c.target.abs();
            ConstraintReport {
                kind: c.kind.to_string(),
                name: c.name.clone(),
                original: c.original,
                target: c.target,
                result,
                error_percent: rel * 100.0,
                met: rel <= tolerance,
            }
        })
        .collect()
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

/// Peak resident set size of this process in MiB (VmHWM), 0 when unknown.
pub fn peak_memory_mb() -> f64 {
    proc_status_mb("VmHWM:")
}

/// Current resident set size of this process in MiB (VmRSS), 0 when unknown.
pub fn resident_memory_mb() -> f64 {
    proc_status_mb("VmRSS:")
}

/// Hands the allocator's free memory back to the system (glibc keeps freed
/// blocks of its per-thread arenas resident; a large set-up step leaves hundreds
/// of MiB of them at a million faces). A no-op elsewhere.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn malloc_trim(pad: usize) -> std::ffi::c_int;
        }
        // SAFETY: malloc_trim only returns free pages of glibc's own arenas.
        unsafe {
            malloc_trim(0);
        }
    }
}

fn proc_status_mb(field: &str) -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with(field)).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|kb| kb.parse::<f64>().ok())
                    .map(|kb| kb / 1024.0)
            })
        })
        .unwrap_or(0.0)
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
    s
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
}
