//! One backend-agnostic suite (paper Fig. 3, Table 1, Fig. 9), instantiated for
//! each backend: `cpu` (block PCG with a Cholesky preconditioner, the default),
//! `cpu_direct` (sparse Cholesky of every system) and `gpu` (WGSL PCG on wgpu).
//! Every metric is measured on the mesh written to disk. The non-default backends
//! are also compared vertex by vertex with the CPU result (parity).
//!
//! GPU tests need a wgpu adapter (lavapipe is enough). Without one they skip with
//! a message on stderr; with `REQUIRE_GPU=1` they fail instead.

mod common;

use common::*;
use metricdeform::pipeline::SolverBackend;

/// Whether tests on `backend` can run here (see the module docs).
fn available(backend: SolverBackend) -> bool {
    if backend != SolverBackend::Gpu || solver_gpu::gpu_available() {
        return true;
    }
    if std::env::var("REQUIRE_GPU").is_ok_and(|v| v == "1") {
        panic!("REQUIRE_GPU=1 but no GPU adapter is available (install mesa-vulkan-drivers for lavapipe)");
    }
    eprintln!("skipping GPU test: no GPU adapter (set REQUIRE_GPU=1 to fail instead)");
    false
}

/// Largest vertex distance between two results, relative to the bbox diagonal.
fn max_deviation(a: &Run, b: &Run) -> f64 {
    common::max_deviation(&a.problem.mesh, &a.written.positions, &b.written.positions)
}

/// Run `text` on `backend`; for a non-reference backend, also on the CPU
/// reference, asserting agreement to `parity` of the bbox diagonal per vertex.
fn run_checked(text: &str, backend: SolverBackend, parity: f64) -> Run {
    let r = run_on(text, backend);
    if backend != SolverBackend::Cpu {
        let reference = run_on(text, SolverBackend::Cpu);
        let dev = max_deviation(&r, &reference);
        eprintln!(
            "{}: max vertex deviation from the CPU result {:.2e} % of the bbox diagonal",
            backend.name(),
            100.0 * dev
        );
        assert!(
            dev <= parity,
            "{} and cpu differ by {:.3e} % of the bbox diagonal (allowed {:.1e} %)",
            backend.name(),
            100.0 * dev,
            100.0 * parity
        );
    }
    r
}

macro_rules! conformance_suite {
    ($module:ident, $backend:expr, $parity:expr) => {
        conformance_suite!($module, $backend, $parity, allow(dead_code));
    };
    ($module:ident, $backend:expr, $parity:expr, $slow:meta) => {
        mod $module {
            use super::*;

            const BACKEND: SolverBackend = $backend;

            /// Paper Fig. 3: volume x8 alone gives the input scaled by 2.
            #[test]
            fn fig3_spot_volume_x8_is_scaling_by_two() {
                if available(BACKEND) {
                    let job = fig3_job("spot.obj", "volume", 8.0);
                    assert_scaled_by_two(&run_checked(&job, BACKEND, $parity));
                }
            }

            /// Paper Fig. 3: total area x4 alone gives the input scaled by 2.
            #[test]
            fn fig3_fandisk_area_x4_is_scaling_by_two() {
                if available(BACKEND) {
                    let job = fig3_job("fandisk.obj", "area", 4.0);
                    assert_scaled_by_two(&run_checked(&job, BACKEND, $parity));
                }
            }

            #[test]
            fn table1_spot_lengths_area_volume() {
                if available(BACKEND) {
                    let (mean, max) = assert_all_met(&run_checked(TABLE1_SPOT, BACKEND, $parity));
                    // Bounds with margin over what this job reaches (mean 1.25, max 2.26).
                    assert!(mean < 1.5, "mean distortion {mean}");
                    assert!(max < 4.0, "max distortion {max}");
                }
            }

            #[test]
            #[$slow]
            fn table1_homer_girths_area_volume() {
                if available(BACKEND) {
                    let (mean, max) = assert_all_met(&run_checked(TABLE1_HOMER, BACKEND, $parity));
                    // This job reaches mean 1.16, max 2.32.
                    assert!(mean < 1.4, "mean distortion {mean}");
                    assert!(max < 4.5, "max distortion {max}");
                }
            }

            /// Paper Fig. 9 at its most demanding step (top area x2.5, bottom kept).
            #[test]
            fn fig9_fandisk_top_area_x2_5_bottom_kept() {
                if available(BACKEND) {
                    let r = run_checked(&fig9_fandisk(2.5), BACKEND, $parity);
                    let (mean, max) = assert_all_met(&r);
                    // Reaches mean 1.08, max 1.68.
                    assert!(mean < 1.25, "mean distortion {mean}");
                    assert!(max < 3.0, "max distortion {max}");
                }
            }
        }
    };
}

