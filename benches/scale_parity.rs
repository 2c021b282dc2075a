//! How exactly the GPU backend solves the scale factors of Eq. 3: the first
//! outer iteration's estimate (sequential constrained Newton steps, each a
//! Schur-complement solve of `k + 1` right-hand sides) with the GPU solver at
//! the backend's tolerance, against the same estimate with the CPU's sparse
//! Cholesky. Prints the largest and the RMS relative difference of the scale
//! factors, and each one's Newton steps.
//!
//! `cargo bench --bench scale_parity -- ROW` with ROW `girths-homer-100k`
//! (default) or `girths-homer-1m` (homer, every edge cut in 3 or 10).
//! Any adapter: on lavapipe the seconds are not GPU seconds, but the
//! difference is the GPU solver's own.

#[path = "../tests/common/mod.rs"]
mod common;

use metricdeform::deform::{Problem, GPU_TOLERANCE};
use metricdeform::job::{Job, JobFormat};
use metricdeform::metrics::VolumeShare;
use metricdeform::scale_factors::{Regulariser, ScaleConstraint, ScaleFactorSystem};
use metricdeform::schur::Multipliers;
use solver_cpu::{SpdSolver, SystemKind};
use std::path::Path;
use std::time::Instant;

fn main() {
    let row = std::env::args()
        .skip(1)
        .find(|a| a.starts_with("girths-"))
        .unwrap_or_else(|| "girths-homer-100k".into());
    let cut = match row.as_str() {
        "girths-homer-100k" => 3,
        "girths-homer-1m" => 10,
        other => panic!("unknown row {other}: girths-homer-100k or girths-homer-1m"),
    };
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let job = Job::from_str(common::GIRTHS_HOMER, JobFormat::Toml, &dir, &row).unwrap();
    let mesh = metricdeform::io::read_mesh(&job.mesh_path())
        .unwrap()
        .subdivide_uniform(cut);
    let p = Problem::build(&job, mesh, &job.mesh_path()).unwrap();
    let x = &p.mesh.positions;
    let areas = p.mesh.face_areas(x);
    let constraints: Vec<ScaleConstraint> = p
        .constraints
        .iter()
        .enumerate()
        .map(|(i, c)| ScaleConstraint {
            coeffs: c.face_coefficients(&p.mesh, x, &areas, VolumeShare::Area),
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
            1.0,
            0.01,
            Regulariser::Area,
            solver,
        )
        .unwrap();
        let (s, info) = sys
            .estimate(&constraints, Multipliers::PerConstraint)
            .unwrap();
        (s, info, t0.elapsed().as_secs_f64())
    };
    let (cpu, cpu_info, cpu_s) = estimate(Box::new(solver_cpu::CholeskySolver::new()));
    let mut gpu_solver = solver_gpu::open().expect("a GPU adapter (lavapipe will do)");
    println!("adapter: {}", gpu_solver.adapter_name());
    gpu_solver.set_tolerance(GPU_TOLERANCE);
    gpu_solver.set_system_kind(SystemKind::ScaleFactors);
    let (gpu, gpu_info, gpu_s) = estimate(Box::new(gpu_solver));
    let mut worst = 0.0f64;
    let mut sq = 0.0;
    for (a, b) in cpu.iter().zip(&gpu) {
        let d = (a - b).abs() / a.abs();
        worst = worst.max(d);
        sq += d * d;
    }
    let rms = (sq / cpu.len() as f64).sqrt();
    println!(
        "{row}: {} faces; scale factors GPU vs Cholesky: largest relative difference {worst:.2e}, RMS {rms:.2e}; \
         Newton steps {} (GPU) and {} (CPU); constraint residual {:.1e} and {:.1e}; {gpu_s:.1} s and {cpu_s:.1} s",
        cpu.len(),
        gpu_info.newton_iterations,
        cpu_info.newton_iterations,
        gpu_info.max_residual,
        cpu_info.max_residual,
    );
}
