//! Shape-system solve benchmark (paper Eq. 7, the system every outer iteration
//! solves): GPU PCG (WGSL, f32 with f64 refinement) next to the CPU block PCG and
//! the CPU sparse Cholesky, on spot subdivided to ~94k and ~1.5M faces and on
//! fandisk (13k). Prints a markdown table.
//!
//! `cargo bench --bench pcg` (`-- --quick` skips the largest mesh). The adapter's
//! name is printed: on lavapipe (a CPU emulation) the GPU column is a
//! correctness/efficiency check, never GPU performance.
//!
//! Effective bandwidth = bytes one minimal SpMV must move (each stored block once,
//! its column index, x read once and y written once, in the solver's precision)
//! / time per PCG iteration. The CPU PCG's matrix is the isotropic-plus-ring form
//! (`iso_spmv_bytes`), the GPU's the explicit blocks (`spmv_bytes`).

#[path = "../tests/common/mod.rs"]
mod common;

use metricdeform::shape::ShapeModel;
use metricdeform::Mesh;
use solver_cpu::{BlockPcgSolver, BlockSym3, CholeskySolver, IsoRingSym3, SpdSolver};
use solver_gpu::{MixedPrecision, Preconditioner};
use std::path::Path;
use std::time::Instant;

fn load(name: &str, subdivisions: usize) -> Mesh {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let mut mesh = metricdeform::mesh::io::read_mesh(&dir.join(name)).unwrap();
    for _ in 0..subdivisions {
        mesh = mesh.subdivide_midpoint();
    }
    mesh
}

/// Bytes of one minimal SpMV over the full symmetric matrix with `scalar` bytes per value.
fn spmv_bytes(a: &BlockSym3, scalar: usize) -> f64 {
    let full_blocks = 2 * a.row_idx.len() - a.n;
    (full_blocks * (9 * scalar + 4) + a.n * 4 + 2 * 3 * a.n * scalar) as f64
}

/// Bytes of one minimal product with the isotropic-plus-ring form (f64): `K`
/// over both triangles with its column indices, the rings read twice (gather and
/// transposed gather) with theirs, the `C_i`, x and y, and the ring terms
/// written and read.
fn iso_spmv_bytes(a: &IsoRingSym3) -> f64 {
    let n = a.n();
    let full = 2 * a.iso.row_idx.len() - n;
    let ring = a.rings.idx.len() + n;
    (full * 12 + 2 * ring * 12 + n * 48 + 2 * 3 * n * 8 + 2 * 3 * n * 8) as f64
}

fn residual(a: &BlockSym3, fixed: &[bool], x: &[f64], b: &[f64]) -> f64 {
    let mut ax = vec![0.0; x.len()];
    a.mul_vec(x, &mut ax);
    let (mut rr, mut bb) = (0.0, 0.0);
    for i in 0..x.len() {
        if fixed[i / 3] {
            continue;
        }
        rr += (ax[i] - b[i]).powi(2);
        bb += b[i] * b[i];
    }
    (rr / bb).sqrt()
}

