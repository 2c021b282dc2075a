//! The pipeline's host steps between the solves, one at a time, on
//! `girths-homer` at a pipeline row's size: what each outer iteration and
//! each fine-tune step does on the host besides solving (the shape
//! matrix's assembly as each backend has it made, and the once-a-run
//! set-ups that run beside each other at the start: the scale factors'
//! matrix and fill ordering, the shape pattern, the shape model's
//! Laplacians).
//!
//! `cargo bench --bench host_steps -- [100k|1m|4m]` (default `1m`); run it
//! with `RAYON_NUM_THREADS=1` beside the default to see what rayon's
//! threads give. Each step runs 5 times on the same inputs; the table gives
//! the fastest and the median. The steps' results are the same bits on
//! any number of threads (the unit tests of `ordered`, `shape`,
//! `anderson` and `constrained_step`).

#[path = "../tests/common/mod.rs"]
mod common;

use glam::DVec3;
use metricdeform::anderson::Anderson;
use metricdeform::constrained_step::step_from_solutions;
use metricdeform::job::{Job, JobFormat};
use metricdeform::metrics::VolumeShare;
use metricdeform::problem::{max_error, Problem};
use metricdeform::scale_factors::{Regulariser, ScaleFactorSystem};
use metricdeform::shape::{CurvatureTarget, ShapeModel};
use std::path::Path;
use std::time::Instant;

/// The fastest and the median of 5 runs of `step`, in seconds (what it
/// returns dropped after its time).
fn timed<T>(mut step: impl FnMut() -> T) -> (f64, f64) {
    let mut seconds: Vec<f64> = (0..5)
        .map(|_| {
            let t = Instant::now();
            let made = std::hint::black_box(step());
            let seconds = t.elapsed().as_secs_f64();
            drop(made);
            seconds
        })
        .collect();
    seconds.sort_by(f64::total_cmp);
    (seconds[0], seconds[2])
}

