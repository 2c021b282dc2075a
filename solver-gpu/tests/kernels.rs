//! The GPU kernels and the solver against CPU references (lavapipe is enough).
//! Without an adapter each test prints "skipping: no GPU adapter" and passes,
//! unless REQUIRE_GPU=1, where it fails.

use solver_cpu::{
    BlockSym3, CholeskySolver, IsoRingSym3, SolverError, SpdSolver, SymCsc, SystemKind,
};
use solver_gpu::{kernels, GpuError, GpuSolver, MixedPrecision, OpenOptions, Preconditioner};

fn require_gpu() -> bool {
    std::env::var("REQUIRE_GPU").is_ok_and(|v| v == "1")
}

fn skip_or_fail(e: GpuError) -> Option<GpuSolver> {
    match e {
        GpuError::NoAdapter(why) if !require_gpu() => {
            eprintln!("skipping: no GPU adapter ({why})");
            None
        }
        other => panic!("could not open the GPU solver: {other}"),
    }
}

/// The GPU tests' turn: one test at a time holds a device.
///
/// On H200s (NVIDIA's driver 580, 16 test threads) this binary hung in 6
/// of 15 runs with 0-2 tests done: 13 test threads waited on one
/// priority-inheritance futex (`futex_lock_pi`) inside the driver, one
/// test thread ran, and each test passed alone. Other projects met the
/// same driver lock with many devices at once (paiml/aprender#2063: their
/// GPU tests made serial). The devices' work here is a few milliseconds a
/// test, so the turns cost little; the tests' host work still runs beside.
static TURN: std::sync::Mutex<()> = std::sync::Mutex::new(());

std::thread_local! {
    /// Devices this thread holds (a test may open two; the first takes
    /// the turn).
    static HELD: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// A device opened in its test's turn ([`TURN`]), which it holds until
/// dropped (the device first: the solver is the first field).
struct Gpu {
    solver: GpuSolver,
    _turn: Option<std::sync::MutexGuard<'static, ()>>,
}

impl Gpu {
    /// `open()` in this test's turn; `None` (skipped) without an adapter.
    fn open(open: impl FnOnce() -> Result<GpuSolver, GpuError>) -> Option<Gpu> {
        let turn = (HELD.get() == 0).then(|| TURN.lock().unwrap_or_else(|e| e.into_inner()));
        HELD.set(HELD.get() + 1);
        let opened = open().map_or_else(skip_or_fail, Some);
        let gpu = opened.map(|solver| Gpu {
            solver,
            _turn: turn,
        });
        if gpu.is_none() {
            HELD.set(HELD.get() - 1);
        }
        gpu
    }
}

impl Drop for Gpu {
    fn drop(&mut self) {
        HELD.set(HELD.get() - 1);
    }
}

impl std::ops::Deref for Gpu {
    type Target = GpuSolver;
    fn deref(&self) -> &GpuSolver {
        &self.solver
    }
}

impl std::ops::DerefMut for Gpu {
    fn deref_mut(&mut self) -> &mut GpuSolver {
        &mut self.solver
    }
}

/// The GPU solver, or `None` (test skipped) when there is no adapter.
fn gpu() -> Option<Gpu> {
    Gpu::open(solver_gpu::open)
}

/// The device opened with its limits lowered by `adjust`.
fn gpu_with_limits(adjust: impl Fn(&mut solver_gpu::wgpu::Limits) + 'static) -> Option<Gpu> {
    let opts = OpenOptions {
        adjust_limits: Some(Box::new(adjust)),
        ..Default::default()
    };
    Gpu::open(|| solver_gpu::open_with(opts))
}

/// SplitMix64: seeded, reproducible.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [-1, 1).
    fn sym(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
    /// Never zero: magnitude in [0.5, 1.5), random sign.
    fn nonzero(&mut self) -> f64 {
        let m = 1.0 + 0.5 * self.sym();
        if self.next() & 1 == 0 {
            m
        } else {
            -m
        }
    }
    fn vec(&mut self, n: usize) -> Vec<f64> {
        (0..n).map(|_| self.nonzero()).collect()
    }
}

/// Edges of a triangulated nx x ny grid (a mesh-like vertex graph, 6-ring inside).
fn grid_edges(nx: usize, ny: usize) -> Vec<(usize, usize)> {
    let id = |i: usize, j: usize| j * nx + i;
    let mut e = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            if i + 1 < nx {
                e.push((id(i, j), id(i + 1, j)));
            }
            if j + 1 < ny {
                e.push((id(i, j), id(i, j + 1)));
            }
            if i + 1 < nx && j + 1 < ny {
                e.push((id(i, j), id(i + 1, j + 1)));
            }
        }
    }
    e
}

/// SPD block matrix: weighted graph Laplacian x I3 plus random (non-symmetric)
/// 3x3 couplings, made block diagonally dominant with a relative `shift`.
fn spd_blocks(nx: usize, ny: usize, shift: f64, rng: &mut Rng) -> BlockSym3 {
    let n = nx * ny;
    let edges = grid_edges(nx, ny);
    let mut a = BlockSym3::from_pattern(n, edges.iter().copied());
    let mut dom = vec![0.0; n];
    for &(i, j) in &edges {
        let w = 1.0 + 0.5 * rng.sym();
        let mut b = [0.0; 9];
        for (q, v) in b.iter_mut().enumerate() {
            *v = 0.2 * w * rng.sym() + if q % 4 == 0 { -w } else { 0.0 };
        }
        let norm = b.iter().map(|v| v * v).sum::<f64>().sqrt();
        dom[i] += norm;
        dom[j] += norm;
        a.add_block(j.max(i), j.min(i), &b);
    }
    for (i, d) in dom.iter().enumerate() {
        let s = 0.1 * shift * d * rng.sym().abs();
        let off = [0.3 * s, -0.2 * s, 0.1 * s];
        let m = [
            d * (1.0 + shift),
            off[0],
            off[1],
            off[0],
            d * (1.0 + shift),
            off[2],
            off[1],
            off[2],
            d * (1.0 + shift),
        ];
        a.add_block(i, i, &m);
    }
    a
}

/// The scalar copy (with the fixed-vertex identity rows) the CPU uses.
fn scalar_of(a: &BlockSym3, fixed: &[bool]) -> SymCsc {
    let mut s = a.scalar_pattern();
    a.fill_scalar(&mut s, fixed);
    s
}

/// Face-adjacency-like scalar SPD matrix: ~4 off-diagonals a row.
fn spd_scalar(n: usize, rng: &mut Rng) -> SymCsc {
    let mut pairs = Vec::new();
    for i in 0..n {
        pairs.push((i, (i + 1) % n));
        pairs.push((i, (i + 37) % n));
    }
    let mut s = SymCsc::from_pattern(n, pairs.iter().copied());
    let mut dom = vec![0.0; n];
    for c in 0..n {
        for k in s.col_ptr[c]..s.col_ptr[c + 1] {
            let r = s.row_idx[k];
            if r != c {
                let v = -(1.0 + 0.5 * rng.sym());
                s.values[k] = v;
                dom[r] += v.abs();
                dom[c] += v.abs();
            }
        }
    }
    for (i, d) in dom.iter().enumerate() {
        let k = s.slot(i, i).unwrap();
        s.values[k] = d * 1.01 + 1e-3;
    }
    s
}

fn fixed_every(n: usize, k: usize) -> Vec<bool> {
    (0..n).map(|v| v % k == 3).collect()
}

fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    let n: f64 = b.iter().map(|y| y * y).sum();
    (d / n).sqrt()
}

fn f32s(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// The GPU block SpMV of `a` (held rows `fixed`, already prepared on `s`)
/// against the CPU product, for 1 to 8 columns.
fn check_block_spmv(s: &GpuSolver, a: &BlockSym3, fixed: &[bool], rng: &mut Rng) {
    let cpu = scalar_of(a, fixed);
    let n = 3 * a.n;
    for ncols in [1, 2, 5, 8] {
        let x = f32s(&rng.vec(n * ncols));
        let (y, dots) = kernels::spmv(s, &x, ncols).unwrap();
        for c in 0..ncols {
            let xc: Vec<f64> = x[c * n..(c + 1) * n].iter().map(|&v| v as f64).collect();
            let mut yc = vec![0.0; n];
            cpu.mul_vec(&xc, &mut yc);
            let yg: Vec<f64> = y[c * n..(c + 1) * n].iter().map(|&v| v as f64).collect();
            let e = rel_err(&yg, &yc);
            assert!(e < 1e-6, "ncols {ncols} column {c}: relative error {e:e}");
            let d: f64 = xc.iter().zip(&yc).map(|(a, b)| a * b).sum();
            let scale: f64 = xc.iter().zip(&yc).map(|(a, b)| (a * b).abs()).sum();
            assert!(
                (dots[c] - d).abs() < 1e-5 * scale,
                "ncols {ncols} column {c}: x.Ax {} vs {d}",
                dots[c]
            );
        }
    }
}

#[test]
fn block_spmv_matches_cpu_for_1_to_8_columns() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(1);
    let a = spd_blocks(23, 17, 0.1, &mut rng);
    let fixed = fixed_every(a.n, 11);
    s.prepare_blocks(&a, &fixed).unwrap();
    check_block_spmv(&s, &a, &fixed, &mut rng);
}

#[test]
fn block_matrix_past_the_binding_limit_is_split_into_chunks_that_match_cpu() {
    // A binding limit of 40 KiB: the ~2.7k blocks of this matrix (36 bytes of
    // values each, ~98 KB) are split by block rows into chunks, one dispatch
    // each; the vectors (8 columns of 1173 f32) still fit one binding. The
    // product, its fused x . Ax partials, new values of the same pattern and
    // a PCG solve must all match the CPU.
    let limit = 40 * 1024;
    let Some(mut s) = gpu_with_limits(move |l| l.max_storage_buffer_binding_size = limit) else {
        return;
    };
    // Block Jacobi: the AMG's dense coarsest inverse would pass this limit.
    s.set_preconditioner(Preconditioner::BlockJacobi).unwrap();
    let mut rng = Rng(12);
    let mut a = spd_blocks(23, 17, 0.1, &mut rng);
    let nnz = 2 * a.row_idx.len() - a.n;
    assert!(
        nnz as u64 * 36 > 2 * limit,
        "{nnz} blocks fit in too few chunks"
    );
    let fixed = fixed_every(a.n, 13);
    s.prepare_blocks(&a, &fixed).unwrap();
    let chunks = kernels::matrix_chunks(&s);
    assert!(chunks.len() >= 3, "chunks {chunks:?}");
    assert_eq!(chunks.first().unwrap().start, 0);
    assert_eq!(chunks.last().unwrap().end, a.n);
    // Some chunk starts inside a workgroup's 128 rows: the partial slots
    // of the chunks are not the row kernels' own.
    assert!(chunks.iter().any(|r| r.start % 128 != 0), "{chunks:?}");
    check_block_spmv(&s, &a, &fixed, &mut rng);
    // Same pattern, new values: written into the same chunks.
    for b in a.blocks.iter_mut() {
        for v in b.iter_mut() {
            *v *= 1.5;
        }
    }
    a.add_scalar(5, 5, 2.0);
    s.prepare_blocks(&a, &fixed).unwrap();
    assert_eq!(kernels::matrix_chunks(&s), chunks);
    check_block_spmv(&s, &a, &fixed, &mut rng);
    // The PCG over the chunked product against Cholesky.
    let b = rng.vec(3 * a.n * 2);
    let mut x = b.clone();
    s.solve_in_place(&mut x, 2).unwrap();
    let want = cholesky_solution(&a, &fixed, &b, 2);
    let e = rel_err(&x, &want);
    assert!(e < 1e-8, "PCG on the chunked matrix vs Cholesky: {e:e}");
    // Without the lowered limit the same matrix is one chunk.
    let Some(mut one) = gpu() else { return };
    one.prepare_blocks(&a, &fixed).unwrap();
    assert_eq!(kernels::matrix_chunks(&one), vec![0..a.n]);
}