fn row(label: &str, mesh: &Mesh, quick_direct: bool) {
    let topo = metricdeform::mesh::topology::Topology::build(mesh);
    let mut model = ShapeModel::new(mesh, &topo, Vec::new()).unwrap();
    let nf = mesh.num_faces();
    // The first outer iteration of a demanding job: every face asked to grow 10 %.
    common::assemble_growing_tenth(&mut model, mesh);
    let b: Vec<f64> = model.reference_gradient().iter().map(|g| -g).collect();
    let (iso, fixed) = model.system();
    // The CPU PCG works on the model's isotropic-plus-ring form; the direct and
    // GPU solvers get the explicit 3x3 blocks.
    let blocks = iso.to_blocks();
    let a = &blocks;
    let bytes64 = iso_spmv_bytes(iso);
    let bytes32 = spmv_bytes(a, 4);

    // CPU PCG (f64) on the isotropic-plus-ring form.
    let mut pcg = BlockPcgSolver::new();
    let t = Instant::now();
    pcg.prepare_shape_owned(iso.clone(), fixed).unwrap();
    let t_prep = t.elapsed().as_secs_f64();
    let mut x = vec![0.0; b.len()];
    let t = Instant::now();
    let info = pcg.solve_with_guess(&b, &mut x, 1).unwrap();
    let t_solve = t.elapsed().as_secs_f64();
    // Time of one bare SpMV pass (the memory-bound floor of an iteration).
    let mut y = vec![0.0; b.len()];
    let reps = 10;
    let t = Instant::now();
    for _ in 0..reps {
        pcg.mul_vec(&x, &mut y);
    }
    let t_spmv = t.elapsed().as_secs_f64() / reps as f64;
    println!(
        "| {label} | {nf} | cpu PCG (f64, isotropic-plus-ring form, isotropic Cholesky precond.) | {:.3} | {:.3} | {} | {:.2} | {:.2} (SpMV alone {:.2} GB/s) | {:.1e} |",
        t_prep,
        t_solve,
        info.iterations,
        1e3 * t_solve / info.iterations.max(1) as f64,
        bytes64 * info.iterations.max(1) as f64 / t_solve / 1e9,
        bytes64 / t_spmv / 1e9,
        residual(a, fixed, &x, &b)
    );
    // Warm start from a nearby solution (the previous outer iteration's role).
    let mut xw: Vec<f64> = x.iter().map(|v| v * 0.9).collect();
    let info_w = pcg.solve_with_guess(&b, &mut xw, 1).unwrap();
    println!(
        "| {label} | {nf} | cpu PCG, warm start from 0.9 x | | | {} | | | {:.1e} |",
        info_w.iterations,
        residual(a, fixed, &xw, &b)
    );

    // CPU sparse Cholesky (f64).
    if quick_direct {
        let mut chol = CholeskySolver::new();
        let t = Instant::now();
        chol.prepare_blocks(a, fixed).unwrap();
        let t_prep = t.elapsed().as_secs_f64();
        let mut xc = b.clone();
        let t = Instant::now();
        chol.solve_in_place(&mut xc, 1).unwrap();
        let t_solve = t.elapsed().as_secs_f64();
        println!(
            "| {label} | {nf} | cpu sparse Cholesky (f64, nnz(L) = {}) | {:.3} | {:.3} | - | | | {:.1e} |",
            chol.factor_nnz(),
            t_prep,
            t_solve,
            residual(a, fixed, &xc, &b)
        );
    } else {
        println!("| {label} | {nf} | cpu sparse Cholesky | skipped (factor beyond this machine's memory budget) | | | | | |");
    }

    // GPU PCG.
    match solver_gpu::open() {
        Err(e) => println!("| {label} | {nf} | gpu | unavailable: {e} | | | | | |"),
        Ok(mut gpu) => {
            let name = gpu.adapter_name().to_string();
            // The pipeline builds the scale-driven systems' AMG on the
            // translations; METRICDEFORM_GPU_PRECONDITIONER=affine-amg gives it
            // the vertex positions here, for the affine near-null space.
            if std::env::var("METRICDEFORM_GPU_PRECONDITIONER").is_ok_and(|v| v == "affine-amg") {
                let positions: Vec<[f64; 3]> =
                    mesh.positions.iter().map(|p| p.to_array()).collect();
                gpu.set_vertex_positions(&positions);
            }
            let t = Instant::now();
            let prep = gpu.prepare_blocks(a, fixed);
            let t_prep = t.elapsed().as_secs_f64();
            if let Err(e) = prep {
                println!("| {label} | {nf} | gpu ({name}) | failed: {e} | | | | | |");
                return;
            }
            let mut xg = vec![0.0; b.len()];
            let t = Instant::now();
            match gpu.solve_with_guess(&b, &mut xg, 1) {
                Err(e) => println!("| {label} | {nf} | gpu ({name}) | failed: {e} | | | | | |"),
                Ok(_) => {
                    let t_solve = t.elapsed().as_secs_f64();
                    let st = gpu.last_stats();
                    println!(
                        "| {label} | {nf} | gpu ({name}; f32 PCG, {:?} preconditioner, {} f64 refinement rounds) | {:.3} | {:.3} | {} | {:.2} | {:.2} | {:.1e} |",
                        gpu.active_preconditioner(),
                        st.rounds,
                        t_prep,
                        t_solve,
                        st.iterations,
                        1e3 * t_solve / st.iterations.max(1) as f64,
                        bytes32 * st.iterations.max(1) as f64 / t_solve / 1e9,
                        residual(a, fixed, &xg, &b)
                    );
                    let mut xw: Vec<f64> = xg.iter().map(|v| v * 0.9).collect();
                    if gpu.solve_with_guess(&b, &mut xw, 1).is_ok() {
                        println!(
                            "| {label} | {nf} | gpu, warm start from 0.9 x | | | {} | | | {:.1e} |",
                            gpu.last_stats().iterations,
                            residual(a, fixed, &xw, &b)
                        );
                    }
                    // The mixed-precision solve from the start (f64 PCG, f32
                    // V-cycle), where the adapter has SHADER_F64.
                    if gpu.adapter().shader_f64 {
                        gpu.set_mixed_precision(MixedPrecision::Always);
                        let mut xm = vec![0.0; b.len()];
                        let t = Instant::now();
                        let res = gpu.solve_with_guess(&b, &mut xm, 1);
                        let t_solve = t.elapsed().as_secs_f64();
                        let st = gpu.last_stats();
                        match res {
                            Err(e) => println!("| {label} | {nf} | gpu, mixed precision | failed: {e} | | | | | |"),
                            Ok(_) => println!(
                                "| {label} | {nf} | gpu, mixed precision (f64 PCG and SpMV, f32 V-cycle; {} rounds) | | {:.3} | {} | {:.2} | | {:.1e} |",
                                st.rounds,
                                t_solve,
                                st.iterations,
                                1e3 * t_solve / st.iterations.max(1) as f64,
                                residual(a, fixed, &xm, &b)
                            ),
                        }
                        gpu.set_mixed_precision(MixedPrecision::Fallback);
                    }
                }
            }
        }
    }
}

