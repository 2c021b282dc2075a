//! The linear solvers' work, counted (not timed): preconditioner set-ups per
//! system kind, host-device traffic per outer iteration, and `--backend auto`'s
//! crossover. These are the counts that predict a discrete GPU's cost (host
//! set-up and transfers), checked on any adapter, lavapipe included.
//!
//! GPU tests need a wgpu adapter (lavapipe is enough). Without one they skip with
//! a message on stderr; with `REQUIRE_GPU=1` they fail instead.

mod common;

use common::*;
use metricdeform::pipeline::{
    auto_uses_gpu, deform, Options, SolverBackend, GPU_FASTER_FROM_FACES,
};
use metricdeform::problem::Problem;

fn gpu_available() -> bool {
    if solver_gpu::gpu_available() {
        return true;
    }
    if std::env::var("REQUIRE_GPU").is_ok_and(|v| v == "1") {
        panic!("REQUIRE_GPU=1 but no GPU adapter is available (install mesa-vulkan-drivers for lavapipe)");
    }
    eprintln!("skipping GPU test: no GPU adapter (set REQUIRE_GPU=1 to fail instead)");
    false
}

fn run(backend: SolverBackend) -> (Problem, Options, metricdeform::pipeline::Outcome) {
    // Spot with a girth, a region's area and the volume: several
    // scale-driven outer iterations, then the fine-tune.
    let job = job(SPOT_DEMO);
    let problem = Problem::load(&job).unwrap();
    let mut options = Options::from_spec(&job.spec.solver);
    options.backend = backend;
    let out = deform(&problem, &options, &mut |_| {}).unwrap();
    (problem, options, out)
}

/// GPU: one preconditioner set-up per system kind per run, and after the
/// first outer iteration no more host-device traffic per outer iteration,
/// each way, than one set of the shape matrix's values in f64.
#[test]
fn gpu_sets_up_each_preconditioner_once_and_moves_one_value_set_per_outer_iteration() {
    if !gpu_available() {
        return;
    }
    let (problem, options, out) = run(SolverBackend::Gpu);
    let w = &out.solver;
    assert!(
        w.outer.len() >= 3,
        "the job needs several outer iterations to test this ({})",
        w.outer.len()
    );
    assert_eq!(w.scale_factors.preconditioner_setups, 1, "{w:?}");
    assert_eq!(w.scale_driven.preconditioner_setups, 1, "{w:?}");
    assert_eq!(w.fine_tune.preconditioner_setups, 1, "{w:?}");
    let value_set = 72 * w.shape_blocks as u64;
    assert!(value_set > 0);
    for (k, o) in w.outer.iter().enumerate().skip(1) {
        let (up, down) = (o.work.bytes_to_device, o.work.bytes_from_device);
        eprintln!(
            "outer iteration {}: {up} bytes to the device, {down} back (one f64 value set: \
             {value_set}), {} solves, {} iterations, {} waits",
            k + 1,
            o.work.solves,
            o.work.iterations,
            o.work.device_waits
        );
        assert_eq!(o.work.preconditioner_setups, 0, "outer iteration {}", k + 1);
        assert!(o.work.solves >= 2, "a shape and a scale-factor solve");
        // Each way at most one set of values: the new shape matrix values
        // (f32, with their diagonal inverses) and the vectors of the solves
        // go up; corrections and convergence states come back. A pattern or
        // an AMG hierarchy would be several sets more.
        for (what, bytes) in [("to the device", up), ("from the device", down)] {
            assert!(
                bytes <= value_set,
                "outer iteration {}: {bytes} bytes {what}, over one f64 value set of the \
                 shape matrix ({value_set})",
                k + 1
            );
        }
    }
    // The counts are the solver's, not a shortcut: the first outer iteration
    // uploads the patterns and hierarchies, far more than later ones.
    let first = w.outer[0].work.bytes_to_device;
    assert!(first > w.outer[1].work.bytes_to_device);
    assert!(w.transfer_bytes() >= first);
    // GPU seconds from timestamp queries where the adapter has them: every
    // PCG batch's pass is timed and read back with the batch's states (so no
    // more timed passes than waits), and the device time lies within the run.
    let phases = [&w.scale_factors, &w.scale_driven, &w.fine_tune];
    let passes: u64 = phases.iter().map(|p| p.device_timed_passes).sum();
    let waits: usize = phases.iter().map(|p| p.device_waits).sum();
    if solver_gpu::default_adapter().unwrap().timestamp_query {
        let timed = w.device_timed_seconds().expect("timed passes");
        let run = out.seconds_scale_driven + out.seconds_fine_tune;
        eprintln!(
            "{passes} timed passes, {timed:.3} s of device time in a {run:.3} s run, {waits} waits"
        );
        assert!(
            passes > 0 && passes <= waits as u64,
            "{passes} passes, {waits} waits"
        );
        assert!(
            timed > 0.0 && timed <= run,
            "{timed} s timed in a {run} s run"
        );
    } else {
        assert_eq!((passes, w.device_timed_seconds()), (0, None));
    }
    // And the result is still the method's.
    let rows = metricdeform::report::constraint_rows(&problem, &out.positions, options.tolerance);
    assert!(rows.iter().all(|r| r.met), "{rows:?}");
}

