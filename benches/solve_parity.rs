//! How exactly the GPU backend solves, against the CPU's sparse Cholesky, on
//! the first outer iteration of the `girths-homer` rows of the pipeline bench:
//!
//! - the scale factors of Eq. 3 (sequential constrained Newton steps, each a
//!   Schur-complement solve of `k + 1` right-hand sides): the largest and the
//!   RMS relative difference of the scale factors;
//! - the shape solve of Eq. 7 for those scale factors (the GPU at the
//!   scale-driven tolerance, with the preconditioner the pipeline gives it):
//!   how far each vertex lands from the Cholesky solution, as % of the bbox
//!   diagonal (largest, 99th percentile, RMS), and how many vertices are
//!   within a factor 2 of the largest (a few: the error sits on a few
//!   vertices; many: it is spread).
//!
//! - with `--fine-tune`: the fine-tune (Eq. 8) from the CPU backend's
//!   scale-driven result on the CPU's block PCG (at its tolerance and the
//!   GPU's), on the GPU, and on the CPU's PCG from that start moved a little,
//!   each against the direct solver's fine-tune.
//!
//! `cargo bench --bench solve_parity -- ROW [--shape] [--fine-tune]` with ROW
//! `girths-homer-100k` (default) or `girths-homer-1m` (homer, every edge cut
//! in 3 or 10); `--shape` adds the shape solve. Any adapter: on lavapipe the
//! seconds are not GPU seconds, but the differences are the GPU solver's own.

#[path = "../tests/common/mod.rs"]
mod common;

use glam::DVec3;
use metricdeform::job::{Job, JobFormat};
use metricdeform::pipeline::{Options, GPU_TOLERANCE, SCALE_DRIVEN_TOLERANCE};
use metricdeform::problem::Problem;
use metricdeform::scale_factors::{ScaleConstraint, ScaleFactorSystem};
use metricdeform::shape::vertex_mean_scale;
use metricdeform::shape::ShapeModel;
use solver_cpu::{CholeskySolver, SpdSolver, SystemKind};
use std::path::Path;
use std::time::Instant;