#[test]
fn scalar_csr_spmv_matches_cpu() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(2);
    let a = spd_scalar(1000, &mut rng);
    s.prepare(&a).unwrap();
    for ncols in [1, 3] {
        let x = f32s(&rng.vec(a.n * ncols));
        let (y, dots) = kernels::spmv(&s, &x, ncols).unwrap();
        for c in 0..ncols {
            let xc: Vec<f64> = x[c * a.n..(c + 1) * a.n]
                .iter()
                .map(|&v| v as f64)
                .collect();
            let mut yc = vec![0.0; a.n];
            a.mul_vec(&xc, &mut yc);
            let yg: Vec<f64> = y[c * a.n..(c + 1) * a.n]
                .iter()
                .map(|&v| v as f64)
                .collect();
            assert!(rel_err(&yg, &yc) < 1e-6);
            let d: f64 = xc.iter().zip(&yc).map(|(a, b)| a * b).sum();
            let scale: f64 = xc.iter().zip(&yc).map(|(a, b)| (a * b).abs()).sum();
            assert!((dots[c] - d).abs() < 1e-5 * scale);
        }
    }
}

#[test]
fn dot_products_two_pass() {
    let Some(s) = gpu() else { return };
    let mut rng = Rng(3);
    // Lengths: one partial workgroup, several, and more partials than the final
    // workgroup has invocations.
    for (n, ncols) in [(77, 1), (5000, 3), (100_003, 8)] {
        let a = f32s(&rng.vec(n * ncols));
        let b = f32s(&rng.vec(n * ncols));
        let d = kernels::dot(&s, &a, &b, ncols).unwrap();
        assert_eq!(d.len(), ncols);
        for (c, &dc) in d.iter().enumerate() {
            let r = c * n..(c + 1) * n;
            let exact: f64 = a[r.clone()]
                .iter()
                .zip(&b[r.clone()])
                .map(|(x, y)| *x as f64 * *y as f64)
                .sum();
            let scale: f64 = a[r.clone()]
                .iter()
                .zip(&b[r])
                .map(|(x, y)| (*x as f64 * *y as f64).abs())
                .sum();
            assert!(
                (dc as f64 - exact).abs() < 1e-5 * scale,
                "n {n} column {c}: {dc} vs {exact}"
            );
        }
    }
}

#[test]
fn block_jacobi_apply_inverts_the_diagonal_blocks() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(4);
    let a = spd_blocks(13, 11, 0.1, &mut rng);
    let fixed = fixed_every(a.n, 7);
    s.prepare_blocks(&a, &fixed).unwrap();
    let n = 3 * a.n;
    let ncols = 3;
    let r = f32s(&rng.vec(n * ncols));
    let z = kernels::block_jacobi(&s, &r, ncols).unwrap();
    // D z = r per vertex block, D the diagonal block (identity where fixed).
    for c in 0..ncols {
        for (v, &fv) in fixed.iter().enumerate() {
            let (k, _) = a.slot(v, v).unwrap();
            let d = if fv {
                [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            } else {
                a.blocks[k]
            };
            let o = c * n + 3 * v;
            for q in 0..3 {
                let dz: f64 = (0..3).map(|t| d[3 * q + t] * z[o + t] as f64).sum();
                let rv = r[o + q] as f64;
                assert!(
                    (dz - rv).abs() < 1e-5 * rv.abs().max(1.0),
                    "vertex {v}: {dz} vs {rv}"
                );
            }
        }
    }
    // Scalar: plain Jacobi.
    let sa = spd_scalar(300, &mut rng);
    s.prepare(&sa).unwrap();
    let r = f32s(&rng.vec(sa.n));
    let z = kernels::block_jacobi(&s, &r, 1).unwrap();
    for i in 0..sa.n {
        let d = sa.values[sa.slot(i, i).unwrap()];
        assert!((d * z[i] as f64 - r[i] as f64).abs() < 1e-5);
    }
}

#[test]
fn pcg_solve_matches_cholesky_with_fixed_vertices() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(5);
    let a = spd_blocks(40, 35, 0.05, &mut rng);
    let fixed = fixed_every(a.n, 50);
    let n = 3 * a.n;
    s.prepare_blocks(&a, &fixed).unwrap();
    let mut cpu = CholeskySolver::new();
    cpu.prepare_blocks(&a, &fixed).unwrap();
    let b = rng.vec(n);
    let mut x = b.clone();
    let info = s.solve_in_place(&mut x, 1).unwrap();
    let mut xc = b.clone();
    cpu.solve_in_place(&mut xc, 1).unwrap();
    let e = rel_err(&x, &xc);
    assert!(e < 1e-8, "GPU vs Cholesky: {e:e} ({info:?})");
    assert!(info.residual <= 1e-10 && info.iterations > 0, "{info:?}");
    // Fixed vertices: identity rows, x = b there.
    for v in (0..a.n).filter(|&v| fixed[v]) {
        for q in 0..3 {
            assert!((x[3 * v + q] - b[3 * v + q]).abs() < 1e-9 * b[3 * v + q].abs());
        }
    }
    eprintln!("one column: {info:?}, {:?}", s.last_stats());
}

#[test]
fn multiple_right_hand_sides_together_and_in_batches() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(6);
    let a = spd_blocks(30, 20, 0.05, &mut rng);
    let fixed = fixed_every(a.n, 40);
    let n = 3 * a.n;
    s.prepare_blocks(&a, &fixed).unwrap();
    let mut cpu = CholeskySolver::new();
    cpu.prepare_blocks(&a, &fixed).unwrap();
    for ncols in [5, 11] {
        let mut b = rng.vec(n * ncols);
        // A zero column is solved trivially.
        b[2 * n..3 * n].fill(0.0);
        let mut x = b.clone();
        let info = s.solve_in_place(&mut x, ncols).unwrap();
        let mut xc = b.clone();
        cpu.solve_in_place(&mut xc, ncols).unwrap();
        for c in 0..ncols {
            let r = c * n..(c + 1) * n;
            if c == 2 {
                assert!(x[r].iter().all(|&v| v == 0.0));
                continue;
            }
            let e = rel_err(&x[r.clone()], &xc[r]);
            assert!(e < 1e-8, "{ncols} columns, column {c}: {e:e}");
        }
        assert!(info.residual <= 1e-10);
    }
}

#[test]
fn scalar_system_matches_cholesky() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(7);
    let a = spd_scalar(5000, &mut rng);
    s.prepare(&a).unwrap();
    let mut cpu = CholeskySolver::new();
    cpu.prepare(&a).unwrap();
    let b = rng.vec(2 * a.n);
    let mut x = b.clone();
    s.solve_in_place(&mut x, 2).unwrap();
    let mut xc = b.clone();
    cpu.solve_in_place(&mut xc, 2).unwrap();
    assert!(rel_err(&x, &xc) < 1e-8);
}

#[test]
fn same_pattern_uploads_values_only_and_warm_start_saves_iterations() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(8);
    let mut a = spd_blocks(40, 40, 0.02, &mut rng);
    let fixed = fixed_every(a.n, 60);
    let n = 3 * a.n;
    s.prepare_blocks(&a, &fixed).unwrap();
    let b = rng.vec(n);
    let mut x0 = vec![0.0; n];
    s.solve_with_guess(&b, &mut x0, 1).unwrap();
    // Next "outer iteration": same pattern, slightly different values.
    for blk in a.blocks.iter_mut() {
        for v in blk.iter_mut() {
            *v *= 1.0 + 1e-4 * rng.sym().abs();
        }
    }
    s.prepare_blocks(&a, &fixed).unwrap();
    assert_eq!((s.pattern_uploads, s.value_uploads), (1, 1));
    let mut cold = vec![0.0; n];
    let ci = s.solve_with_guess(&b, &mut cold, 1).unwrap();
    let mut warm = x0.clone();
    let wi = s.solve_with_guess(&b, &mut warm, 1).unwrap();
    assert!(rel_err(&warm, &cold) < 1e-8);
    eprintln!("cold {ci:?}, warm {wi:?}");
    assert!(
        wi.iterations < ci.iterations,
        "warm start {} iterations, cold {}",
        wi.iterations,
        ci.iterations
    );
}

#[test]
fn iteration_cap_gives_no_convergence_instead_of_hanging() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(9);
    let a = spd_blocks(40, 40, 0.01, &mut rng);
    let fixed = vec![false; a.n];
    s.prepare_blocks(&a, &fixed).unwrap();
    s.set_max_iterations(5);
    let mut x = rng.vec(3 * a.n);
    match s.solve_in_place(&mut x, 1) {
        Err(SolverError::NoConvergence {
            iterations,
            residual,
        }) => {
            assert!(iterations <= 32, "{iterations}");
            assert!(residual > 1e-10);
        }
        other => panic!("expected NoConvergence, got {other:?}"),
    }
    // The limit is lifted: the same solver converges.
    s.set_max_iterations(100_000);
    let mut x = rng.vec(3 * a.n);
    s.solve_in_place(&mut x, 1).unwrap();
}

#[test]
fn buffer_over_the_binding_limit_is_a_typed_error() {
    // Lower the device's binding limit so that a small matrix exceeds it.
    let Some(mut s) = gpu_with_limits(|l| l.max_storage_buffer_binding_size = 4096) else {
        return;
    };
    assert_eq!(s.limits().max_storage_buffer_binding_size, 4096);
    let mut rng = Rng(10);
    // A scalar matrix keeps its values in a storage buffer: 5000 rows are
    // well over 4096 bytes.
    let a = spd_scalar(5000, &mut rng);
    let err = s.prepare(&a).unwrap_err();
    match &err {
        SolverError::Backend(msg) => assert!(
            msg.contains("max_storage_buffer_binding_size") && msg.contains("matrix values"),
            "{msg}"
        ),
        other => panic!("expected a limit error, got {other:?}"),
    }
    let mut x = vec![1.0; a.n];
    assert_eq!(s.solve_in_place(&mut x, 1), Err(SolverError::NotPrepared));
}

#[test]
fn amg_solves_a_block_matrix_past_the_storage_binding_limit() {
    // Every matrix of the AMG hierarchy (and the PCG's block matrix, which is
    // its finest A) is split by block rows into chunks that fit one binding,
    // so a binding limit that the matrices' values pass by far, but the
    // vectors fit in, still gives an AMG solve.
    let limit = 16 * 1024;
    let Some(mut s) = gpu_with_limits(move |l| l.max_storage_buffer_binding_size = limit) else {
        return;
    };
    s.set_preconditioner(Preconditioner::Amg).unwrap();
    s.set_amg_options(solver_gpu::amg::AmgOptions {
        max_coarse: 60,
        ..Default::default()
    });
    let mut rng = Rng(12);
    let a = laplacian_blocks(20, 20, &mut rng);
    let fixed = fixed_every(a.n, 50);
    s.prepare_blocks(&a, &fixed).unwrap();
    let chunks = kernels::matrix_chunks(&s).len();
    assert!(chunks >= 4, "{chunks} chunks");
    let h = s.amg_hierarchy().expect("AMG in use").clone();
    assert!(h.levels.len() >= 2, "levels {:?}", h.sizes());
    let value_bytes = |m: &solver_gpu::amg::Bsr| m.vals.len() as u64 * 4;
    let fine = &h.levels[0];
    assert!(value_bytes(&fine.a) > 4 * limit && value_bytes(&fine.p) > limit);
    // The chunked V-cycle against the f64 reference of the hierarchy.
    let e = vcycle_error(&mut s, &h, 2, &mut rng);
    assert!(e < 1e-4, "chunked V-cycle: {e:e} (levels {:?})", h.sizes());
    let n = 3 * a.n;
    let b = rng.vec(n);
    let mut x = b.clone();
    s.solve_in_place(&mut x, 1).unwrap();
    let want = cholesky_solution(&a, &fixed, &b, 1);
    let e = rel_err(&x, &want);
    assert!(e < 1e-8, "AMG past the binding limit vs Cholesky: {e:e}");
}

#[test]
fn affine_amg_vcycle_past_the_storage_binding_limit_matches_the_reference() {
    // The wide blocks of an affine hierarchy (3 x 12 P, 12 x 3 R, 12 x 12
    // coarse A) split into chunks like the 3x3 ones: the V-cycle still
    // matches the f64 reference.
    let limit = 48 * 1024;
    let Some(mut s) = gpu_with_limits(move |l| l.max_storage_buffer_binding_size = limit) else {
        return;
    };
    let (_, _, h) = affine_amg_on_sheet(&mut s, 24, 20, 60);
    let value_bytes = |m: &solver_gpu::amg::Bsr| m.vals.len() as u64 * 4;
    let fine = &h.levels[0];
    assert!(
        value_bytes(&fine.a) > 2 * limit && value_bytes(&fine.p) > limit,
        "A {} P {} bytes",
        value_bytes(&fine.a),
        value_bytes(&fine.p)
    );
    let mut rng = Rng(43);
    for ncols in [1, 3] {
        let e = vcycle_error(&mut s, &h, ncols, &mut rng);
        assert!(e < 1e-4, "{ncols} columns: {e:e} (levels {:?})", h.sizes());
    }
}

