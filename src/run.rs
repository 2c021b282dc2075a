//! A whole run in memory: a [`Problem`] deformed by the pipeline and reported
//! on, with no file read or written (the CLI adds the files around it).

use crate::pipeline::{deform as run_pipeline, Options, Progress, SolverBackend};
use crate::problem::Problem;
use crate::report::{Report, RunInfo};
use crate::Result;
use glam::DVec3;
use std::time::Instant;

/// What [`deform`] produces.
#[derive(Debug, Clone)]
pub struct Deformation {
    /// The deformed vertex positions, in the input's vertex order.
    pub positions: Vec<DVec3>,
    /// Per face, `sqrt(area out / area in)`: the scale factor `s` of Eq. 3
    /// the result realises.
    pub face_scale: Vec<f64>,
    /// Per face, the quasi-conformal distortion of the map from input to
    /// result (1 for a similarity).
    pub face_distortion: Vec<f64>,
    /// The metrics, iterations, timings and solver work, as in the JSON report
    /// (`report.constraints[i]` is demand `i`; `report.satisfied` says whether
    /// every target was met within the tolerance).
    pub report: Report,
}

/// Deform `problem` with `options`: the scale-driven iteration (Eqs. 3 and 7)
/// and the fine-tune (Eq. 8), then the report. A target that cannot be met is
/// not an error: `report.satisfied` is false and `report.reason` says why.
pub fn deform(problem: &Problem, options: &Options) -> Result<Deformation> {
    deform_with_progress(problem, options, &mut |_| {})
}

/// [`deform`], calling `progress` at every outer and fine-tune iteration.
pub fn deform_with_progress(
    problem: &Problem,
    options: &Options,
    progress: &mut dyn FnMut(Progress),
) -> Result<Deformation> {
    let t0 = Instant::now();
    let outcome = run_pipeline(problem, options, progress)?;
    let input = &problem.mesh.positions;
    let face_distortion =
        crate::distortion::face_distortions(&problem.mesh, input, &outcome.positions);
    let adapter = match options.backend {
        SolverBackend::Gpu => solver_gpu::default_adapter().ok().map(|a| a.name),
        _ => None,
    };
    let report = Report::of_deformation(
        problem,
        options.tolerance,
        &outcome,
        &outcome.positions,
        &face_distortion,
        RunInfo {
            output: None,
            backend: options.backend.name().to_string(),
            adapter,
            load_seconds: 0.0,
            total_seconds: t0.elapsed().as_secs_f64(),
            preview: options.preview.is_some(),
        },
    );
    Ok(Deformation {
        face_distortion,
        face_scale: outcome.face_scale,
        positions: outcome.positions,
        report,
    })
}

/// The input's metrics for every demand of `problem` (nothing is moved);
/// `tolerance` decides each row's `met`.
pub fn measure(problem: &Problem, tolerance: f64) -> Report {
    Report::of_measurement(
        problem,
        tolerance,
        RunInfo {
            backend: "none".into(),
            ..RunInfo::default()
        },
    )
}