/// The fine-tune system (Eq. 8's Hessian, `k_m = k_l = 100 k_f`) on the GPU
/// with each AMG near-null space: translations, and the vertices' affine
/// motions (`set_vertex_positions`, as the pipeline does).
fn fine_tune_row(label: &str, mesh: &Mesh) {
    let topo = metricdeform::mesh::topology::Topology::build(mesh);
    let mut model = ShapeModel::new(mesh, &topo, Vec::new()).unwrap();
    let (nf, n) = (mesh.num_faces(), mesh.num_vertices());
    let w = metricdeform::pipeline::Options::default().fine_tune;
    model
        .assemble_and_factor(mesh, &mesh.positions, &vec![1.0; nf], &vec![1.0; n], &w)
        .unwrap();
    // Right-hand sides like the constrained step's: smooth fields, `cols` of
    // them (`--columns K`; the pipeline solves k + 1 at once).
    let cols: usize = std::env::args()
        .skip_while(|a| a != "--columns")
        .nth(1)
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let (iso, fixed) = model.system();
    let b: Vec<f64> = (0..cols * 3 * n)
        .map(|i| {
            let (c, i) = (i / (3 * n), i % (3 * n));
            let v = ((i / 3) as f64 * 0.001 * (1 + c) as f64 + (i % 3) as f64).sin();
            if fixed[i / 3] {
                0.0
            } else {
                v
            }
        })
        .collect();
    let a = iso.to_blocks();
    let positions: Vec<[f64; 3]> = mesh.positions.iter().map(|p| p.to_array()).collect();
    // Both near-null spaces, or the one METRICDEFORM_GPU_PRECONDITIONER names.
    let both = [Preconditioner::AffineAmg, Preconditioner::Amg];
    let chosen: Vec<Preconditioner> = match std::env::var("METRICDEFORM_GPU_PRECONDITIONER") {
        Ok(_) => vec![Preconditioner::from_env()],
        Err(_) => both.to_vec(),
    };
    for p in chosen {
        let mut gpu = match solver_gpu::open() {
            Ok(g) => g,
            Err(e) => {
                return println!("| {label} fine-tune | {nf} | gpu | unavailable: {e} | | | | |")
            }
        };
        let name = gpu.adapter_name().to_string();
        gpu.set_preconditioner(p).unwrap();
        gpu.set_vertex_positions(&positions);
        gpu.set_tolerance(1e-8); // the pipeline's GPU tolerance
        let t = Instant::now();
        gpu.prepare_blocks(&a, fixed).unwrap();
        let t_prep = t.elapsed().as_secs_f64();
        let h = gpu
            .amg_hierarchy()
            .map(|h| (h.sizes(), h.operator_complexity()));
        let mut x = vec![0.0; b.len()];
        let t = Instant::now();
        let res = gpu.solve_with_guess(&b, &mut x, cols);
        let t_solve = t.elapsed().as_secs_f64();
        let st = gpu.last_stats();
        match res {
            Err(e) => println!("| {label} fine-tune | {nf} | gpu ({name}, {p:?}) | failed: {e} | | | | |"),
            Ok(_) => println!(
                "| {label} fine-tune | {nf} | gpu ({name}; {:?}, levels {:?}, operator complexity {:.2}) | {t_prep:.3} | {t_solve:.3} | {} ({} rounds) | {:.2} | {:.1e} |",
                gpu.active_preconditioner(),
                h.as_ref().map(|h| h.0.clone()).unwrap_or_default(),
                h.map_or(0.0, |h| h.1),
                st.iterations,
                st.rounds,
                1e3 * t_solve / st.iterations.max(1) as f64,
                (0..cols)
                    .map(|c| {
                        let r = c * 3 * n..(c + 1) * 3 * n;
                        residual(&a, fixed, &x[r.clone()], &b[r])
                    })
                    .fold(0.0, f64::max)
            ),
        }
    }
}

fn main() {
    // `RUST_LOG=solver_gpu=trace` shows each refinement round's residual.
    let _ = env_logger::builder().format_timestamp_millis().try_init();
    let quick = std::env::args().any(|a| a == "--quick");
    if std::env::args().any(|a| a == "--fine-tune") {
        println!("| system | faces | solver | prepare s | solve s | iterations | ms / iteration | relative residual |");
        println!("|---|---|---|---|---|---|---|---|");
        fine_tune_row("fandisk", &load("fandisk.obj", 0));
        if !quick {
            fine_tune_row("spot-x16", &load("spot.obj", 2));
        }
        return;
    }
    println!("| mesh | faces | solver | prepare s | solve s | iterations | ms / iteration | effective GB/s | relative residual |");
    println!("|---|---|---|---|---|---|---|---|---|");
    row("fandisk", &load("fandisk.obj", 0), true);
    row("spot-x16", &load("spot.obj", 2), true);
    if !quick {
        row("spot-x256", &load("spot.obj", 4), false);
    }
}