#[test]
fn block_row_over_the_binding_limit_is_a_typed_error() {
    // A matrix is split between block rows, never inside one: a star whose
    // centre row holds 40 blocks (1440 bytes of values) cannot fit a 1 KiB
    // binding, however it is chunked.
    let Some(mut s) = gpu_with_limits(|l| l.max_storage_buffer_binding_size = 1024) else {
        return;
    };
    s.set_preconditioner(Preconditioner::BlockJacobi).unwrap();
    let mut rng = Rng(11);
    let n = 40;
    let mut a = BlockSym3::from_pattern(n, (1..n).map(|i| (i, 0)));
    let id = |v: f64| [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v];
    for i in 1..n {
        a.add_block(i, 0, &id(-0.1));
        a.add_block(i, i, &id(1.0));
    }
    a.add_block(0, 0, &id(1.0 + 0.1 * n as f64));
    let err = s.prepare_blocks(&a, &vec![false; a.n]).unwrap_err();
    match &err {
        SolverError::Backend(msg) => assert!(
            msg.contains("max_storage_buffer_binding_size")
                && msg.contains("block matrix")
                && msg.contains("block row 0"),
            "{msg}"
        ),
        other => panic!("expected a limit error, got {other:?}"),
    }
    let mut x = vec![1.0; 3 * a.n];
    assert_eq!(s.solve_in_place(&mut x, 1), Err(SolverError::NotPrepared));
    // A matrix that fits is solved by the same device.
    let small = spd_blocks(4, 4, 0.1, &mut rng);
    s.prepare_blocks(&small, &vec![false; small.n]).unwrap();
    let mut x = rng.vec(3 * small.n);
    s.solve_in_place(&mut x, 1).unwrap();
}

#[test]
fn indefinite_matrices_are_reported() {
    let Some(mut s) = gpu() else { return };
    // Negative diagonal block: caught when the preconditioner is built.
    let mut a = BlockSym3::from_pattern(2, [(1, 0)]);
    a.add_scalar(0, 0, -1.0);
    a.add_scalar(1, 1, 1.0);
    assert_eq!(
        s.prepare_blocks(&a, &[false, false]),
        Err(SolverError::NotPositiveDefinite)
    );
    // Positive diagonal, indefinite matrix [[I, 2I], [2I, I]]: PCG breakdown.
    let mut a = BlockSym3::from_pattern(2, [(1, 0)]);
    a.add_scalar(0, 0, 1.0);
    a.add_scalar(1, 1, 1.0);
    a.add_scalar(1, 0, 2.0);
    s.prepare_blocks(&a, &[false, false]).unwrap();
    let mut x = vec![1.0, 1.0, 1.0, -1.0, -1.0, -1.0];
    assert_eq!(
        s.solve_in_place(&mut x, 1),
        Err(SolverError::NotPositiveDefinite)
    );
}

#[test]
fn plain_f32_pcg_converges() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(11);
    let a = spd_blocks(30, 30, 0.05, &mut rng);
    let fixed = fixed_every(a.n, 30);
    s.prepare_blocks(&a, &fixed).unwrap();
    let n = 3 * a.n;
    let b = f32s(&rng.vec(2 * n));
    let out = kernels::pcg(&mut s, &b, 2, 1e-5, 10_000).unwrap();
    assert_eq!(out.status, vec![1, 1]);
    assert!(out.residual.iter().all(|&r| r <= 1e-5));
    // True residual in f64 of the f32 solution.
    let cpu = scalar_of(&a, &fixed);
    for c in 0..2 {
        let xc = &out.x[c * n..(c + 1) * n];
        let mut ax = vec![0.0; n];
        cpu.mul_vec(xc, &mut ax);
        let bc: Vec<f64> = b[c * n..(c + 1) * n].iter().map(|&v| v as f64).collect();
        assert!(rel_err(&ax, &bc) < 1e-4);
    }
}

#[test]
fn f64_kernels_converge_past_f32_precision() {
    let Some(mut s) = gpu() else { return };
    if !s.adapter().shader_f64 {
        eprintln!("skipped: adapter {} has no SHADER_F64", s.adapter_name());
        return;
    }
    let mut rng = Rng(13);
    let a = laplacian_blocks(24, 20, &mut rng);
    let fixed = fixed_every(a.n, 40);
    s.prepare_blocks(&a, &fixed).unwrap();
    let n = 3 * a.n;
    let b = rng.vec(2 * n);
    let cpu_a = scalar_of(&a, &fixed);
    let true_residual = |x: &[f64], c: usize| {
        let mut ax = vec![0.0; n];
        cpu_a.mul_vec(&x[c * n..(c + 1) * n], &mut ax);
        rel_err(&ax, &b[c * n..(c + 1) * n])
    };
    // f64 kernels straight to 1e-11, far below what f32 vectors can hold.
    let f64_run =
        kernels::scalar_pcg(&mut s, kernels::Precision::F64, &b, 2, 1e-11, 20_000).unwrap();
    assert_eq!(f64_run.status, vec![1, 1]);
    let want = cholesky_solution(&a, &fixed, &b, 2);
    for c in 0..2 {
        let r = true_residual(&f64_run.x, c);
        assert!(r < 1e-10, "f64 column {c}: true residual {r:e}");
        let e = rel_err(&f64_run.x[c * n..(c + 1) * n], &want[c * n..(c + 1) * n]);
        assert!(e < 1e-7, "f64 column {c} vs Cholesky: {e:e}");
    }
    // The same kernels in f32 and f64 run the same algorithm: to a tolerance
    // both reach, their iteration counts agree closely.
    let mut loose = |p| kernels::scalar_pcg(&mut s, p, &b, 2, 1e-4, 20_000).unwrap();
    let (r32, r64) = (
        loose(kernels::Precision::F32),
        loose(kernels::Precision::F64),
    );
    assert_eq!(
        (r32.status.clone(), r64.status.clone()),
        (vec![1, 1], vec![1, 1])
    );
    for c in 0..2 {
        let (i32_, i64_) = (r32.iterations[c] as f64, r64.iterations[c] as f64);
        assert!(
            (i32_ - i64_).abs() <= 0.05 * i64_ + 2.0,
            "column {c}: f32 {i32_} vs f64 {i64_} iterations"
        );
        assert!(true_residual(&r32.x, c) < 2e-4);
    }
    eprintln!(
        "scalar Jacobi PCG: f64 to 1e-11 in {:?} iterations; to 1e-4 f32 {:?}, f64 {:?}",
        f64_run.iterations, r32.iterations, r64.iterations
    );
}

/// `L^2 (x) I3` for the 5-point Laplacian `L` of an `nx x ny` grid with a
/// Dirichlet boundary (`L = 4 I - adjacency`), SPD.
fn biharmonic_blocks(nx: usize, ny: usize) -> BlockSym3 {
    let n = nx * ny;
    let lap = |i: usize| {
        let (x, y) = (i % nx, i / nx);
        let mut row = vec![(i, 4.0)];
        if x > 0 {
            row.push((i - 1, -1.0));
        }
        if x + 1 < nx {
            row.push((i + 1, -1.0));
        }
        if y > 0 {
            row.push((i - nx, -1.0));
        }
        if y + 1 < ny {
            row.push((i + nx, -1.0));
        }
        row
    };
    // (L^2)_ij = sum_k L_ik L_kj, lower triangle.
    let mut entries = std::collections::BTreeMap::new();
    for i in 0..n {
        for (k, lik) in lap(i) {
            for (j, lkj) in lap(k) {
                if j <= i {
                    *entries.entry((i, j)).or_insert(0.0) += lik * lkj;
                }
            }
        }
    }
    let mut a = BlockSym3::from_pattern(n, entries.keys().filter(|(i, j)| i != j).copied());
    for (&(i, j), &v) in &entries {
        a.add_scalar(i, j, v);
    }
    a
}

/// The CPU Cholesky solution of `a` (held vertices `fixed`) for the `ncols`
/// column-major right-hand sides `b`: the reference of the GPU solves.
fn cholesky_solution(a: &BlockSym3, fixed: &[bool], b: &[f64], ncols: usize) -> Vec<f64> {
    let mut cpu = CholeskySolver::new();
    cpu.prepare_blocks(a, fixed).unwrap();
    let mut x = b.to_vec();
    cpu.solve_in_place(&mut x, ncols).unwrap();
    x
}

/// An adapter with SHADER_F64, or None (skipped with a message).
fn gpu_f64() -> Option<Gpu> {
    let s = gpu()?;
    if !s.adapter().shader_f64 {
        eprintln!("skipped: adapter {} has no SHADER_F64", s.adapter_name());
        return None;
    }
    Some(s)
}

#[test]
fn a_tolerance_below_the_f64_rounding_floor_ends_at_the_floor() {
    let Some(mut s) = gpu_f64() else { return };
    let (nx, ny) = (40, 40);
    let a = biharmonic_blocks(nx, ny);
    let fixed = vec![false; a.n];
    let n = 3 * a.n;
    // A smooth right-hand side: a large solution, so eps ||A|| ||x|| / ||b||
    // is far above the asked 1e-15.
    let b: Vec<f64> = (0..n)
        .map(|i| 1.0 + 0.1 * ((i / 3) as f64 * 0.01).sin())
        .collect();
    let xc = cholesky_solution(&a, &fixed, &b, 1);
    let norm = |v: &[f64]| v.iter().map(|t| t * t).sum::<f64>().sqrt();
    let anorm = 64.0; // ||A||_inf of the biharmonic stencil: 20 + 4 x 8 + 4 x 2 + 4 x 1
    let floor = f64::EPSILON * anorm * norm(&xc) / norm(&b);
    assert!(
        floor > 1e-13,
        "floor {floor:e}: the case must sit well above 1e-15"
    );
    s.prepare_blocks(&a, &fixed).unwrap();
    s.set_tolerance(1e-15);
    let mut x = b.clone();
    let info = s.solve_in_place(&mut x, 1).unwrap();
    assert!(
        info.residual <= floor,
        "{info:?} against the floor {floor:e}"
    );
    assert!(rel_err(&x, &xc) < 1e-6, "{:e}", rel_err(&x, &xc));
}

#[test]
fn mixed_precision_solve_matches_cholesky() {
    let Some(mut s) = gpu_f64() else { return };
    s.set_preconditioner(Preconditioner::Amg).unwrap();
    s.set_mixed_precision(MixedPrecision::Always);
    let mut rng = Rng(61);
    let a = laplacian_blocks(50, 40, &mut rng);
    let fixed = fixed_every(a.n, 70);
    s.prepare_blocks(&a, &fixed).unwrap();
    let n = 3 * a.n;
    let b = rng.vec(3 * n);
    let mut x = b.clone();
    s.solve_in_place(&mut x, 3).unwrap();
    assert!(s.last_solve_mixed());
    let mut cpu = CholeskySolver::new();
    cpu.prepare_blocks(&a, &fixed).unwrap();
    let mut want = b;
    cpu.solve_in_place(&mut want, 3).unwrap();
    for c in 0..3 {
        let cols = c * n..(c + 1) * n;
        let e = rel_err(&x[cols.clone()], &want[cols]);
        assert!(e < 1e-8, "column {c}: {e:e}");
    }
    // New values, same pattern: the f64 copy of the matrix follows.
    let a2 = laplacian_blocks(50, 40, &mut Rng(62));
    s.prepare_blocks(&a2, &fixed).unwrap();
    let b2 = rng.vec(n);
    let mut x2 = b2.clone();
    s.solve_in_place(&mut x2, 1).unwrap();
    cpu.prepare_blocks(&a2, &fixed).unwrap();
    let mut want2 = b2;
    cpu.solve_in_place(&mut want2, 1).unwrap();
    assert!(rel_err(&x2, &want2) < 1e-8);
}