fn main() {
    metricdeform::memory::keep_freed_memory();
    let size = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .unwrap_or_else(|| "1m".into());
    let cuts = match size.as_str() {
        "100k" => 3,
        "1m" => 10,
        "4m" => 19,
        other => panic!("unknown size {other}: 100k, 1m or 4m"),
    };
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let job = Job::from_str(common::GIRTHS_HOMER, JobFormat::Toml, &dir, "girths").unwrap();
    let mesh = metricdeform::mesh::io::read_mesh(&job.mesh_path())
        .unwrap()
        .subdivide_uniform(cuts);
    let p = Problem::build(&job, mesh, &job.mesh_path()).unwrap();
    let mesh = &p.mesh;
    let (n, nf) = (mesh.num_vertices(), mesh.num_faces());
    let _ = env_logger::builder().format_timestamp_millis().try_init();
    let t = Instant::now();
    let model = ShapeModel::new(mesh, &p.topo, Vec::new()).unwrap();
    let model_seconds = t.elapsed().as_secs_f64();
    // Positions moved as an outer iteration moves them, and its images.
    let x: Vec<DVec3> = mesh
        .positions
        .iter()
        .enumerate()
        .map(|(i, q)| *q * (1.0 + 0.01 * ((i % 17) as f64 / 17.0)))
        .collect();
    let image = |k: f64| -> Vec<DVec3> {
        x.iter()
            .enumerate()
            .map(|(i, q)| *q + DVec3::splat(k * 1e-3 * ((i % 5) as f64 - 2.0)))
            .collect()
    };
    let s: Vec<f64> = (0..nf)
        .map(|f| 1.0 + 0.1 * ((f % 11) as f64 / 11.0))
        .collect();
    let threads = rayon::current_num_threads();
    println!("girths-homer-{size}: {nf} faces, {n} vertices, {threads} of rayon's threads");
    println!("shape model set up in {model_seconds:.3} s (once; RUST_LOG=debug for its parts)");
    println!("| step | fastest s | median s |");
    println!("|---|---|---|");
    let row = |name: &str, (fast, median): (f64, f64)| {
        println!("| {name} | {fast:.4} | {median:.4} |");
    };
    let areas = mesh.face_areas(&x);
    row(
        "the scale factors' matrix (set-up, once a run)",
        timed(|| {
            ScaleFactorSystem::hessian(&p.topo.face_pairs, &areas, 1.0, 0.01, Regulariser::Area)
        }),
    );
    let centroids: Vec<DVec3> = (0..nf).map(|f| mesh.centroid(&mesh.positions, f)).collect();
    row(
        "the faces' fill ordering (their centroids' nested dissection, once a run)",
        timed(|| solver_cpu::coordinate_nested_dissection_of_pairs(&centroids, &p.topo.face_pairs)),
    );
    row(
        "the shape pattern from the faces (its ordering thread's, once a run)",
        timed(|| metricdeform::shape::shape_pattern(n, &mesh.faces)),
    );
    let skip = mesh.degenerate_faces(&mesh.positions);
    row(
        "the shape model's two Laplacians (once a run)",
        timed(|| {
            use metricdeform::shape::{cotangent_laplacian_masked, mean_value_laplacian_masked};
            rayon::join(
                || cotangent_laplacian_masked(mesh, &mesh.positions, &skip),
                || mean_value_laplacian_masked(mesh, &mesh.positions, &skip),
            )
        }),
    );
    let w = metricdeform::pipeline::Options::default().shape;
    row(
        "the shape systems' K for a factor made ahead (set-up, once a kind)",
        timed(|| model.isotropic_part(mesh, &mesh.positions, &w)),
    );
    // Each outer iteration's shape matrix as each backend has it assembled
    // (the solver only answers what it wants in `K`; nothing is factored).
    let c = vec![1.0; n];
    for (name, gpu_path) in [
        (
            "the shape matrix as the CPU backend has it (E_m, E_l's isotropic part in K)",
            false,
        ),
        (
            "the shape matrix as the GPU path has it (E_l in the rings, E_m on the GPU)",
            true,
        ),
    ] {
        let solver = Box::new(AssemblyOnly(gpu_path));
        let mut m = ShapeModel::with_solver(mesh, &p.topo, Vec::new(), solver).unwrap();
        row(name, timed(|| m.assemble(mesh, &x, &s, &c, &w).unwrap()));
    }
    row("face areas", timed(|| mesh.face_areas(&x)));
    let mut coeffs: Vec<Vec<(u32, f64)>> = vec![Vec::new(); p.constraints.len()];
    row(
        "the constraints' face coefficients",
        timed(|| {
            use rayon::prelude::*;
            coeffs
                .par_iter_mut()
                .zip(&p.constraints)
                .for_each(|(out, c)| {
                    c.face_coefficients_into(mesh, &x, &areas, VolumeShare::Area, out)
                });
        }),
    );
    row(
        "curvature targets (vertex mean scale)",
        timed(|| {
            metricdeform::shape::curvature_targets(
                &model,
                mesh,
                &areas,
                &s,
                CurvatureTarget::Scaled,
                None,
            )
        }),
    );
    // One step with two columns of history: each run on a copy made
    // outside its time.
    let mut history = Anderson::new(2);
    for k in 0..3 {
        history.step(&image(k as f64), image(k as f64 + 0.5));
    }
    let (x3, g3) = (image(3.0), image(3.5));
    let mut copies: Vec<(Anderson, Vec<DVec3>)> =
        (0..5).map(|_| (history.clone(), g3.clone())).collect();
    row(
        "Anderson step, 2 columns",
        timed(|| {
            let (mut a, g) = copies.pop().unwrap();
            (a.step(&x3, g), a)
        }),
    );
    row("metrics (max error)", timed(|| max_error(&p, &x)));
    row(
        "the constraints' gradient rows",
        timed(|| {
            p.constraints
                .iter()
                .map(|c| {
                    let mut r = vec![0.0; 3 * n];
                    c.add_gradient(mesh, &x, 1.0 / c.target, &mut r);
                    r
                })
                .collect::<Vec<_>>()
        }),
    );
    let k = p.constraints.len();
    let ycols: Vec<f64> = (0..k * 3 * n)
        .map(|i| ((i % 97) as f64 - 48.0) * 1e-3)
        .collect();
    let rows: Vec<Vec<f64>> = (0..k)
        .map(|j| {
            (0..3 * n)
                .map(|i| ((i * (j + 3)) % 89) as f64 * 1e-2)
                .collect()
        })
        .collect();
    let row_refs: Vec<&[f64]> = rows.iter().map(|r| &r[..]).collect();
    let values = vec![1e-3; k];
    row(
        "multipliers and the step from the solutions",
        timed(|| {
            let y: Vec<f64> = (0..3 * n).map(|i| (i % 7) as f64 * 1e-3).collect();
            step_from_solutions(y, &values, &row_refs, &ycols).unwrap()
        }),
    );
}

/// A solver that factors nothing: it answers what each backend wants in
/// the shape matrix, `.0` the GPU path once its preconditioner is made (no
/// isotropic part read apart, E_m's Hessian added on the device).
struct AssemblyOnly(bool);

impl solver_cpu::SpdSolver for AssemblyOnly {
    fn prepare(&mut self, _: &solver_cpu::SymCsc) -> Result<(), solver_cpu::SolverError> {
        Ok(())
    }
    fn prepare_blocks(
        &mut self,
        _: &solver_cpu::BlockSym3,
        _: &[bool],
    ) -> Result<(), solver_cpu::SolverError> {
        Ok(())
    }
    fn wants_isotropic_part(&self) -> bool {
        !self.0
    }
    fn adds_laplacian_square(&self) -> bool {
        self.0
    }
    fn solve_in_place(
        &mut self,
        _: &mut [f64],
        _: usize,
    ) -> Result<solver_cpu::SolveInfo, solver_cpu::SolverError> {
        Err(solver_cpu::SolverError::NotPrepared)
    }
    fn counters(&self) -> solver_cpu::WorkCounters {
        solver_cpu::WorkCounters::default()
    }
    fn name(&self) -> &str {
        "assembly only"
    }
}