fn gpu(kind: SystemKind, tolerance: f64) -> Box<dyn SpdSolver> {
    let mut s = solver_gpu::open().expect("a GPU adapter (lavapipe will do)");
    s.set_tolerance(tolerance);
    s.set_system_kind(kind);
    Box::new(s)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let row = args
        .iter()
        .find(|a| a.starts_with("girths-"))
        .cloned()
        .unwrap_or_else(|| "girths-homer-100k".into());
    let cut = match row.as_str() {
        "girths-homer-100k" => 3,
        "girths-homer-1m" => 10,
        other => panic!("unknown row {other}: girths-homer-100k or girths-homer-1m"),
    };
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let job = Job::from_str(common::GIRTHS_HOMER, JobFormat::Toml, &dir, &row).unwrap();
    let o = Options::from_spec(&job.spec.solver);
    let mesh = metricdeform::mesh::io::read_mesh(&job.mesh_path())
        .unwrap()
        .subdivide_uniform(cut);
    let p = Problem::build(&job, mesh, &job.mesh_path()).unwrap();
    let mesh = &p.mesh;
    let x = &mesh.positions;
    println!(
        "adapter: {}",
        solver_gpu::default_adapter().map_or("none".into(), |a| a.name)
    );

    // Eq. 3.
    let areas = mesh.face_areas(x);
    let constraints: Vec<ScaleConstraint> = p
        .constraints
        .iter()
        .enumerate()
        .map(|(i, c)| ScaleConstraint {
            coeffs: c.face_coefficients(mesh, x, &areas, o.volume_share),
            degree: c.degree(),
            target: c.target,
            group: i,
        })
        .collect();
    let estimate = |solver: Box<dyn SpdSolver>| {
        let t0 = Instant::now();
        let mut sys = ScaleFactorSystem::with_solver(
            &p.topo.face_pairs,
            &areas,
            o.k_d,
            o.k_r,
            o.regulariser,
            solver,
        )
        .unwrap();
        let (s, info) = sys.estimate(&constraints, o.multipliers).unwrap();
        (s, info, t0.elapsed().as_secs_f64())
    };
    let (s_cpu, cpu_info, cpu_s) = estimate(Box::new(CholeskySolver::new()));
    let (s_gpu, gpu_info, gpu_s) = estimate(gpu(SystemKind::ScaleFactors, GPU_TOLERANCE));
    let rel: Vec<f64> = s_cpu
        .iter()
        .zip(&s_gpu)
        .map(|(a, b)| (a - b).abs() / a.abs())
        .collect();
    let worst = rel.iter().cloned().fold(0.0, f64::max);
    let rms = (rel.iter().map(|d| d * d).sum::<f64>() / rel.len() as f64).sqrt();
    println!(
        "{row}: {} faces; scale factors GPU vs Cholesky: largest relative difference {worst:.2e}, RMS {rms:.2e}; \
         Newton steps {} (GPU) and {} (CPU); constraint residual {:.1e} and {:.1e}; {gpu_s:.1} s and {cpu_s:.1} s",
        s_cpu.len(),
        gpu_info.newton_iterations,
        cpu_info.newton_iterations,
        gpu_info.max_residual,
        cpu_info.max_residual,
    );
    if args.iter().any(|a| a == "--fine-tune") {
        fine_tune_parity(&row, &p, &job);
    }
    if !args.iter().any(|a| a == "--shape") {
        return;
    }

    // Eq. 7 for the Cholesky scale factors, with the curvature targets the
    // pipeline gives the first step (area-weighted mean scale factor per vertex).
    let n = mesh.num_vertices();
    let c = vertex_mean_scale(mesh, &areas, &s_cpu);
    let shape_solve = |solver: Box<dyn SpdSolver>| -> (Vec<DVec3>, f64) {
        let t0 = Instant::now();
        let mut model = ShapeModel::with_solver(mesh, &p.topo, p.handles.clone(), solver).unwrap();
        model
            .assemble_and_factor(mesh, x, &s_cpu, &c, &o.shape)
            .unwrap();
        let y = model.solve_unconstrained(x).unwrap();
        (y, t0.elapsed().as_secs_f64())
    };
    let (y_cpu, cpu_s) = shape_solve(Box::new(CholeskySolver::new()));
    let (y_gpu, gpu_s) = shape_solve(gpu(SystemKind::ScaleDriven, SCALE_DRIVEN_TOLERANCE));
    let diag = mesh.bbox_diagonal(x);
    let mut d: Vec<f64> = y_cpu
        .iter()
        .zip(&y_gpu)
        .map(|(a, b)| 100.0 * (*a - *b).length() / diag)
        .collect();
    let moved = y_cpu
        .iter()
        .zip(x)
        .map(|(a, b)| 100.0 * (*a - *b).length() / diag)
        .fold(0.0, f64::max);
    d.sort_by(f64::total_cmp);
    let max = *d.last().unwrap();
    let p99 = d[((0.99 * d.len() as f64).ceil() as usize).clamp(1, d.len()) - 1];
    let rms = (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt();
    let near_max = d.iter().filter(|&&v| v >= 0.5 * max).count();
    println!(
        "{row}: {n} vertices; first shape solve (Eq. 7), GPU vs Cholesky, % of the bbox diagonal: \
         largest {max:.2e}, p99 {p99:.2e}, RMS {rms:.2e}; {near_max} vertices within a factor 2 of the largest; \
         the step itself moves vertices up to {moved:.2e}; {gpu_s:.1} s and {cpu_s:.1} s"
    );
}

/// Where the backends' final results part: the fine-tune (Eq. 8) from one
/// scale-driven result (the CPU backend's), on the CPU's block PCG, the
/// direct Cholesky solver and the GPU; and on the CPU's PCG from that start
/// moved by a smooth field of `1e-8` of the bbox diagonal. Distances in % of
/// the bbox diagonal against the direct solver's fine-tune.
fn fine_tune_parity(row: &str, p: &Problem, job: &Job) {
    use metricdeform::fine_tune::{fine_tune, FineTuneParams};
    use metricdeform::pipeline::{deform, SolverBackend, CPU_TOLERANCE};
    use solver_cpu::BlockPcgSolver;
    let mesh = &p.mesh;
    let mut o = Options::from_spec(&job.spec.solver);
    let params = FineTuneParams {
        weights: o.fine_tune,
        tolerance: o.tolerance,
        max_iterations: o.fine_tune_iterations,
        multipliers: o.multipliers,
    };
    o.fine_tune_iterations = 0;
    o.backend = SolverBackend::Cpu;
    let start = deform(p, &o, &mut |_| {}).unwrap().positions;
    let groups: Vec<usize> = (0..p.constraints.len()).collect();
    let diag = mesh.bbox_diagonal(&mesh.positions);
    let run = |solver: Box<dyn SpdSolver>, tol: f64, x: &[DVec3]| {
        let t0 = Instant::now();
        let mut model = ShapeModel::with_solver(mesh, &p.topo, p.handles.clone(), solver).unwrap();
        model.solver().set_tolerance(tol);
        let (y, steps) = fine_tune(p, &params, &mut model, &groups, x, &mut |_, _| Ok(())).unwrap();
        (y, steps, t0.elapsed().as_secs_f64())
    };
    let dist = |a: &[DVec3], b: &[DVec3]| {
        a.iter()
            .zip(b)
            .map(|(u, v)| 100.0 * (*u - *v).length() / diag)
            .fold(0.0, f64::max)
    };
    if std::env::var("PROBE_GPU_ONLY").is_ok() {
        let _ = run(
            gpu(SystemKind::FineTune, GPU_TOLERANCE),
            GPU_TOLERANCE,
            &start,
        );
        return;
    }
    let (direct, steps_d, sd) = run(Box::new(CholeskySolver::new()), CPU_TOLERANCE, &start);
    let (pcg, steps_c, sc) = run(Box::new(BlockPcgSolver::new()), CPU_TOLERANCE, &start);
    let (pcg8, _, _) = run(Box::new(BlockPcgSolver::new()), GPU_TOLERANCE, &start);
    let moved: Vec<DVec3> = start
        .iter()
        .map(|v| {
            *v + 1e-8 * diag * DVec3::new((v.y * 7.0).sin(), (v.z * 5.0).cos(), (v.x * 3.0).sin())
        })
        .collect();
    let (from_moved, _, _) = run(Box::new(BlockPcgSolver::new()), CPU_TOLERANCE, &moved);
    let (gpu_y, steps_g, sg) = run(
        gpu(SystemKind::FineTune, GPU_TOLERANCE),
        GPU_TOLERANCE,
        &start,
    );
    println!(
        "{row}: fine-tune from the CPU's scale-driven result, largest distance from the direct solver's, \
         % of the bbox diagonal: CPU PCG at {CPU_TOLERANCE:e} {:.2e}, at {GPU_TOLERANCE:e} {:.2e}; GPU {:.2e}; \
         CPU PCG from the start moved by up to {:.1e} %: {:.2e}; steps {steps_d} (direct), {steps_c} (CPU PCG), \
         {steps_g} (GPU); {sd:.1} s, {sc:.1} s, {sg:.1} s; the fine-tune moves vertices up to {:.2e}",
        dist(&pcg, &direct),
        dist(&pcg8, &direct),
        dist(&gpu_y, &direct),
        dist(&moved, &start),
        dist(&from_moved, &direct),
        dist(&direct, &start),
    );
}