#[test]
fn mixed_precision_solve_past_the_storage_binding_limit() {
    // The mixed-precision PCG's f64 block matrix is two f32 parts (high: the
    // f32 matrix's own buffers; low) in the f32 matrix's chunks, so a binding
    // limit that an f64 copy of the values (9 x 8 bytes per block) passes 10
    // times over, and that the f64 vectors fit in, still gives a
    // mixed-precision solve.
    let limit = 24 * 1024;
    let Some(mut s) = gpu_with_limits(move |l| l.max_storage_buffer_binding_size = limit) else {
        return;
    };
    if !s.adapter().shader_f64 {
        return eprintln!("skipped: adapter {} has no SHADER_F64", s.adapter_name());
    }
    s.set_preconditioner(Preconditioner::Amg).unwrap();
    s.set_mixed_precision(MixedPrecision::Always);
    s.set_amg_options(solver_gpu::amg::AmgOptions {
        max_coarse: 60,
        ..Default::default()
    });
    let mut rng = Rng(65);
    let a = laplacian_blocks(25, 25, &mut rng);
    let fixed = fixed_every(a.n, 40);
    s.prepare_blocks(&a, &fixed).unwrap();
    let chunks = kernels::matrix_chunks(&s).len();
    assert!(chunks >= 5, "{chunks} chunks");
    let n = 3 * a.n;
    assert!(n as u64 * 8 <= limit, "one f64 column must fit");
    let nnzb = a.blocks.len() * 2 - a.n; // both triangles
    assert!(nnzb as u64 * 72 > 10 * limit, "{nnzb} blocks");
    let b = rng.vec(n);
    let mut x = b.clone();
    s.solve_in_place(&mut x, 1).unwrap();
    assert!(s.last_solve_mixed());
    assert_eq!(s.last_stats().f32_rounds, 0);
    let want = cholesky_solution(&a, &fixed, &b, 1);
    let e = rel_err(&x, &want);
    assert!(
        e < 1e-8,
        "mixed precision past the binding limit vs Cholesky: {e:e}"
    );
}

#[test]
fn f32_refinement_that_stops_short_falls_back_to_mixed_precision() {
    let Some(mut s) = gpu_f64() else { return };
    s.set_preconditioner(Preconditioner::Amg).unwrap();
    // One f32 round (inner tolerance 1e-3) cannot reach 1e-10: the same
    // branch as a stagnating refinement (three rounds without halving the
    // residual) hands the solve to the mixed-precision PCG.
    s.set_max_rounds(1);
    s.set_inner_tolerance(1e-3);
    let mut rng = Rng(63);
    let a = biharmonic_blocks(40, 40);
    let fixed = vec![false; a.n];
    s.prepare_blocks(&a, &fixed).unwrap();
    let n = 3 * a.n;
    let b = rng.vec(n);
    let true_residual = |x: &[f64]| {
        let mut ax = vec![0.0; n];
        scalar_of(&a, &fixed).mul_vec(x, &mut ax);
        rel_err(&ax, &b)
    };
    s.set_mixed_precision(MixedPrecision::Never);
    let mut x = b.clone();
    match s.solve_in_place(&mut x, 1) {
        Err(SolverError::NoConvergence { .. }) => {}
        other => panic!("f32 refinement alone: expected NoConvergence, got {other:?}"),
    }
    assert!(!s.last_solve_mixed());
    assert_eq!(s.last_stats().f32_rounds, 1);
    s.set_mixed_precision(MixedPrecision::Fallback);
    let mut x = b.clone();
    s.solve_in_place(&mut x, 1).unwrap();
    assert!(s.last_solve_mixed());
    assert_eq!(s.last_stats().f32_rounds, 1);
    let r = true_residual(&x);
    assert!(r < 2e-10, "true residual {r:e}");
    // The pattern needed the fallback once: the next solve starts there.
    let mut x = b.clone();
    s.solve_in_place(&mut x, 1).unwrap();
    assert!(s.last_solve_mixed());
    assert_eq!(s.last_stats().f32_rounds, 0);
    assert!(true_residual(&x) < 2e-10);
    // A new pattern starts with f32 refinement again.
    let small = biharmonic_blocks(12, 10);
    s.set_max_rounds(20);
    s.prepare_blocks(&small, &vec![false; small.n]).unwrap();
    let mut y = Rng(64).vec(3 * small.n);
    s.solve_in_place(&mut y, 1).unwrap();
    assert!(!s.last_solve_mixed());
    assert!(s.last_stats().f32_rounds >= 1);
}

/// Badly conditioned SPD block matrix like the shape systems: a weighted grid
/// Laplacian with per-edge SPD 3x3 couplings (`sum_e w_e (e_i - e_j)(e_i - e_j)^T
/// (x) K_e`) plus a small mass term.
fn laplacian_blocks(nx: usize, ny: usize, rng: &mut Rng) -> BlockSym3 {
    let n = nx * ny;
    let edges = grid_edges(nx, ny);
    let mut a = BlockSym3::from_pattern(n, edges.iter().copied());
    let mut diag = vec![[0.0; 9]; n];
    for &(i, j) in &edges {
        let w = 1.0 + 0.5 * rng.sym();
        let (p, q, r) = (0.1 * rng.sym(), 0.1 * rng.sym(), 0.1 * rng.sym());
        let k = [1.0, p, q, p, 1.0, r, q, r, 1.0];
        let off = k.map(|v| -w * v);
        a.add_block(j.max(i), j.min(i), &off);
        for d in [i, j] {
            for (o, kv) in diag[d].iter_mut().zip(&k) {
                *o += w * kv;
            }
        }
    }
    for (i, mut d) in diag.into_iter().enumerate() {
        for q in [0, 4, 8] {
            d[q] += 1e-3;
        }
        a.add_block(i, i, &d);
    }
    a
}

/// Iterations of the whole solve (all rounds) with each preconditioner.
fn iterations_with(
    s: &mut GpuSolver,
    p: Preconditioner,
    b: &[f64],
    ncols: usize,
) -> (Vec<f64>, usize) {
    s.set_preconditioner(p).unwrap();
    assert_eq!(s.active_preconditioner(), p);
    let mut x = b.to_vec();
    let info = s.solve_in_place(&mut x, ncols).unwrap();
    assert!(info.residual <= 1e-10, "{p:?}: {info:?}");
    (x, info.iterations)
}

/// The largest relative difference, over `ncols` random columns, between the
/// GPU V-cycle (f32) and the f64 reference of `h`.
fn vcycle_error(
    s: &mut GpuSolver,
    h: &solver_gpu::amg::Hierarchy,
    ncols: usize,
    rng: &mut Rng,
) -> f64 {
    let n = h.n();
    let r = rng.vec(n * ncols);
    let z = kernels::amg_vcycle(s, &f32s(&r), ncols).unwrap();
    (0..ncols)
        .map(|c| {
            let want = h.vcycle(&r[c * n..(c + 1) * n]);
            let got: Vec<f64> = z[c * n..(c + 1) * n].iter().map(|&v| v as f64).collect();
            rel_err(&got, &want)
        })
        .fold(0.0, f64::max)
}

#[test]
fn amg_vcycle_matches_the_cpu_reference() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(21);
    // Blocks: several levels (small coarse limit to exercise the recursion).
    s.set_amg_options(solver_gpu::amg::AmgOptions {
        max_coarse: 90,
        ..Default::default()
    });
    let a = spd_blocks(45, 40, 0.02, &mut rng);
    let fixed = fixed_every(a.n, 40);
    let a2 = spd_blocks(45, 40, 0.5, &mut Rng(22));
    // 1. The hierarchy of `a`.
    s.set_system_kind(SystemKind::ScaleDriven);
    let uploads = s.pattern_uploads;
    s.prepare_blocks(&a, &fixed).unwrap();
    assert_eq!(s.pattern_uploads, uploads + 1);
    let h = s.amg_hierarchy().unwrap().clone();
    assert!(h.levels.len() >= 2, "levels {:?}", h.sizes());
    for ncols in [1, 3] {
        let e = vcycle_error(&mut s, &h, ncols, &mut rng);
        assert!(
            e < 1e-4,
            "bs 3, {ncols} columns: {e:e} (levels {:?})",
            h.sizes()
        );
    }
    // 2. New values of the same kind and pattern: one set-up per kind, so the
    // hierarchy is kept; the finest A of the V-cycle is the PCG's own matrix
    // (values-only upload) and the finest smoother's diagonal is rewritten.
    let setups = s.counters().preconditioner_setups;
    s.prepare_blocks(&a2, &fixed).unwrap();
    assert_eq!(s.pattern_uploads, uploads + 1);
    assert_eq!(s.counters().preconditioner_setups, setups, "kept");
    let r = rng.vec(3 * h.n());
    let kept = kernels::amg_vcycle(&mut s, &f32s(&r), 3).unwrap();
    // 3. A new kind rebuilds it for the new values (same patterns: values
    // only), and the V-cycle sees them.
    s.set_system_kind(SystemKind::FineTune);
    s.prepare_blocks(&a2, &fixed).unwrap();
    assert_eq!(s.counters().preconditioner_setups, setups + 1, "rebuilt");
    let h2 = s.amg_hierarchy().unwrap().clone();
    for ncols in [1, 3] {
        let e = vcycle_error(&mut s, &h2, ncols, &mut rng);
        assert!(
            e < 1e-4,
            "bs 3, rebuilt, {ncols} columns: {e:e} (levels {:?})",
            h2.sizes()
        );
    }
    // The kept V-cycle of step 2 is `h`'s coarse levels under the finest
    // level of `a2` (its matrix and inverted diagonal, with `h`'s weight).
    let mut expected = h.clone();
    expected.levels[0].a = h2.levels[0].a.clone();
    expected.levels[0].dinv = h2.levels[0].dinv.clone();
    let n = h.n();
    for c in 0..3 {
        let want = expected.vcycle(&r[c * n..(c + 1) * n]);
        let got: Vec<f64> = kept[c * n..(c + 1) * n].iter().map(|&v| v as f64).collect();
        let e = rel_err(&got, &want);
        assert!(e < 1e-4, "kept hierarchy, column {c}: {e:e}");
        // And it differs from the rebuilt one: the test sees which ran.
        assert!(rel_err(&got, &h2.vcycle(&r[c * n..(c + 1) * n])) > 1e-3);
    }
    // Scalar.
    let sa = spd_scalar(3000, &mut rng);
    s.prepare(&sa).unwrap();
    let h = s.amg_hierarchy().unwrap().clone();
    assert!(!h.levels.is_empty(), "levels {:?}", h.sizes());
    let r = rng.vec(sa.n * 2);
    let z = kernels::amg_vcycle(&mut s, &f32s(&r), 2).unwrap();
    for c in 0..2 {
        let want = h.vcycle(&r[c * sa.n..(c + 1) * sa.n]);
        let got: Vec<f64> = z[c * sa.n..(c + 1) * sa.n]
            .iter()
            .map(|&v| v as f64)
            .collect();
        let e = rel_err(&got, &want);
        assert!(e < 1e-4, "bs 1, column {c}: {e:e} (levels {:?})", h.sizes());
    }
}

/// Positions of `biharmonic_blocks`' grid nodes on a gently curved sheet.
/// The biharmonic sheet `nx x ny` (every 97th vertex held) prepared with the
/// affine AMG (coarsest level at most `max_coarse` rows): the matrix, the
/// held flags and the hierarchy, which has two levels at least.
fn affine_amg_on_sheet(
    s: &mut GpuSolver,
    nx: usize,
    ny: usize,
    max_coarse: usize,
) -> (BlockSym3, Vec<bool>, solver_gpu::amg::Hierarchy) {
    let a = biharmonic_blocks(nx, ny);
    let fixed = fixed_every(a.n, 97);
    s.set_amg_options(solver_gpu::amg::AmgOptions {
        max_coarse,
        ..Default::default()
    });
    s.set_preconditioner(Preconditioner::AffineAmg).unwrap();
    s.set_vertex_positions(&sheet_positions(nx, ny));
    s.prepare_blocks(&a, &fixed).unwrap();
    assert_eq!(s.active_preconditioner(), Preconditioner::AffineAmg);
    let h = s.amg_hierarchy().unwrap().clone();
    assert!(h.affine && h.levels.len() >= 2, "levels {:?}", h.sizes());
    (a, fixed, h)
}

fn sheet_positions(nx: usize, ny: usize) -> Vec<[f64; 3]> {
    (0..nx * ny)
        .map(|v| {
            let (x, y) = ((v % nx) as f64, (v / nx) as f64);
            [x, y, 0.01 * (x * x + y * y)]
        })
        .collect()
}