/// GPU: every pipeline the run's solves use is compiled ahead, on another
/// thread from the run's start (`SpdSolver::warm_up`): none is compiled
/// where a scale estimate or a shape solve first runs it.
#[test]
fn gpu_compiles_the_pipelines_of_its_solves_ahead() {
    if !gpu_available() {
        return;
    }
    let (_, options, out) = run(SolverBackend::Gpu);
    if !solver_gpu::default_adapter().unwrap().shader_f64 {
        // Only the f64 path is compiled ahead.
        return;
    }
    let w = &out.solver;
    let mut phases = vec![
        ("scale-driven", &w.scale_driven),
        ("fine-tune", &w.fine_tune),
    ];
    // The scale factors' Newton steps run on the GPU with per-constraint
    // multipliers only.
    if options.multipliers == metricdeform::constrained_step::Multipliers::PerConstraint {
        phases.push(("scale factors", &w.scale_factors));
    }
    for (phase, p) in phases {
        eprintln!(
            "{phase}: {} pipelines compiled at first use, {} ahead",
            p.device_compiles, p.device_compiles_ahead
        );
        assert_eq!(p.device_compiles, 0, "{phase}: {p:?}");
    }
    let ahead = w.scale_driven.device_compiles_ahead + w.scale_factors.device_compiles_ahead;
    assert!(ahead > 0, "{w:?}");
}

/// The GPU's scale-driven factor made from the symbolic analysis on
/// (`Options::overlap_factorizations`), from the input's positions, is the
/// factor made after the scale factors' set-up: the same result to the
/// bit. Either way each shape kind's set-up takes its factor made ahead
/// (the solver keeps one such at a time: the fine-tune's must not be handed
/// over before the scale-driven kind has taken its own), and so does the
/// scale factors' (made on the host while the device was opened).
#[test]
fn gpu_shape_factors_made_at_once_give_the_result_made_one_after_the_other() {
    if !gpu_available() {
        return;
    }
    let job = job(SPOT_DEMO);
    let problem = Problem::load(&job).unwrap();
    let runs: Vec<Vec<u64>> = [false, true]
        .into_iter()
        .map(|at_once| {
            let mut options = Options::from_spec(&job.spec.solver);
            options.backend = SolverBackend::Gpu;
            // Two outer iterations, then the fine-tune: both kinds set up.
            options.max_iterations = 2;
            options.overlap_factorizations = Some(at_once);
            let out = deform(&problem, &options, &mut |_| {}).unwrap();
            let w = &out.solver;
            assert_eq!(
                (
                    w.scale_driven.setups_from_factors_ahead,
                    w.fine_tune.setups_from_factors_ahead,
                    w.fine_tune.preconditioner_setups,
                    w.scale_factors.setups_from_factors_ahead,
                    w.scale_factors.preconditioner_setups
                ),
                (1, 1, 1, 1, 1),
                "at once: {at_once}; {w:?}"
            );
            out.positions
                .iter()
                .flat_map(|p| p.to_array())
                .map(f64::to_bits)
                .collect()
        })
        .collect();
    assert!(runs[0] == runs[1], "the results differ");
}