conformance_suite!(cpu, SolverBackend::Cpu, 0.0);
// PCG (to 1e-10 relative residual) against exact Cholesky: agreement far inside 1e-5.
conformance_suite!(cpu_direct, SolverBackend::CpuDirect, 1e-7);
// The parity bound: 0.001 % of the bbox diagonal per vertex. The homer job
// takes about 4 min on lavapipe run alone (2 cores), now that the fine-tune AMG
// has the affine near-null space (its fine-tune, weights 1/100/100, had not
// finished a step in 2 min with translations only).
conformance_suite!(gpu, SolverBackend::Gpu, 1e-5);

/// The CPU-only Fig. 3 cases (the suite above covers one of each kind per backend).
#[test]
fn fig3_spot_area_x4_and_fandisk_volume_x8_on_cpu() {
    assert_scaled_by_two(&run(&fig3_job("spot.obj", "area", 4.0)));
    assert_scaled_by_two(&run(&fig3_job("fandisk.obj", "volume", 8.0)));
}

/// Fig. 9's milder steps on the CPU.
#[test]
fn fig9_fandisk_top_area_x1_5_and_x2_on_cpu() {
    for scale in [1.5, 2.0] {
        let (mean, max) = assert_all_met(&run(&fig9_fandisk(scale)));
        assert!(mean < 1.25, "x{scale}: mean distortion {mean}");
        assert!(max < 3.0, "x{scale}: max distortion {max}");
    }
}

/// GPU parity at the million-face class (homer with every edge cut in 10:
/// 1.2M faces; two girths and the volume), on a hardware adapter only: on
/// lavapipe this run does not finish within a CI run. Every metric within the
/// tolerance, GPU and CPU results within 1e-3 % of the bbox diagonal.
#[test]
fn gpu_parity_at_a_million_faces_on_hardware() {
    match solver_gpu::default_adapter() {
        Ok(a) if a.device_type != "Cpu" => {}
        Ok(a) => {
            eprintln!(
                "skipping the 1M-face GPU parity test: {} is a CPU emulation",
                a.name
            );
            return;
        }
        Err(why) => {
            eprintln!("skipping the 1M-face GPU parity test: {why}");
            return;
        }
    }
    let job = job(GIRTHS_HOMER);
    let mesh = metricdeform::mesh::io::read_mesh(&job.mesh_path())
        .unwrap()
        .subdivide_uniform(10);
    let problem = metricdeform::problem::Problem::build(&job, mesh, &job.mesh_path()).unwrap();
    assert!(problem.mesh.num_faces() > 1_000_000);
    let mut options = metricdeform::pipeline::Options::from_spec(&job.spec.solver);
    let mut result = |backend| {
        options.backend = backend;
        metricdeform::pipeline::deform(&problem, &options, &mut |_| {}).unwrap()
    };
    let gpu = result(SolverBackend::Gpu);
    let cpu = result(SolverBackend::Cpu);
    for c in &problem.constraints {
        let err = c.residual(&problem.mesh, &gpu.positions).abs();
        assert!(
            err <= options.tolerance,
            "{}: relative error {err:.2e}",
            c.name
        );
    }
    let dev = common::max_deviation(&problem.mesh, &gpu.positions, &cpu.positions);
    eprintln!(
        "1.2M faces: GPU and CPU results {:.2e} % of the bbox diagonal apart",
        100.0 * dev
    );
    assert!(
        dev <= 1e-5,
        "{:.3e} % of the bbox diagonal apart",
        100.0 * dev
    );
}