#[test]
fn affine_amg_vcycle_matches_the_cpu_reference_and_cuts_iterations() {
    let Some(mut s) = gpu() else { return };
    let (nx, ny) = (36, 30);
    // Linear functions of the positions are near-null for the biharmonic
    // operator: the affine near-null space pays off.
    let (a, fixed, h) = affine_amg_on_sheet(&mut s, nx, ny, 300);
    let n = 3 * a.n;
    // Every wide kernel (3 x 12, 12 x 3, 12 x 12) and the 12 x 12 Jacobi run.
    let mut rng = Rng(41);
    for ncols in [1, 3] {
        let e = vcycle_error(&mut s, &h, ncols, &mut rng);
        assert!(e < 1e-4, "{ncols} columns: {e:e} (levels {:?})", h.sizes());
    }
    // The whole solve against Cholesky, and against the translations-only AMG.
    let ncols = 2;
    let b = rng.vec(n * ncols);
    let mut xc = b.clone();
    let mut cpu = CholeskySolver::new();
    cpu.prepare_blocks(&a, &fixed).unwrap();
    cpu.solve_in_place(&mut xc, ncols).unwrap();
    let (xa, ia) = iterations_with(&mut s, Preconditioner::AffineAmg, &b, ncols);
    let (xt, it) = iterations_with(&mut s, Preconditioner::Amg, &b, ncols);
    for c in 0..ncols {
        let r = c * n..(c + 1) * n;
        let e = rel_err(&xa[r.clone()], &xc[r.clone()]);
        assert!(e < 1e-8, "affine AMG vs Cholesky, column {c}: {e:e}");
        assert!(rel_err(&xt[r.clone()], &xc[r]) < 1e-8);
    }
    eprintln!("biharmonic, {ncols} columns: affine AMG {ia} iterations, translations {it}");
    assert!(ia * 2 < it, "affine {ia} vs translations {it}");
    // Positions dropped: the next hierarchy has translations only.
    s.set_vertex_positions(&[]);
    s.set_preconditioner(Preconditioner::AffineAmg).unwrap();
    assert_eq!(s.active_preconditioner(), Preconditioner::Amg);
}

#[test]
fn amg_pcg_matches_cholesky_in_fewer_iterations_than_block_jacobi() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(33);
    let a = laplacian_blocks(60, 50, &mut rng);
    let fixed = fixed_every(a.n, 70);
    let n = 3 * a.n;
    s.prepare_blocks(&a, &fixed).unwrap();
    let mut cpu = CholeskySolver::new();
    cpu.prepare_blocks(&a, &fixed).unwrap();
    let ncols = 3;
    let b = rng.vec(n * ncols);
    let mut xc = b.clone();
    cpu.solve_in_place(&mut xc, ncols).unwrap();
    let (xa, ia) = iterations_with(&mut s, Preconditioner::Amg, &b, ncols);
    let (xj, ij) = iterations_with(&mut s, Preconditioner::BlockJacobi, &b, ncols);
    for c in 0..ncols {
        let r = c * n..(c + 1) * n;
        let e = rel_err(&xa[r.clone()], &xc[r.clone()]);
        assert!(e < 1e-8, "AMG vs Cholesky, column {c}: {e:e}");
        assert!(rel_err(&xj[r.clone()], &xc[r]) < 1e-8);
    }
    for v in (0..a.n).filter(|&v| fixed[v]) {
        assert!((xa[3 * v] - b[3 * v]).abs() < 1e-9 * b[3 * v].abs());
    }
    eprintln!("blocks, 3 columns: AMG {ia} iterations, block Jacobi {ij}");
    assert!(ia * 3 < ij, "AMG {ia} vs block Jacobi {ij}");
    // Same pattern, new values: values-only upload, still converges.
    let a2 = laplacian_blocks(60, 50, &mut Rng(34));
    let uploads = s.pattern_uploads;
    s.set_preconditioner(Preconditioner::Amg).unwrap();
    s.prepare_blocks(&a2, &fixed).unwrap();
    assert_eq!(s.pattern_uploads, uploads);
    let mut x2 = b[..n].to_vec();
    s.solve_in_place(&mut x2, 1).unwrap();
    let mut x2c = b[..n].to_vec();
    cpu.prepare_blocks(&a2, &fixed).unwrap();
    cpu.solve_in_place(&mut x2c, 1).unwrap();
    assert!(rel_err(&x2, &x2c) < 1e-8);
}

#[test]
fn amg_scalar_system_matches_cholesky_in_fewer_iterations() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(44);
    // A 2-D grid Laplacian-like scalar system with a small mass term.
    let a = laplacian_blocks(40, 35, &mut rng);
    let sa = scalar_of(&a, &fixed_every(a.n, 90));
    s.prepare(&sa).unwrap();
    let mut cpu = CholeskySolver::new();
    cpu.prepare(&sa).unwrap();
    let b = rng.vec(sa.n * 2);
    let mut xc = b.clone();
    cpu.solve_in_place(&mut xc, 2).unwrap();
    let (xa, ia) = iterations_with(&mut s, Preconditioner::Amg, &b, 2);
    let (_, ij) = iterations_with(&mut s, Preconditioner::BlockJacobi, &b, 2);
    let e = rel_err(&xa, &xc);
    assert!(e < 1e-8, "AMG vs Cholesky: {e:e}");
    eprintln!("scalar, 2 columns: AMG {ia} iterations, Jacobi {ij}");
    assert!(ia * 3 < ij, "AMG {ia} vs Jacobi {ij}");
}

#[cfg(feature = "bench-kernels")]
#[test]
fn read_ceiling_reads_every_value() {
    // The benchmark's read ceiling checks that each pass's partials add up to
    // the sum of the values it read; a small binding limit measures over the
    // largest binding instead of failing.
    let Some(s) = gpu() else { return };
    let c = kernels::read_ceiling(&s, 1 << 20, 2).unwrap();
    assert_eq!(c.bytes, 1 << 20);
    assert!(c.seconds > 0.0, "{c:?}");
    let Some(small) = gpu_with_limits(|l| l.max_storage_buffer_binding_size = 1 << 16) else {
        return;
    };
    let c = kernels::read_ceiling(&small, 1 << 20, 1).unwrap();
    assert!(c.bytes == 1 << 16 && c.seconds > 0.0, "{c:?}");
}

/// A PCG run of a system kind solved before starts with a batch as long as
/// that run took, and a batch sized to finish brings `x` back with the column
/// states (counted host waits, not time): the same solve again waits once per
/// refinement round, and gives the same answer.
#[test]
fn a_repeated_solve_of_one_kind_waits_less() {
    let Some(mut s) = gpu() else { return };
    s.set_preconditioner(Preconditioner::BlockJacobi).unwrap();
    let mut rng = Rng(11);
    let a = spd_blocks(30, 20, 0.05, &mut rng);
    let fixed = fixed_every(a.n, 40);
    s.prepare_blocks(&a, &fixed).unwrap();
    let b = rng.vec(3 * a.n);
    let waits = |s: &GpuSolver| s.counters().device_waits;
    let mut x1 = b.clone();
    let w0 = waits(&s);
    let first = s.solve_in_place(&mut x1, 1).unwrap();
    let w1 = waits(&s);
    let mut x2 = b.clone();
    let second = s.solve_in_place(&mut x2, 1).unwrap();
    let w2 = waits(&s);
    assert!(
        first.iterations > 16,
        "the system needs several batches ({} iterations)",
        first.iterations
    );
    assert!(
        w2 - w1 < w1 - w0,
        "second solve waited {} times, the first {}",
        w2 - w1,
        w1 - w0
    );
    let rounds = s.last_stats().rounds;
    assert_eq!(w2 - w1, rounds, "one wait per refinement round");
    assert!(rel_err(&x1, &x2) < 1e-8, "{:e}", rel_err(&x1, &x2));
    assert!(second.residual <= 1e-10);
}

/// The squared-Laplacian preconditioner on the GPU, `z = B^-1 Mt B^-1 r`
/// with each `B^-1` two warm-started V-cycles of the scalar hierarchy of `B`
/// applied to x, y and z of every vertex (scalar CSR kernels on 3-vectors, no
/// `v I3` blocks), equals the scalar CPU V-cycles run on each component.
#[test]
fn squared_laplacian_on_3_vectors_is_the_scalar_vcycle_per_component() {
    use solver_cpu::{ShapeOperatorModel, SparseRows};
    let Some(mut s) = gpu() else { return };
    let (nx, ny) = (45, 40);
    let mut rng = Rng(51);
    let a = laplacian_blocks(nx, ny, &mut rng);
    let n = a.n;
    let fixed = fixed_every(n, 61);
    // A grid Laplacian S with random positive weights and a lumped mass Mt.
    let t: Vec<(u32, u32, f64)> = grid_edges(nx, ny)
        .into_iter()
        .flat_map(|(i, j)| {
            let w = 1.0 + 0.5 * rng.sym();
            [(i as u32, j as u32, w), (j as u32, i as u32, w)]
        })
        .collect();
    let model = std::sync::Arc::new(ShapeOperatorModel {
        laplacian: std::sync::Arc::new(SparseRows::from_triplets(n, t, false)),
        mt: (0..n).map(|_| 0.5 + 0.4 * rng.sym()).collect(),
        c: 30.0,
    });
    s.set_amg_options(solver_gpu::amg::AmgOptions {
        max_coarse: 80,
        ..Default::default()
    });
    s.set_system_kind(SystemKind::ScaleDriven);
    s.set_shape_model(Some(model.clone()));
    s.prepare_blocks(&a, &fixed).unwrap();
    assert_eq!(s.active_preconditioner(), Preconditioner::SquaredLaplacian);
    let h = s.amg_hierarchy().unwrap().clone();
    assert!(
        h.bs == 1 && h.levels.len() >= 2,
        "a scalar multilevel hierarchy, levels {:?}",
        h.sizes()
    );
    let (b, mt) =
        solver_gpu::amg::squared_laplacian(&model, &fixed, solver_gpu::amg::SQUARED_LAPLACIAN_TAU);
    assert!(b.same_pattern(&h.levels[0].a), "the hierarchy is B's");
    // B^-1 as the GPU runs it: a V-cycle, then Richardson steps x += V(b - B x).
    let b_inv = |rhs: &[f64]| {
        let mut x = h.vcycle(rhs);
        for _ in 1..solver_gpu::squared_laplacian_vcycles(b.rows) {
            let mut bx = vec![0.0; n];
            b.matvec(&x, &mut bx);
            let res: Vec<f64> = rhs.iter().zip(&bx).map(|(r, q)| r - q).collect();
            for (xi, d) in x.iter_mut().zip(h.vcycle(&res)) {
                *xi += d;
            }
        }
        x
    };
    for ncols in [1, 3] {
        let r = rng.vec(3 * n * ncols);
        let z = kernels::squared_laplacian(&mut s, &f32s(&r), ncols).unwrap();
        for c in 0..ncols {
            for q in 0..3 {
                let comp: Vec<f64> = (0..n).map(|i| r[c * 3 * n + 3 * i + q]).collect();
                let mut t = b_inv(&comp);
                t.iter_mut().zip(&mt).for_each(|(v, m)| *v *= m);
                let want = b_inv(&t);
                let got: Vec<f64> = (0..n).map(|i| z[c * 3 * n + 3 * i + q] as f64).collect();
                let e = rel_err(&got, &want);
                assert!(
                    e < 1e-4,
                    "{ncols} columns, column {c}, component {q}: {e:e} (levels {:?})",
                    h.sizes()
                );
            }
        }
    }
}

/// A shape matrix `K (x) I3` in isotropic-plus-ring form (no rings): `K` a
/// triangulated grid's Laplacian with random positive weights plus a positive
/// diagonal, of `nx x ny` vertices.
fn iso_grid(nx: usize, ny: usize, rng: &mut Rng) -> solver_cpu::IsoRingSym3 {
    use solver_cpu::{IsoRingSym3, SparseRows};
    let n = nx * ny;
    let edges = grid_edges(nx, ny);
    let pairs = (0..n).map(|i| (i, i)).chain(edges.iter().copied());
    let k = weighted_laplacian(n, pairs, rng, |rng| 0.05 * (1.0 + rng.sym()));
    let rings = std::sync::Arc::new(SparseRows::from_triplets(n, Vec::new(), false));
    let mut a = IsoRingSym3::new(n, k.col_ptr, k.row_idx, rings);
    a.iso.values = k.values;
    a.ring_c = vec![[0.0; 6]; n];
    a
}