#[test]
fn cpu_reports_its_solver_work() {
    let (_, _, out) = run(SolverBackend::Cpu);
    let w = &out.solver;
    assert_eq!(w.scale_factors.preconditioner_setups, 1, "{w:?}");
    assert!(w.scale_driven.preconditioner_setups >= 1, "{w:?}");
    assert!(w.iterations_max() > 0, "the shape systems run a block PCG");
    assert_eq!(w.device_seconds(), 0.0);
    assert_eq!(w.transfer_bytes(), 0);
    assert_eq!(w.outer.len(), out.scale_driven_iterations);
}

/// `auto` never picks a CPU emulation, and picks a hardware adapter only from
/// the recorded crossover on (BENCHMARKS.md).
#[test]
fn auto_follows_the_measured_crossover() {
    for faces in [0, 5_856, 100_000, 1_200_000, 4_300_000, usize::MAX] {
        assert!(
            !auto_uses_gpu(faces, false),
            "emulated adapter, {faces} faces"
        );
        assert_eq!(
            auto_uses_gpu(faces, true),
            GPU_FASTER_FROM_FACES.is_some_and(|from| faces >= from),
            "{faces} faces"
        );
    }
}

/// The shape systems' preconditioners on the GPU, for the scale-driven kind
/// (the pipeline's scale-driven weights) and the fine-tune kind (its weights,
/// `Options::default().fine_tune`), on spot refined once: with the Cholesky
/// factor of `K` (`solver_gpu::Preconditioner::Cholesky`, the default) the
/// GPU solve agrees with the CPU backend's in as many PCG iterations (the same
/// preconditioner), up to two more; with the squared Laplacian (the fallback)
/// it agrees in fewer than the affine AMG; each is set up for the first
/// matrix and kept for a second of the kind (new reference positions).
#[test]
fn cholesky_and_squared_laplacian_precondition_the_shape_systems() {
    use metricdeform::shape::ShapeWeights;
    use solver_cpu::SystemKind;
    if !gpu_available() {
        return;
    }
    let _ = env_logger::builder().is_test(true).try_init();
    let scale_driven = ShapeWeights {
        k_f: 1000.0,
        k_m: 1.0,
        k_l: 1.0,
        k_p: 1000.0,
    };
    let fine_tune = metricdeform::pipeline::Options::default().fine_tune;
    squared_laplacian_on(SystemKind::ScaleDriven, scale_driven);
    squared_laplacian_on(SystemKind::FineTune, fine_tune);
}