/// The active Cholesky preconditioner's application to `ncols` random
/// columns of `n` 3-vectors equals `reference`'s f64 solve per component: to
/// 1e-6 with an f64 factor, 1e-4 with an f32 one (f32 in and out either way).
fn check_factor_solve(
    s: &mut GpuSolver,
    reference: &mut CholeskySolver,
    n: usize,
    ncols: usize,
    rng: &mut Rng,
    what: &str,
) {
    let tol = match kernels::cholesky_is_f64(s).unwrap() {
        true => 1e-6,
        false => 1e-4,
    };
    let r = rng.vec(3 * n * ncols);
    let z = kernels::cholesky(s, &f32s(&r), ncols).unwrap();
    for c in 0..ncols {
        for q in 0..3 {
            let mut want: Vec<f64> = (0..n).map(|i| r[c * 3 * n + 3 * i + q]).collect();
            reference.solve_in_place(&mut want, 1).unwrap();
            let got: Vec<f64> = (0..n).map(|i| z[c * 3 * n + 3 * i + q] as f64).collect();
            let e = rel_err(&got, &want);
            assert!(e < tol, "{what}, column {c}, component {q}: {e:e}");
        }
    }
}

/// The Cholesky preconditioner's triangular solves on the GPU (level by level
/// of the supernodal elimination tree, in f32) equal the host's f64 solve with
/// `K` (held rows identity) per component, for 1 and 3 columns; a small grid
/// (a few supernodes) and one with nested dissection's shallow tree; and the
/// PCG it preconditions lands on the CPU backend's solution in a few
/// iterations, with one set-up per system kind.
#[test]
fn cholesky_preconditioner_is_the_factor_solve_per_component() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(97);
    for (nx, ny) in [(7, 5), (260, 200)] {
        let n = nx * ny;
        let a = iso_grid(nx, ny, &mut rng);
        let fixed = fixed_every(n, 61);
        let kh = a.iso_held_identity(&fixed);
        s.set_system_kind(SystemKind::ScaleDriven);
        let a = prepare_shape(&mut s, a, &fixed);
        assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
        let (depth, nnz) = kernels::cholesky_shape(&s).unwrap();
        // In f64 where the shape systems' PCG starts in f64 (the default).
        let f64 = kernels::cholesky_is_f64(&s).unwrap();
        assert_eq!(f64, s.adapter().shader_f64, "the factor's precision");
        assert!(depth >= 1 && nnz >= n, "{depth} levels, {nnz} values");
        let mut reference = CholeskySolver::new();
        reference.prepare(&kh).unwrap();
        for ncols in [1, 3] {
            let what = format!("{nx}x{ny}, {ncols} columns");
            check_factor_solve(&mut s, &mut reference, n, ncols, &mut rng, &what);
        }
        // The solve: K (x) I3 itself is preconditioned exactly (to f32).
        let b = rng.vec(3 * n * 2);
        let mut x = vec![0.0; b.len()];
        s.set_tolerance(1e-10);
        let info = s.solve_with_guess(&b, &mut x, 2).unwrap();
        assert!(
            info.iterations <= 2 * 6,
            "{nx}x{ny}: {} iterations",
            info.iterations
        );
        let y = cpu_shape_solve(a, &fixed, &b, 2);
        let e = rel_err(&x, &y);
        assert!(e < 1e-8, "{nx}x{ny}: GPU against CPU {e:e}");
        // Another matrix of the same kind keeps the factor; a new kind makes one.
        let setups = s.counters().preconditioner_setups;
        let a2 = iso_grid(nx, ny, &mut rng);
        s.prepare_shape_owned(a2, &fixed).unwrap();
        assert_eq!(s.counters().preconditioner_setups, setups);
        s.set_system_kind(SystemKind::FineTune);
        let a3 = iso_grid(nx, ny, &mut rng);
        s.prepare_shape_owned(a3, &fixed).unwrap();
        assert_eq!(s.counters().preconditioner_setups, setups + 1);
        assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
    }
}

/// The shape factor's symbolic analysis, made ahead on another thread by the
/// solver the GPU solver configures (`isotropic_analyser`), is adopted: the
/// first shape matrix's set-up makes no analysis of its own, and its solve
/// is that of a solver that analysed itself, to the bit.
#[test]
fn an_isotropic_analysis_made_ahead_is_adopted() {
    let (nx, ny) = (60, 40);
    let n = nx * ny;
    let mut rng = Rng(41);
    let a = iso_grid(nx, ny, &mut rng);
    let fixed = fixed_every(n, 61);
    let ordering: Vec<usize> = (0..n).rev().collect();
    let b = rng.vec(3 * n);
    let solve = |ahead: bool| -> Option<(Vec<f64>, usize)> {
        let mut s = gpu()?;
        s.set_system_kind(SystemKind::ScaleDriven);
        s.set_fill_ordering(solver_cpu::FillOrdering::Given(ordering.clone().into()));
        if ahead {
            let analyser = s.isotropic_analyser().expect("the Cholesky factor of K");
            let ((), analysed, _) = solver_cpu::analyse_beside(analyser, &a.iso, || ());
            s.adopt_isotropic_analysis(analysed.unwrap());
            assert!(s.isotropic_analyser().is_none(), "analysed already");
        }
        prepare_shape(&mut s, a.clone(), &fixed);
        assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
        let mut x = vec![0.0; b.len()];
        s.set_tolerance(1e-10);
        s.solve_with_guess(&b, &mut x, 1).unwrap();
        Some((x, kernels::cholesky_analyses(&s)))
    };
    let Some((plain, analyses)) = solve(false) else {
        return;
    };
    let (ahead, analyses_ahead) = solve(true).unwrap();
    assert_eq!((analyses, analyses_ahead), (1, 1));
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&plain), bits(&ahead));
}

/// A 60 x 40 grid's shape matrix of the scale-driven kind, and another
/// positive definite one on its pattern for the fine-tune (scaled, with a
/// varied diagonal shift), its held vertices, and the generator.
fn two_kinds_of_one_pattern(
    seed: u64,
) -> (
    solver_cpu::IsoRingSym3,
    solver_cpu::IsoRingSym3,
    Vec<bool>,
    Rng,
) {
    let (nx, ny) = (60, 40);
    let n = nx * ny;
    let mut rng = Rng(seed);
    let a = iso_grid(nx, ny, &mut rng);
    let mut a_ft = a.clone();
    a_ft.iso.values.iter_mut().for_each(|v| *v *= 1.7);
    for j in 0..n {
        a_ft.iso.values[a_ft.iso.col_ptr[j]] += 0.05 * rng.sym().abs();
    }
    (a, a_ft, fixed_every(n, 61), rng)
}

/// `a_ft` solved as the fine-tune kind's matrix: the solution, the host's
/// Cholesky factorizations and the preconditioner set-ups so far.
fn fine_tune_solve(
    s: &mut GpuSolver,
    a_ft: &solver_cpu::IsoRingSym3,
    fixed: &[bool],
    b: &[f64],
) -> (Vec<f64>, usize, usize) {
    s.set_system_kind(SystemKind::FineTune);
    prepare_shape(s, a_ft.clone(), fixed);
    assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
    let mut x = vec![0.0; b.len()];
    s.set_tolerance(1e-10);
    s.solve_with_guess(b, &mut x, 1).unwrap();
    let setups = s.counters().preconditioner_setups;
    (x, kernels::cholesky_factorizations(s), setups)
}

/// The fine-tune kind's factor of `K`, made ahead on another thread by a
/// solver sharing the scale-driven kind's analysis (`isotropic_factorer`),
/// is that kind's preconditioner: its set-up factors nothing on the host,
/// and its solve is that of the solver that factored the same `K` itself,
/// to the bit. One set-up per kind either way.
#[test]
fn a_factor_made_ahead_is_the_kinds_preconditioner() {
    let (a, a_ft, fixed, mut rng) = two_kinds_of_one_pattern(43);
    let b = rng.vec(3 * a.n());
    let solve = |ahead: bool| -> Option<(Vec<f64>, usize, usize)> {
        let mut s = gpu()?;
        // The host's factor made ahead (on a hardware adapter the GPU
        // makes its factors by default).
        s.set_factorization(solver_gpu::Factorization::Host);
        s.set_system_kind(SystemKind::ScaleDriven);
        assert!(
            s.isotropic_factorer(SystemKind::FineTune).is_none(),
            "nothing analysed yet"
        );
        prepare_shape(&mut s, a.clone(), &fixed);
        assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
        assert!(s.isotropic_factorer(SystemKind::ScaleFactors).is_none());
        if ahead {
            let twin = s
                .isotropic_factorer(SystemKind::FineTune)
                .expect("the factor of K");
            let k = a_ft.iso_held_identity(&fixed);
            let (factored, _) = solver_cpu::FactorAhead::spawn(twin, k).unwrap().join();
            s.adopt_isotropic_factor(SystemKind::FineTune, factored.unwrap());
        }
        Some(fine_tune_solve(&mut s, &a_ft, &fixed, &b))
    };
    let Some((plain, factored, setups)) = solve(false) else {
        return;
    };
    let (ahead, factored_ahead, setups_ahead) = solve(true).unwrap();
    assert_eq!((factored, factored_ahead), (2, 1));
    assert_eq!((setups, setups_ahead), (2, 2));
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&plain), bits(&ahead));
}

/// A factor made ahead goes up on a thread of its own, beside the solver's
/// caller, where uploads go beside it: its submissions are counted there,
/// and they are those the caller makes itself where the kind's set-up
/// factors and uploads on its thread, but for the index sections: of the
/// same analysis as the factor on the device, it sends its values alone
/// (the same solve otherwise, to the bit). The kind's set-up takes it (no host factorization). Where
/// uploads stay on the caller's thread, nothing is submitted beside it.
#[test]
fn a_factor_made_ahead_goes_up_beside_the_caller() {
    let (a, a_ft, fixed, mut rng) = two_kinds_of_one_pattern(53);
    let b = rng.vec(3 * a.n());
    // Submissions (caller's, beside), the solve, host factorizations, and
    // the bytes sent beside the caller with the active factor's values'.
    type Run = ((u64, u64), Vec<f64>, usize, [Option<u64>; 2]);
    let run = |ahead: bool| -> Option<Run> {
        let mut s = gpu()?;
        // The host's factor made ahead (on a hardware adapter the GPU
        // makes its factors by default).
        s.set_factorization(solver_gpu::Factorization::Host);
        kernels::set_beside_uploads(&mut s, true);
        s.set_system_kind(SystemKind::ScaleDriven);
        prepare_shape(&mut s, a.clone(), &fixed);
        let before = kernels::submissions(&s);
        let bytes_before = kernels::beside_bytes(&s);
        if ahead {
            let twin = s.isotropic_factorer(SystemKind::FineTune).unwrap();
            let k = a_ft.iso_held_identity(&fixed);
            let (factored, _) = solver_cpu::FactorAhead::spawn(twin, k).unwrap().join();
            s.adopt_isotropic_factor(SystemKind::FineTune, factored.unwrap());
        }
        let (x, factorizations, _) = fine_tune_solve(&mut s, &a_ft, &fixed, &b);
        let after = kernels::submissions(&s);
        let made = (after.0 - before.0, after.1 - before.1);
        let bytes = [
            Some(kernels::beside_bytes(&s) - bytes_before),
            kernels::cholesky_value_bytes(&s),
        ];
        Some((made, x, factorizations, bytes))
    };
    let Some(((here, none_beside), plain, factored, _)) = run(false) else {
        return;
    };
    let ((caller, beside), ahead, factored_ahead, [sent, values]) = run(true).unwrap();
    assert_eq!(
        none_beside, 0,
        "nothing beside the caller without a factor ahead"
    );
    assert_eq!((factored, factored_ahead), (2, 1));
    assert!(beside >= 1, "the values: {beside} submissions");
    // Its values alone went up: the index sections are the scale-driven
    // factor's on the device (the same analysis).
    assert!(values.is_some_and(|v| v > 0));
    assert_eq!(
        sent, values,
        "bytes sent beside the caller, the factor's values"
    );
    // The factor made here went up from the caller as its index sections
    // (one window) and its values; the one made ahead as its values alone,
    // beside it.
    assert_eq!(
        (caller, beside),
        (here - beside - 1, beside),
        "the upload's submissions moved off the caller's thread, the index's gone"
    );
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&plain), bits(&ahead));
    // Uploads on the caller's thread: the factor made ahead still taken.
    let mut s = gpu().unwrap();
    // The host's factor made ahead (on a hardware adapter the GPU
    // makes its factors by default).
    s.set_factorization(solver_gpu::Factorization::Host);
    kernels::set_beside_uploads(&mut s, false);
    s.set_system_kind(SystemKind::ScaleDriven);
    prepare_shape(&mut s, a.clone(), &fixed);
    let twin = s.isotropic_factorer(SystemKind::FineTune).unwrap();
    let k = a_ft.iso_held_identity(&fixed);
    let (factored, _) = solver_cpu::FactorAhead::spawn(twin, k).unwrap().join();
    s.adopt_isotropic_factor(SystemKind::FineTune, factored.unwrap());
    let (here, factorizations, _) = fine_tune_solve(&mut s, &a_ft, &fixed, &b);
    assert_eq!(kernels::submissions(&s).1, 0, "nothing beside the caller");
    assert_eq!(factorizations, 1);
    assert_eq!(bits(&here), bits(&ahead));
}