fn squared_laplacian_on(kind: solver_cpu::SystemKind, w: metricdeform::shape::ShapeWeights) {
    use metricdeform::shape::ShapeModel;
    use solver_cpu::SpdSolver;
    use solver_gpu::Preconditioner;
    let path = meshes().join("spot.obj");
    let mesh = metricdeform::mesh::io::read_mesh(&path)
        .unwrap()
        .subdivide_midpoint();
    let topo = metricdeform::mesh::topology::Topology::build(&mesh);
    let (nf, n) = (mesh.num_faces(), mesh.num_vertices());
    let s = vec![1.1; nf];
    let c = vec![1.1; n];
    // Reference positions of a later outer iteration: the input, bulged.
    let moved: Vec<glam::DVec3> = mesh
        .positions
        .iter()
        .map(|p| *p * (1.0 + 0.05 * (3.0 * p.y).sin()))
        .collect();
    let solve = |solver: Box<dyn SpdSolver>| {
        let mut model = ShapeModel::with_solver(&mesh, &topo, Vec::new(), solver).unwrap();
        model.solver().set_system_kind(kind);
        let mut out = Vec::new();
        for x in [&mesh.positions, &moved] {
            model.assemble_and_factor(&mesh, x, &s, &c, &w).unwrap();
            let before = model.solver().counters();
            let mut rhs: Vec<f64> = model.reference_gradient().iter().map(|g| -g).collect();
            let info = model.solver().solve_in_place(&mut rhs, 1).unwrap();
            let after = model.solver().counters();
            let setups = after.preconditioner_setups;
            out.push((
                rhs,
                info.iterations,
                setups - before.preconditioner_setups,
                setups,
                after.since(&before),
                after.bytes_to_device,
            ));
        }
        out
    };
    // The host's factors (on a hardware adapter the GPU's are the
    // default): `chol_on_gpu` below is the GPU's.
    let gpu = |p: Preconditioner| -> Box<dyn SpdSolver> {
        let mut g = solver_gpu::open().unwrap();
        g.set_preconditioner(p).unwrap();
        g.set_factorization(solver_gpu::Factorization::Host);
        Box::new(g)
    };
    let cpu = solve(Box::new(solver_cpu::BlockPcgSolver::new()));
    let chol = solve(gpu(Preconditioner::Cholesky));
    let chol_on_gpu = solve({
        let mut g = solver_gpu::open().unwrap();
        g.set_factorization(solver_gpu::Factorization::Gpu);
        Box::new(g)
    });
    let squared = solve(gpu(Preconditioner::SquaredLaplacian));
    let affine = solve(gpu(Preconditioner::AffineAmg));
    let rel = |a: &[f64], b: &[f64]| {
        let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
        let nb: f64 = b.iter().map(|y| y * y).sum();
        (d / nb).sqrt()
    };
    // System k's GPU solution `x` (preconditioned by `what`) against the CPU's.
    let close_to_cpu = |what: &str, x: &[f64], k: usize| {
        let e = rel(x, &cpu[k].0);
        assert!(
            e < 1e-6,
            "{kind:?} system {k}: {what}: GPU and CPU differ by {e:e}"
        );
        e
    };
    for k in 0..2 {
        let e = close_to_cpu("Cholesky", &chol[k].0, k);
        eprintln!(
            "{kind:?} system {k}: Cholesky {} iterations, CPU {}, GPU - CPU {e:.1e}",
            chol[k].1, cpu[k].1
        );
        assert!(
            chol[k].1 <= cpu[k].1 + 2,
            "{kind:?} system {k}: {} iterations against the CPU's {}",
            chol[k].1,
            cpu[k].1
        );
    }
    // The factor made on the GPU from K's values: the host's factor to
    // rounding, so the same solves in as many iterations (one more at
    // most); K's values go up instead of the factor.
    for k in 0..2 {
        let e = close_to_cpu("Cholesky factored on the GPU", &chol_on_gpu[k].0, k);
        eprintln!(
            "{kind:?} system {k}: factored on the GPU {} iterations, on the host {}, GPU - CPU \
             {e:.1e}; {} bytes up against {}",
            chol_on_gpu[k].1, chol[k].1, chol_on_gpu[k].5, chol[k].5
        );
        assert!(chol_on_gpu[k].1.abs_diff(chol[k].1) <= 1);
    }
    assert_eq!(chol_on_gpu[0].3, 1, "one set-up for the first matrix");
    assert_eq!(
        chol_on_gpu[1].2, 0,
        "the second matrix of the kind keeps it"
    );
    if solver_gpu::default_adapter().is_ok_and(|a| a.shader_f64) {
        // Spot x4: a factor of 1.4M values (11.4 MB) against K's 0.1M.
        assert!(
            10 * chol_on_gpu[0].5 < 6 * chol[0].5,
            "{} bytes up against {} with the host's factor",
            chol_on_gpu[0].5,
            chol[0].5
        );
    }
    assert_eq!(chol[0].3, 1, "one Cholesky set-up for the first matrix");
    assert_eq!(
        chol[1].2, 0,
        "the second matrix of the kind keeps the factor"
    );
    for k in 0..2 {
        let e = close_to_cpu("squared Laplacian", &squared[k].0, k);
        eprintln!(
            "{kind:?} system {k}: squared Laplacian {} iterations, affine AMG {}, GPU - CPU {e:.1e}",
            squared[k].1, affine[k].1
        );
        assert!(
            squared[k].1 < affine[k].1,
            "{kind:?} system {k}: {} iterations against {} with the affine AMG",
            squared[k].1,
            affine[k].1
        );
    }
    // Set up once (the first matrix), kept for the second.
    assert_eq!(squared[0].3, 1, "one set-up for the first matrix");
    assert_eq!(squared[1].2, 0, "the second matrix of the kind keeps it");
    // What a discrete GPU pays per PCG iteration (solver_gpu::KernelWork):
    // the preconditioner's kernels, a scalar B on 3-vectors in storage
    // buffers, stay within 2x the least bytes of the operator applications,
    // vector updates included.
    for (k, run) in squared.iter().enumerate() {
        let w = &run.4;
        let its = run.1 as u64;
        eprintln!(
            "{kind:?} system {k}: {} dispatches, {:.2} MB modelled, {:.2} MB least, {} iterations",
            w.device_dispatches,
            w.device_bytes as f64 / 1e6,
            w.device_bytes_minimal as f64 / 1e6,
            its
        );
        assert!(w.device_bytes_minimal > 0 && w.device_dispatches > its);
        assert!(
            w.device_bytes <= 2 * w.device_bytes_minimal,
            "{kind:?} system {k}: {} bytes modelled against {} least",
            w.device_bytes,
            w.device_bytes_minimal
        );
    }
}