/// The fine-tune kind's factor of `K` made ahead on its own symbolic
/// analysis in another fill ordering (METIS's nested dissection of the
/// pattern, as the pipeline makes it beside the scale-driven iteration,
/// `FactorAhead::spawn_analysing`), not on a twin of the solver's own
/// minimum-degree analysis, is that kind's preconditioner too: its set-up
/// factors nothing on the host, and its solve lands on the solution of the
/// solver that factored the same `K` itself. A factor of another pattern is
/// refused, and the set-up factors.
#[test]
fn a_factor_made_ahead_in_another_ordering_is_the_kinds_preconditioner() {
    use solver_cpu::{FactorAhead, FillOrdering};
    let (a, a_ft, fixed, mut rng) = two_kinds_of_one_pattern(47);
    let n = a.n();
    let other = iso_grid(60, 41, &mut rng);
    let (forward, _) =
        solver_cpu::nested_dissection_of_pattern(n, &a.iso.col_ptr, &a.iso.row_idx).unwrap();
    let forward: std::sync::Arc<[usize]> = forward.into();
    let b = rng.vec(3 * n);
    // `ahead`: none, one of this pattern in METIS's ordering, or one of
    // `other`'s pattern.
    let solve = |ahead: Option<bool>| -> Option<(Vec<f64>, usize, usize)> {
        let mut s = gpu()?;
        // The host's factor made ahead (on a hardware adapter the GPU
        // makes its factors by default).
        s.set_factorization(solver_gpu::Factorization::Host);
        s.set_system_kind(SystemKind::ScaleDriven);
        prepare_shape(&mut s, a.clone(), &fixed);
        assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
        if let Some(same_pattern) = ahead {
            let plan = s
                .isotropic_factor_plan(SystemKind::FineTune)
                .expect("a plan for the fine-tune's factor");
            let (k, ordering) = if same_pattern {
                (
                    a_ft.iso_held_identity(&fixed),
                    FillOrdering::Given(forward.clone()),
                )
            } else {
                let fixed = fixed_every(other.n(), 61);
                (other.iso_held_identity(&fixed), FillOrdering::Amd)
            };
            let (factored, _) = FactorAhead::spawn_analysing(plan, move || ordering, k)
                .unwrap()
                .join();
            let factored = factored.unwrap();
            let twin = s.isotropic_factorer(SystemKind::FineTune).unwrap();
            if same_pattern {
                assert_ne!(
                    factored.factor_nnz(),
                    twin.factor_nnz(),
                    "another ordering than the solver's analysis"
                );
            }
            s.adopt_isotropic_factor(SystemKind::FineTune, factored);
        }
        Some(fine_tune_solve(&mut s, &a_ft, &fixed, &b))
    };
    let Some((plain, factored, setups)) = solve(None) else {
        return;
    };
    let (ahead, factored_ahead, setups_ahead) = solve(Some(true)).unwrap();
    let (_, factored_other, setups_other) = solve(Some(false)).unwrap();
    assert_eq!(
        (factored, factored_ahead, factored_other),
        (2, 1, 2),
        "host factorizations: none for the kind whose factor was taken"
    );
    assert_eq!((setups, setups_ahead, setups_other), (2, 2, 2));
    let scale = plain.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = plain
        .iter()
        .zip(&ahead)
        .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
    assert!(
        diff <= 1e-7 * scale,
        "the solutions differ by {diff:e} (largest entry {scale:e})"
    );
}

/// A Cholesky factor larger than one storage binding has its values split
/// over several, at supernode boundaries: it stays the preconditioner, its
/// solve is still the factor's, and the PCG lands on the CPU backend's
/// solution as with one buffer.
#[test]
fn cholesky_factor_over_one_binding_is_split_over_several() {
    let (nx, ny) = (260, 200);
    let n = nx * ny;
    let mut rng = Rng(5);
    let a = iso_grid(nx, ny, &mut rng);
    let fixed = fixed_every(n, 61);
    let kh = a.iso_held_identity(&fixed);
    let mut host = CholeskySolver::new();
    host.analyse(&kh).unwrap();
    let factor_bytes = 8 * host.factor_nnz() as u64;
    // Room for the vectors and the matrix's chunks, not for the factor.
    let limit = (factor_bytes / 2).max(4 << 20) / 4 * 4;
    assert!(limit < factor_bytes, "{limit} {factor_bytes}");
    let Some(mut s) = gpu_with_limits(move |l| l.max_storage_buffer_binding_size = limit) else {
        return;
    };
    s.set_system_kind(SystemKind::ScaleDriven);
    let a = prepare_shape(&mut s, a, &fixed);
    assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
    let chunks = kernels::cholesky_chunks(&s).unwrap();
    let least = factor_bytes.div_ceil(limit) as usize;
    let f64 = kernels::cholesky_is_f64(&s).unwrap();
    if f64 {
        assert!(chunks >= least, "{chunks} buffers for {factor_bytes} bytes");
    }
    assert!(chunks >= 2 || !f64, "{chunks} buffers");
    let mut reference = CholeskySolver::new();
    reference.prepare(&kh).unwrap();
    // One column: the updates of two would not fit the lowered binding.
    check_factor_solve(&mut s, &mut reference, n, 1, &mut rng, "split factor");
    // Two columns: solved in batches whose updates fit.
    let b = rng.vec(3 * n * 2);
    let mut x = vec![0.0; b.len()];
    s.set_tolerance(1e-10);
    let info = s.solve_with_guess(&b, &mut x, 2).unwrap();
    assert!(info.iterations <= 2 * 6, "{} iterations", info.iterations);
    let y = cpu_shape_solve(a, &fixed, &b, 2);
    let e = rel_err(&x, &y);
    assert!(e < 1e-8, "GPU against CPU {e:e}");
}

/// A scalar 3-D grid Laplacian plus a positive diagonal: its nested
/// dissection ends in a dense separator of about `n^(2/3)` unknowns.
fn scalar_grid_3d(m: usize, rng: &mut Rng) -> SymCsc {
    let id = |i: usize, j: usize, k: usize| (i * m + j) * m + k;
    let mut pairs = Vec::new();
    for i in 0..m {
        for j in 0..m {
            for k in 0..m {
                pairs.push((id(i, j, k), id(i, j, k)));
                if i + 1 < m {
                    pairs.push((id(i + 1, j, k), id(i, j, k)));
                }
                if j + 1 < m {
                    pairs.push((id(i, j + 1, k), id(i, j, k)));
                }
                if k + 1 < m {
                    pairs.push((id(i, j, k + 1), id(i, j, k)));
                }
            }
        }
    }
    weighted_laplacian(m * m * m, pairs, rng, |_| 0.1)
}

/// The Laplacian of the graph `pairs` (the diagonal included) with random
/// weights in [0.5, 1.5], plus `shift(rng)` on each diagonal entry.
fn weighted_laplacian(
    n: usize,
    pairs: impl IntoIterator<Item = (usize, usize)>,
    rng: &mut Rng,
    shift: impl Fn(&mut Rng) -> f64,
) -> SymCsc {
    let mut a = SymCsc::from_pattern(n, pairs);
    let mut diag = vec![0.0; n];
    for j in 0..n {
        for s in a.col_ptr[j]..a.col_ptr[j + 1] {
            let i = a.row_idx[s];
            if i != j {
                let w = 1.0 + 0.5 * rng.sym();
                a.values[s] = -w;
                diag[i] += w;
                diag[j] += w;
            }
        }
    }
    for (j, d) in diag.iter().enumerate() {
        let s = a.slot(j, j).unwrap();
        a.values[s] = d + shift(rng);
    }
    a
}

/// A factor whose largest supernode would not fit one storage binding is
/// refused after the symbolic analysis (no numeric factorization is wasted on
/// it): the scale-factor system falls back to AMG and still solves as the
/// CPU's direct solver does.
#[test]
fn cholesky_supernode_over_the_binding_limit_falls_back() {
    let mut rng = Rng(9);
    let a = scalar_grid_3d(30, &mut rng);
    let mut host = CholeskySolver::single_precision();
    host.analyse(&a).unwrap();
    let supernode = 4 * host.largest_supernode_nnz() as u64;
    let limit = (supernode / 2) / 4 * 4;
    // The matrix itself (values and indices) fits the lowered binding.
    assert!(12 * a.values.len() as u64 <= limit, "{limit} {supernode}");
    let Some(mut s) = gpu_with_limits(move |l| l.max_storage_buffer_binding_size = limit) else {
        return;
    };
    s.set_system_kind(SystemKind::ScaleFactors);
    s.prepare(&a).unwrap();
    assert_ne!(s.active_preconditioner(), Preconditioner::Cholesky);
    assert!(kernels::cholesky_shape(&s).is_none());
    let b = rng.vec(a.n);
    let mut x = vec![0.0; b.len()];
    s.set_tolerance(1e-10);
    s.solve_with_guess(&b, &mut x, 1).unwrap();
    let mut cpu = CholeskySolver::new();
    cpu.prepare(&a).unwrap();
    let mut y = b.clone();
    cpu.solve_in_place(&mut y, 1).unwrap();
    let e = rel_err(&x, &y);
    assert!(e < 1e-8, "GPU against CPU {e:e}");
}

/// The scale factors' Hessian (Eq. 3) is constant for a run: the GPU solver
/// factors it once (f32) and preconditions its PCG with that exact factor, so
/// the f64 iteration ends in one round of a few iterations, one host wait.
#[test]
fn scale_factor_system_is_preconditioned_by_its_own_factor() {
    let Some(mut s) = gpu() else { return };
    let mut rng = Rng(41);
    let a = spd_scalar(30_000, &mut rng);
    s.set_system_kind(SystemKind::ScaleFactors);
    s.prepare(&a).unwrap();
    assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
    // f64 where the adapter has it: the scale factors' Newton steps solve
    // with it directly (`SpdSolver::power_sum_newton`).
    let f64_factor = s.adapter().shader_f64;
    assert_eq!(kernels::cholesky_is_f64(&s), Some(f64_factor));
    let mut reference = CholeskySolver::new();
    reference.prepare(&a).unwrap();
    // The preconditioner is the factor's solve (read back in f32).
    let r = rng.vec(2 * a.n);
    let f32_input: Vec<f64> = f32s(&r).iter().map(|&v| v as f64).collect();
    let z = kernels::cholesky(&mut s, &f32s(&r), 2).unwrap();
    let mut want = f32_input;
    reference.solve_in_place(&mut want, 2).unwrap();
    let got: Vec<f64> = z.iter().map(|&v| v as f64).collect();
    let e = rel_err(&got, &want);
    let most = if f64_factor { 1e-7 } else { 1e-4 };
    assert!(e < most, "factor solve against the f64 reference: {e:e}");
    // A solve of `ncols` random columns to `tol`: its distance from the CPU's
    // direct solve, its iterations and its host waits.
    let mut solve = |s: &mut GpuSolver, ncols: usize, tol: f64| {
        let b = rng.vec(ncols * a.n);
        let mut x = vec![0.0; b.len()];
        s.set_tolerance(tol);
        let waits = s.counters().device_waits;
        let info = s.solve_with_guess(&b, &mut x, ncols).unwrap();
        let waits = s.counters().device_waits - waits;
        let mut y = b;
        reference.solve_in_place(&mut y, ncols).unwrap();
        (rel_err(&x, &y), info.iterations, waits)
    };
    // The solves: as the CPU's direct solve, in a few iterations.
    for k in 0..2 {
        let (e, iterations, waits) = solve(&mut s, 4, 1e-10);
        assert!(e < 1e-9, "solve {k}: GPU against CPU {e:e}");
        assert!(iterations <= 3, "solve {k}: {iterations} iterations");
        if s.adapter().shader_f64 {
            // One mixed round; the second solve's batch is sized by the first.
            let most = if k == 0 { 2 } else { 1 };
            assert!(waits <= most, "solve {k}: {waits} waits");
        }
    }
    // The same (constant) matrix again keeps the factor.
    let setups = s.counters().preconditioner_setups;
    s.prepare(&a).unwrap();
    assert_eq!(s.counters().preconditioner_setups, setups);
    assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
    // The f32 PCG with an f32 factor (a solver that never runs mixed)
    // converges too, by refinement rounds.
    let Some(mut s) = gpu() else { return };
    s.set_mixed_precision(MixedPrecision::Never);
    s.set_system_kind(SystemKind::ScaleFactors);
    s.prepare(&a).unwrap();
    assert_eq!(kernels::cholesky_is_f64(&s), Some(false));
    let (e, iterations, _) = solve(&mut s, 1, 1e-8);
    assert!(e < 1e-7, "f32 PCG against CPU {e:e}");
    assert!(iterations <= 6, "f32 PCG: {iterations} iterations");
}

/// The CPU backend's solve of the shape matrix `a` for `ncols` columns
/// `b`, to 1e-12: the reference of the GPU's shape solves.
fn cpu_shape_solve(a: IsoRingSym3, fixed: &[bool], b: &[f64], ncols: usize) -> Vec<f64> {
    let mut cpu = solver_cpu::BlockPcgSolver::new();
    cpu.set_tolerance(1e-12);
    cpu.prepare_shape_owned(a, fixed).unwrap();
    let mut y = vec![0.0; b.len()];
    cpu.solve_with_guess(b, &mut y, ncols).unwrap();
    y
}

/// `s` prepared with the shape matrix `a`; `a` back (a copy of it where the
/// solver keeps it).
fn prepare_shape(s: &mut GpuSolver, a: IsoRingSym3, fixed: &[bool]) -> IsoRingSym3 {
    match s.prepare_shape_owned(a, fixed).unwrap() {
        Some(a) => a,
        None => s.shape_matrix().expect("the kept matrix").clone(),
    }
}

/// New values of a shape pattern that the kind's Cholesky factor
/// preconditions go up without the inverse diagonal blocks, which only the
/// block-Jacobi and AMG preconditioners read: its 36 bytes a vertex are the
/// whole difference from a block-Jacobi solver's upload of the same
/// matrix. A switch to block Jacobi afterwards writes the current matrix's
/// blocks first: the solve equals, to the bit, that of a solver that was
/// block Jacobi from the start.
#[test]
fn a_cholesky_kind_leaves_the_inverse_diagonal_until_asked() {
    let (nx, ny) = (40, 30);
    let n = nx * ny;
    let mut rng = Rng(71);
    let a1 = iso_grid(nx, ny, &mut rng);
    let mut a2 = a1.clone();
    for (k, v) in a2.iso.values.iter_mut().enumerate() {
        *v *= 1.0 + 0.3 * ((k % 7) as f64 / 7.0);
    }
    let fixed = fixed_every(n, 37);
    let b = rng.vec(3 * n);
    // The bytes the second matrix moved to the device, and the solve of
    // it with block Jacobi (set after the matrix, where `switch`).
    let run = |p: Preconditioner, switch: bool| -> Option<(u64, Vec<f64>, usize)> {
        let mut s = gpu()?;
        s.set_system_kind(SystemKind::ScaleDriven);
        s.set_preconditioner(p).unwrap();
        prepare_shape(&mut s, a1.clone(), &fixed);
        assert_eq!(s.active_preconditioner(), p);
        let before = s.counters().bytes_to_device;
        prepare_shape(&mut s, a2.clone(), &fixed);
        let moved = s.counters().bytes_to_device - before;
        if switch {
            s.set_preconditioner(Preconditioner::BlockJacobi).unwrap();
        }
        s.set_tolerance(1e-8);
        let mut x = vec![0.0; b.len()];
        s.solve_with_guess(&b, &mut x, 1).unwrap();
        Some((moved, x, s.counters().iterations))
    };
    let Some((moved_chol, switched, it_switched)) = run(Preconditioner::Cholesky, true) else {
        return;
    };
    let (moved_jacobi, jacobi, it_jacobi) = run(Preconditioner::BlockJacobi, false).unwrap();
    assert_eq!(moved_jacobi - moved_chol, 36 * n as u64);
    assert_eq!(it_switched, it_jacobi);
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&switched), bits(&jacobi));
}

/// The vertex positions are asked for while a kind's preparation may set
/// up an AMG (the first matrix of a kind, any matrix with an AMG), not
/// once the kind's Cholesky factor is made.
#[test]
fn vertex_positions_are_wanted_until_the_kinds_factor_is_made() {
    let mut rng = Rng(5);
    let a = iso_grid(12, 10, &mut rng);
    let fixed = fixed_every(a.n(), 41);
    let Some(mut s) = gpu() else {
        return;
    };
    s.set_system_kind(SystemKind::ScaleDriven);
    assert!(s.wants_vertex_positions(), "no matrix yet");
    prepare_shape(&mut s, a.clone(), &fixed);
    assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
    assert!(!s.wants_vertex_positions(), "the kind's factor is made");
    s.set_system_kind(SystemKind::FineTune);
    assert!(s.wants_vertex_positions(), "a new kind's first matrix");
    prepare_shape(&mut s, a.clone(), &fixed);
    assert!(!s.wants_vertex_positions());
    s.set_preconditioner(Preconditioner::AffineAmg).unwrap();
    prepare_shape(&mut s, a, &fixed);
    assert!(s.wants_vertex_positions(), "an AMG reads them");
}

/// The pipelines of a kind's solves compiled ahead on another thread
/// (`SpdSolver::warm_up`): the scale-driven kind's one-column solve and the
/// fine-tune's four- and three-column solves (its first step and the next)
/// then compile none where they run, while a solver without it compiles
/// some; the solutions are the same to the bit.
#[test]
fn warmed_up_kinds_compile_no_pipeline_where_they_solve() {
    let mut rng = Rng(17);
    let a = iso_grid(16, 12, &mut rng);
    let n = a.n();
    let fixed = fixed_every(n, 29);
    let b1 = rng.vec(3 * n);
    let b4 = rng.vec(3 * n * 4);
    // (pipelines compiled where the systems were prepared and solved,
    // pipelines compiled ahead, the solutions' bits)
    let run = |warm: bool| -> Option<(u64, u64, Vec<u64>)> {
        let mut s = gpu_f64()?;
        if warm {
            s.warm_up(SystemKind::ScaleDriven, &[1]);
            s.warm_up(SystemKind::FineTune, &[4, 3]);
            s.wait_for_warm_up();
        }
        s.set_tolerance(1e-10);
        let before = s.counters();
        let mut bits = Vec::new();
        for (kind, b, ncols) in [
            (SystemKind::ScaleDriven, &b1[..], 1),
            (SystemKind::FineTune, &b4[..], 4),
            (SystemKind::FineTune, &b4[..3 * n * 3], 3),
        ] {
            if ncols != 3 {
                s.set_system_kind(kind);
                prepare_shape(&mut s, a.clone(), &fixed);
                assert_eq!(s.active_preconditioner(), Preconditioner::Cholesky);
            }
            let mut x = vec![0.0; b.len()];
            s.solve_with_guess(b, &mut x, ncols).unwrap();
            bits.extend(x.iter().map(|v| v.to_bits()));
        }
        let after = s.counters();
        Some((
            after.device_compiles - before.device_compiles,
            after.device_compiles_ahead,
            bits,
        ))
    };
    let Some((at_use_cold, ahead_cold, cold)) = run(false) else {
        return;
    };
    let (at_use_warm, ahead_warm, warm) = run(true).unwrap();
    assert_eq!(ahead_cold, 0);
    assert!(at_use_cold > 0, "a solver without warm-up compiled nothing");
    assert!(ahead_warm > 0, "nothing compiled ahead");
    assert_eq!(
        at_use_warm, 0,
        "{at_use_warm} compiled where the solves ran"
    );
    assert!(cold == warm, "the solutions differ");
}

/// A scale-driven shape matrix on the 2-ring pattern of an `nx x ny` grid,
/// its rings each vertex's grid neighbours (as E_l's rows), `K` a weighted
/// Laplacian plus a positive diagonal, no `C_i`; and a Laplacian square
/// model whose `S` has the rings' rows (as E_m's cotangent rows have E_l's
/// columns).
fn ring_grid(
    nx: usize,
    ny: usize,
    rng: &mut Rng,
) -> (IsoRingSym3, std::sync::Arc<solver_cpu::ShapeOperatorModel>) {
    use solver_cpu::{ShapeOperatorModel, SparseRows};
    use std::sync::Arc;
    let n = nx * ny;
    let edges = grid_edges(nx, ny);
    let t: Vec<(u32, u32, f64)> = edges
        .iter()
        .flat_map(|&(i, j)| {
            let w = 1.0 + 0.5 * rng.sym();
            [(i as u32, j as u32, w), (j as u32, i as u32, w)]
        })
        .collect();
    let rings = Arc::new(SparseRows::from_triplets(n, t, false));
    // Every pair of a ring's vertices (the row's own vertex included).
    let mut pairs: Vec<(usize, usize)> = (0..n).map(|i| (i, i)).collect();
    for i in 0..n {
        let members: Vec<usize> = std::iter::once(i)
            .chain(rings.row(i).map(|(j, _)| j))
            .collect();
        for &p in &members {
            for &q in &members {
                pairs.push((p.max(q), p.min(q)));
            }
        }
    }
    let pattern = SymCsc::from_pattern(n, pairs);
    let mut a = IsoRingSym3::new(n, pattern.col_ptr, pattern.row_idx, rings.clone());
    for j in 0..n {
        for k in a.iso.col_ptr[j]..a.iso.col_ptr[j + 1] {
            a.iso.values[k] = if a.iso.row_idx[k] == j {
                8.0 + rng.sym()
            } else {
                -0.05 * (1.0 + rng.sym().abs())
            };
        }
    }
    let model = Arc::new(ShapeOperatorModel {
        laplacian: rings,
        mt: (0..n).map(|_| 0.5 + 0.4 * rng.sym()).collect(),
        c: 0.0,
    });
    (a, model)
}

/// The Laplacian square term's values are summed on another thread from
/// the scale-driven kind's first shape matrix on (once its factor is made),
/// and the next matrix, which names the term, takes them: its solve equals
/// the CPU's direct solve of that matrix. Block Jacobi (no factor: its
/// matrices never name the term) starts none.
#[test]
fn the_laplacian_squares_values_are_summed_ahead_and_taken() {
    let Some(mut s) = gpu() else { return };
    if !s.adapter().shader_f64 {
        // No shape sum on the GPU: nothing to sum ahead.
        return;
    }
    let mut rng = Rng(91);
    let (a, model) = ring_grid(30, 20, &mut rng);
    let n = a.n();
    let fixed = fixed_every(n, 53);
    s.set_system_kind(SystemKind::ScaleDriven);
    s.set_preconditioner(Preconditioner::Cholesky).unwrap();
    s.set_shape_model(Some(model.clone()));
    prepare_shape(&mut s, a.clone(), &fixed);
    assert_eq!(kernels::square_values_ahead(&s), (true, 0), "started");
    let mut named = a.clone();
    named.laplacian_square = Some(model.clone());
    prepare_shape(&mut s, named.clone(), &fixed);
    assert_eq!(kernels::square_values_ahead(&s), (false, 1), "taken");
    let b = rng.vec(3 * n);
    let mut x = vec![0.0; b.len()];
    s.set_tolerance(1e-11);
    s.solve_with_guess(&b, &mut x, 1).unwrap();
    let y = cpu_shape_solve(named, &fixed, &b, 1);
    let e = rel_err(&x, &y);
    assert!(e < 1e-8, "GPU against CPU {e:e}");
    // Block Jacobi: no factor, so no matrix will name the term.
    let Some(mut s) = gpu() else { return };
    s.set_system_kind(SystemKind::ScaleDriven);
    s.set_preconditioner(Preconditioner::BlockJacobi).unwrap();
    s.set_shape_model(Some(model));
    prepare_shape(&mut s, a, &fixed);
    assert_eq!(kernels::square_values_ahead(&s), (false, 0));
}