/// The scale factors' estimation (Eq. 3) from `solver`, with `problem`'s
/// constraints in scale-factor form at positions `x` (`extra` more copies of
/// the volume's, appended).
fn scale_estimate(
    problem: &Problem,
    sys: &mut metricdeform::scale_factors::ScaleFactorSystem,
    x: &[glam::DVec3],
    extra: usize,
) -> (Vec<f64>, metricdeform::scale_factors::ScaleInfo) {
    use metricdeform::scale_factors::ScaleConstraint;
    let o = Options::default();
    let areas = problem.mesh.face_areas(x);
    let mut cons: Vec<ScaleConstraint> = problem
        .constraints
        .iter()
        .enumerate()
        .map(|(g, c)| ScaleConstraint {
            coeffs: c.face_coefficients(&problem.mesh, x, &areas, o.volume_share),
            degree: c.degree(),
            target: c.target,
            group: g,
        })
        .collect();
    // Each copy's coefficients and target scaled by 3, 7, ...: the same
    // demand, whose rows round differently from the original's.
    let volume = cons.iter().position(|c| c.degree == 3).unwrap();
    for j in 0..extra {
        let c = &cons[volume];
        let f = (4 * j + 3) as f64;
        cons.push(ScaleConstraint {
            coeffs: c.coeffs.iter().map(|&(face, v)| (face, f * v)).collect(),
            degree: 3,
            target: f * c.target,
            group: c.group,
        });
    }
    sys.estimate(
        &cons,
        metricdeform::constrained_step::Multipliers::PerConstraint,
    )
    .unwrap()
}

fn scale_system(
    problem: &Problem,
    solver: Box<dyn solver_cpu::SpdSolver>,
) -> metricdeform::scale_factors::ScaleFactorSystem {
    let o = Options::default();
    let areas = problem.mesh.face_areas(&problem.mesh.positions);
    metricdeform::scale_factors::ScaleFactorSystem::with_solver(
        &problem.topo.face_pairs,
        &areas,
        o.k_d,
        o.k_r,
        o.regulariser,
        solver,
    )
    .unwrap()
}

/// GPU: the scale factors' Newton steps run on the device, a batch of them
/// per host wait (`SpdSolver::power_sum_newton`): an estimation like the
/// last waits once, and lands where the CPU's steps land, in as many steps.
/// The demo's girth (degree 1, its row solved at the first step only), area
/// (2) and volume (3), at the rest positions and at moved ones; then the
/// volume three times over (a singular multiplier system, which both
/// pseudo-invert); then more constraints than the device's steps take (the
/// host's steps through the same solver, as before).
#[test]
fn gpu_takes_the_scale_factors_newton_steps_waiting_once_an_estimation() {
    if !gpu_available() {
        return;
    }
    let problem = Problem::load(&job(SPOT_DEMO)).unwrap();
    let mut cpu = scale_system(&problem, Box::new(solver_cpu::CholeskySolver::new()));
    let mut gpu = scale_system(&problem, {
        let mut g = solver_gpu::open().unwrap();
        solver_cpu::SpdSolver::set_system_kind(&mut g, solver_cpu::SystemKind::ScaleFactors);
        Box::new(g)
    });
    let x0 = problem.mesh.positions.clone();
    // Moved: stretched along y and bulged, so the coefficients change.
    let x1: Vec<glam::DVec3> = x0
        .iter()
        .map(|p| glam::DVec3::new(p.x * (1.0 + 0.2 * p.y), 1.1 * p.y, p.z))
        .collect();
    for (what, x, extra, waits) in [
        ("rest", &x0, 0, None),
        ("rest again", &x0, 0, Some(1)),
        ("moved", &x1, 0, None),
        ("moved again", &x1, 0, Some(1)),
        ("volume three times", &x0, 2, None),
        ("volume three times again", &x0, 2, Some(1)),
        ("nine constraints (host steps)", &x0, 6, None),
    ] {
        let (s_cpu, i_cpu) = scale_estimate(&problem, &mut cpu, x, extra);
        let before = gpu.counters();
        let (s_gpu, i_gpu) = scale_estimate(&problem, &mut gpu, x, extra);
        let work = gpu.counters().since(&before);
        let apart = s_cpu
            .iter()
            .zip(&s_gpu)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        let moved = s_cpu.iter().fold(0.0f64, |m, v| m.max((v - 1.0).abs()));
        eprintln!(
            "{what}: {} steps (cpu {}), max |C| {:.1e}, |s_gpu - s_cpu| {apart:.1e}, \
             |s - 1| {moved:.3}, {} waits, {} solves, {} PCG iterations",
            i_gpu.newton_iterations,
            i_cpu.newton_iterations,
            i_gpu.max_residual,
            work.device_waits,
            work.solves,
            work.iterations
        );
        assert!(moved > 0.01, "{what}: the constraints move s ({moved})");
        assert_eq!(i_gpu.newton_iterations, i_cpu.newton_iterations, "{what}");
        assert!(i_gpu.max_residual < 1e-12, "{what}: {i_gpu:?}");
        assert!(apart < 1e-10, "{what}: {apart:e} from the CPU's s");
        match (extra > 2, waits) {
            // The host's steps: a solve (at least one wait) per step.
            (true, _) => {
                assert!(
                    work.device_waits >= i_gpu.newton_iterations,
                    "{what}: {work:?}"
                );
                assert!(work.iterations > 0, "{what}: PCG solves ({work:?})");
            }
            // The device's: no PCG, one wait where the last estimation
            // took as many steps.
            (false, Some(w)) => {
                assert_eq!(work.device_waits, w, "{what}: {work:?}");
                assert_eq!(work.iterations, 0, "{what}: {work:?}");
                assert_eq!(work.solves, i_gpu.newton_iterations, "{what}: {work:?}");
            }
            // With no estimation like it before: batches of a few steps,
            // fewer waits than steps.
            (false, None) => assert!(
                work.device_waits < i_gpu.newton_iterations.max(2),
                "{what}: {work:?}"
            ),
        }
    }
}
