//! PCG kernel benchmark: synthetic 3x3-block SPD matrices with ~19 blocks per row
//! (the 2-ring of a regular triangle mesh), n = 6.5k, 50k, 500k block rows.
//!
//! Prints, per size: the GPU PCG time per iteration (1 and 4 right-hand sides),
//! the effective bandwidth (bytes a minimal iteration must move / time),
//! iterations to a relative residual of 1e-6 with block-Jacobi (plain f32 PCG, and
//! the refined solver cold and warm-started from the previous outer iteration's
//! solution), next to the same PCG single-threaded on the CPU (f32 and f64) and
//! the single-thread CPU SpMV bandwidth. The adapter is named: on a software
//! rasterizer (lavapipe/llvmpipe) the "GPU" numbers are CPU numbers.
//!
//! A second table compares precisions where the adapter has `SHADER_F64`: the
//! same kernels (`csr_spmv.wgsl`, `pcg.wgsl`) in f32 and in f64 on the scalar
//! expansion of the matrix (9 entries per block, scalar Jacobi), per-iteration
//! time and iterations to 1e-6 and 1e-10.
//!
//! A third table gives the adapter's read ceiling (`kernels::read_ceiling`,
//! `shaders/stream.wgsl`) over the bytes of a minimal iteration: what any
//! kernel reading them costs at least, next to a single-thread CPU read and
//! the CPU SpMV.
//!
//! `cargo bench -p solver-gpu --features bench-kernels --bench pcg_kernels
//! [-- 6500 50000]` (sizes optional; the feature builds the read-ceiling kernel
//! and the per-kernel timers, which production builds leave out).

use solver_cpu::{BlockSym3, SpdSolver};
use solver_gpu::kernels::Precision;
use solver_gpu::{block_jacobi::invert_spd3, kernels, GpuSolver};
use std::time::Instant;

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

/// Block matrix on an s x s triangular lattice, couplings within the 2-ring.
fn synthetic(rows: usize, shift: f64, rng: &mut Rng) -> (BlockSym3, Vec<bool>) {
    let s = (rows as f64).sqrt().round() as i64;
    let n = (s * s) as usize;
    let ring1 = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1)];
    let mut offs: Vec<(i64, i64)> = ring1.to_vec();
    for a in ring1 {
        for b in ring1 {
            let o = (a.0 + b.0, a.1 + b.1);
            if o != (0, 0) && !offs.contains(&o) {
                offs.push(o);
            }
        }
    }
    let mut pairs = Vec::with_capacity(n * offs.len() / 2);
    for y in 0..s {
        for x in 0..s {
            let i = (y * s + x) as usize;
            for &(dx, dy) in &offs {
                let (u, v) = (x + dx, y + dy);
                if u >= 0 && v >= 0 && u < s && v < s {
                    let j = (v * s + u) as usize;
                    if j < i {
                        pairs.push((i, j));
                    }
                }
            }
        }
    }
    // A = sum over edges (e_i - e_j)(e_i - e_j)^T (x) W_e + shift * mean degree * I,
    // W_e = w (I + M M^T / |M|^2) SPD: a mesh-like anisotropic graph Laplacian,
    // positive definite through the shift only (cond ~ 2 / shift).
    let mut a = BlockSym3::from_pattern(n, pairs);
    let mut diag = vec![[0.0; 9]; n];
    let mut total = 0.0;
    for j in 0..n {
        for k in a.col_ptr[j]..a.col_ptr[j + 1] {
            let i = a.row_idx[k];
            if i == j {
                continue;
            }
            let w = 1.0 + 0.5 * rng.next();
            let m: Vec<f64> = (0..9).map(|_| rng.next()).collect();
            let f2: f64 = m.iter().map(|v| v * v).sum();
            let mut we = [0.0; 9];
            for r in 0..3 {
                for c in 0..3 {
                    let mm: f64 = (0..3).map(|t| m[3 * r + t] * m[3 * c + t]).sum();
                    we[3 * r + c] = w * (mm / f2 + if r == c { 1.0 } else { 0.0 });
                }
            }
            for q in 0..9 {
                a.blocks[k][q] = -we[q];
                diag[i][q] += we[q];
                diag[j][q] += we[q];
            }
            total += 2.0 * (we[0] + we[4] + we[8]) / 3.0;
        }
    }
    let mean = total / n as f64;
    for (i, d) in diag.iter().enumerate() {
        let (k, _) = a.slot(i, i).unwrap();
        let mut blk = *d;
        blk[0] += shift * mean;
        blk[4] += shift * mean;
        blk[8] += shift * mean;
        a.blocks[k] = blk;
    }
    let fixed = (0..n).map(|v| v % 997 == 5).collect();
    (a, fixed)
}

/// Full (both triangles) block-CSR with fixed rows/columns as identity.
struct Full<T> {
    rows: usize,
    row_ptr: Vec<usize>,
    col_idx: Vec<u32>,
    vals: Vec<T>,
    minv: Vec<T>,
}

fn expand(a: &BlockSym3, fixed: &[bool]) -> Full<f64> {
    let n = a.n;
    let mut rows: Vec<Vec<(u32, [f64; 9])>> = vec![Vec::new(); n];
    for j in 0..n {
        for k in a.col_ptr[j]..a.col_ptr[j + 1] {
            let i = a.row_idx[k];
            let cut = fixed[i] || fixed[j];
            let b = if cut {
                if i == j {
                    [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
                } else {
                    [0.0; 9]
                }
            } else {
                a.blocks[k]
            };
            rows[i].push((j as u32, b));
            if i != j {
                let mut t = [0.0; 9];
                for r in 0..3 {
                    for c in 0..3 {
                        t[3 * r + c] = b[3 * c + r];
                    }
                }
                rows[j].push((i as u32, t));
            }
        }
    }
    let mut f = Full {
        rows: n,
        row_ptr: vec![0],
        col_idx: Vec::new(),
        vals: Vec::new(),
        minv: Vec::new(),
    };
    for (i, r) in rows.iter_mut().enumerate() {
        r.sort_by_key(|e| e.0);
        for (j, b) in r.iter() {
            f.col_idx.push(*j);
            f.vals.extend_from_slice(b);
            if *j as usize == i {
                f.minv
                    .extend_from_slice(&invert_spd3(b).expect("SPD diagonal block"));
            }
        }
        f.row_ptr.push(f.col_idx.len());
    }
    f
}

fn to_f32(f: &Full<f64>) -> Full<f32> {
    Full {
        rows: f.rows,
        row_ptr: f.row_ptr.clone(),
        col_idx: f.col_idx.clone(),
        vals: f.vals.iter().map(|&v| v as f32).collect(),
        minv: f.minv.iter().map(|&v| v as f32).collect(),
    }
}

trait Real:
    Copy
    + Default
    + PartialOrd
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
    + std::ops::AddAssign
{
    fn f64(self) -> f64;
}
impl Real for f32 {
    fn f64(self) -> f64 {
        self as f64
    }
}
impl Real for f64 {
    fn f64(self) -> f64 {
        self
    }
}

fn spmv<T: Real>(m: &Full<T>, x: &[T], y: &mut [T]) {
    for i in 0..m.rows {
        let mut acc = [T::default(); 3];
        for k in m.row_ptr[i]..m.row_ptr[i + 1] {
            let j = m.col_idx[k] as usize;
            let b = &m.vals[9 * k..9 * k + 9];
            let (x0, x1, x2) = (x[3 * j], x[3 * j + 1], x[3 * j + 2]);
            for r in 0..3 {
                acc[r] += b[3 * r] * x0 + b[3 * r + 1] * x1 + b[3 * r + 2] * x2;
            }
        }
        y[3 * i..3 * i + 3].copy_from_slice(&acc);
    }
}

fn dotp<T: Real>(a: &[T], b: &[T]) -> T {
    let mut s = T::default();
    for (x, y) in a.iter().zip(b) {
        s += *x * *y;
    }
    s
}

/// Single-thread block-Jacobi PCG; returns (iterations, seconds, converged).
fn cpu_pcg<T: Real>(m: &Full<T>, b: &[T], tol: f64, max_it: usize) -> (usize, f64, bool) {
    let n = b.len();
    let t = Instant::now();
    let mut x = vec![T::default(); n];
    let mut r = b.to_vec();
    let mut z = vec![T::default(); n];
    let mut ap = vec![T::default(); n];
    let prec = |r: &[T], z: &mut [T]| {
        for i in 0..m.rows {
            let mi = &m.minv[9 * i..9 * i + 9];
            for q in 0..3 {
                z[3 * i + q] = mi[3 * q] * r[3 * i]
                    + mi[3 * q + 1] * r[3 * i + 1]
                    + mi[3 * q + 2] * r[3 * i + 2];
            }
        }
    };
    prec(&r, &mut z);
    let mut p = z.clone();
    let mut rz = dotp(&r, &z);
    let bb = dotp(b, b).f64();
    for it in 1..=max_it {
        spmv(m, &p, &mut ap);
        let alpha = rz / dotp(&p, &ap);
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] = r[i] - alpha * ap[i];
        }
        if dotp(&r, &r).f64() <= tol * tol * bb {
            return (it, t.elapsed().as_secs_f64(), true);
        }
        prec(&r, &mut z);
        let rz2 = dotp(&r, &z);
        let beta = rz2 / rz;
        rz = rz2;
        for i in 0..n {
            p[i] = z[i] + beta * p[i];
        }
    }
    (max_it, t.elapsed().as_secs_f64(), false)
}

fn gb(bytes: f64, secs: f64) -> f64 {
    bytes / secs / 1e9
}

fn main() {
    let mut sizes: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    if sizes.is_empty() {
        sizes = vec![6_500, 50_000, 500_000];
    }
    let mut gpu = match solver_gpu::open() {
        Ok(g) => Some(g),
        Err(e) => {
            println!("no GPU solver: {e}; CPU columns only");
            None
        }
    };
    let adapter = gpu
        .as_ref()
        .map(|g| {
            let a = g.adapter();
            let l = g.limits();
            format!(
                "{} ({}, {}, {}); max_storage_buffer_binding_size {} MiB, max_buffer_size {} MiB",
                a.name,
                a.backend,
                a.device_type,
                a.driver_info,
                l.max_storage_buffer_binding_size >> 20,
                l.max_buffer_size >> 20
            )
        })
        .unwrap_or_else(|| "none".into());
    println!("adapter: {adapter}");
    let software = gpu.as_ref().is_some_and(|g| {
        let a = g.adapter();
        a.device_type == "Cpu" || a.name.contains("llvmpipe") || a.name.contains("lavapipe")
    });
    if software {
        println!("note: this adapter is a software rasterizer running on the CPU; its numbers are not GPU performance");
    }
    let wg = if software { "adapter" } else { "gpu" };
    println!("bytes per minimal PCG iteration and column: matrix blocks 36 B + column index 4 B per block, row pointers, \
              block-Jacobi inverse 36 B per row, vectors 12 x 4 B per unknown (SpMV p->Ap 2, update x,p,r,Ap->x,r,z 7, direction 3)");
    println!();
    println!("| block rows | blocks/row | {wg} ms/iter (1 rhs) | {wg} GB/s | {wg} ms/iter (4 rhs) | {wg} f32 PCG its to 1e-6 | solver 1e-6 cold its (ms) | solver 1e-6 warm its (ms) | cpu f32 ms/iter | cpu f32 its | cpu f64 ms/iter | cpu f64 its | cpu SpMV f32 GB/s | cpu SpMV f64 GB/s |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let mut precision_rows = Vec::new();
    let mut ceiling_rows = Vec::new();
    for &rows in &sizes {
        let mut rng = Rng(rows as u64);
        let (mut a, fixed) = synthetic(rows, 1e-3, &mut rng);
        let n = 3 * a.n;
        let full = expand(&a, &fixed);
        let nnzb = full.col_idx.len();
        let per_row = nnzb as f64 / a.n as f64;
        let matrix_bytes = nnzb as f64 * 40.0 + (a.n as f64 + 1.0) * 4.0;
        let nv = a.n as f64;
        let vec_bytes = move |cols: usize| (cols * n) as f64 * 4.0 * 12.0 + nv * 36.0;
        let b: Vec<f64> = (0..n).map(|_| rng.next() + 1.5).collect();
        let b32: Vec<f32> = b.iter().map(|&v| v as f32).collect();
        let mut cells: Vec<String> = vec![a.n.to_string(), format!("{per_row:.1}")];

        // GPU (or whatever adapter there is).
        let mut gpu_cells = vec!["-".to_string(); 6];
        if let Some(g) = gpu.as_mut() {
            match gpu_run(g, &mut a, &fixed, &b, &b32, matrix_bytes, &vec_bytes) {
                Ok(c) => gpu_cells = c,
                Err(e) => gpu_cells[0] = format!("error: {e}"),
            }
            if g.adapter().shader_f64 {
                let cells = match precision_run(g, &a, &fixed, &b, nnzb) {
                    Ok(c) => c,
                    Err(e) => vec![format!("error: {e}")],
                };
                precision_rows.push(format!("| {} | {} |", a.n, cells.join(" | ")));
            }
        }
        cells.extend(gpu_cells);

        // CPU, single thread.
        let f32m = to_f32(&full);
        let max_it = 5000;
        let (it32, t32, ok32) = cpu_pcg(&f32m, &b32, 1e-6, max_it);
        let (it64, t64, ok64) = cpu_pcg(&full, &b, 1e-6, max_it);
        let mark = |ok: bool| if ok { "" } else { " (cap)" };
        cells.push(format!("{:.2}", 1e3 * t32 / it32 as f64));
        cells.push(format!("{it32}{}", mark(ok32)));
        cells.push(format!("{:.2}", 1e3 * t64 / it64 as f64));
        cells.push(format!("{it64}{}", mark(ok64)));
        let reps = (20_000_000 / nnzb).clamp(3, 200);
        let mut y32 = vec![0f32; n];
        let t = Instant::now();
        for _ in 0..reps {
            spmv(&f32m, &b32, &mut y32);
        }
        let s32 = t.elapsed().as_secs_f64() / reps as f64;
        let mut y64 = vec![0f64; n];
        let t = Instant::now();
        for _ in 0..reps {
            spmv(&full, &b, &mut y64);
        }
        let s64 = t.elapsed().as_secs_f64() / reps as f64;
        let spmv32 = matrix_bytes + 2.0 * n as f64 * 4.0;
        let spmv64 = nnzb as f64 * 76.0 + (a.n as f64 + 1.0) * 8.0 + 2.0 * n as f64 * 8.0;
        cells.push(format!("{:.2}", gb(spmv32, s32)));
        cells.push(format!("{:.2}", gb(spmv64, s64)));
        std::hint::black_box((&y32, &y64));
        // The read ceiling over the bytes of a minimal iteration.
        if let Some(g) = gpu.as_ref() {
            let bytes = matrix_bytes + vec_bytes(1);
            let iteration = cells[3].parse::<f64>().ok();
            ceiling_rows.push(ceiling_row(g, a.n, bytes, gb(spmv32, s32), iteration));
        }
        println!("| {} |", cells.join(" | "));
    }
    if !ceiling_rows.is_empty() {
        println!();
        println!("read ceiling over the bytes of a minimal PCG iteration (1 rhs): the least work per byte \
                  (sum 16-byte elements, one partial per invocation; shaders/stream.wgsl) from a storage buffer \
                  (over at most one storage binding); a plain single-thread CPU sum of as many f32; the PCG \
                  iteration and the storage-buffer ceiling as a share of the single-thread CPU SpMV (f32)");
        println!();
        println!("| block rows | MB per iteration | {wg} storage-buffer read GB/s | cpu 1-thread read GB/s | cpu SpMV f32 GB/s | {wg} PCG iteration / cpu SpMV | {wg} storage-buffer read / cpu SpMV |");
        println!("|---|---|---|---|---|---|---|");
        for r in ceiling_rows {
            println!("{r}");
        }
    }
    if !precision_rows.is_empty() {
        println!();
        println!("precision, same kernels on the scalar expansion (9 entries per block, scalar Jacobi); \
                  bytes per iteration: entries (value + 4 B column), 12 vector passes, inverse diagonal");
        println!();
        println!("| block rows | {wg} f32 ms/iter | {wg} f32 GB/s | {wg} f64 ms/iter | {wg} f64 GB/s | f32 its to 1e-6 | f64 its to 1e-6 | f64 its to 1e-10 (ms) |");
        println!("|---|---|---|---|---|---|---|---|");
        for r in precision_rows {
            println!("{r}");
        }
    }
}

/// f32 and f64 kernels on the scalar expansion of the prepared matrix:
/// per-iteration time (difference of a 16- and an 80-iteration run, so the
/// setup cancels), effective bandwidth, iterations to 1e-6 and 1e-10.
fn precision_run(
    g: &mut GpuSolver,
    a: &BlockSym3,
    fixed: &[bool],
    b: &[f64],
    nnzb: usize,
) -> Result<Vec<String>, String> {
    g.prepare_blocks(a, fixed).map_err(|e| e.to_string())?;
    let n = b.len();
    let mut cells = Vec::new();
    let mut its = Vec::new();
    for p in [Precision::F32, Precision::F64] {
        let fp = p.bytes() as f64;
        let mut run = |tol: f64, iters: usize| {
            let t = Instant::now();
            let out = kernels::scalar_pcg(g, p, b, 1, tol, iters).map_err(|e| e.to_string())?;
            Ok::<_, String>((out, t.elapsed().as_secs_f64()))
        };
        let (short, t16) = run(0.0, 16)?;
        let (long, t80) = run(0.0, 80)?;
        let per_iter = (t80 - t16) / (long.dispatched - short.dispatched) as f64;
        let bytes = 9.0 * nnzb as f64 * (fp + 4.0) + (n as f64 + 1.0) * 4.0 + n as f64 * fp * 13.0;
        cells.push(format!("{:.2}", 1e3 * per_iter));
        cells.push(format!("{:.2}", gb(bytes, per_iter)));
        let (to6, _) = run(1e-6, 20_000)?;
        its.push(converged(&to6));
        if p == Precision::F64 {
            let (to10, t) = run(1e-10, 20_000)?;
            its.push(format!("{} ({:.0})", converged(&to10), 1e3 * t));
        }
    }
    cells.extend(its);
    Ok(cells)
}

/// One row of the read-ceiling table (`spmv_cpu`: the single-thread CPU SpMV
/// in GB/s; `iteration`: the adapter's PCG iteration in GB/s).
fn ceiling_row(
    g: &GpuSolver,
    rows: usize,
    bytes: f64,
    spmv_cpu: f64,
    iteration: Option<f64>,
) -> String {
    let c = match kernels::read_ceiling(g, bytes as u64, 20) {
        Ok(c) => c,
        Err(e) => return format!("| {rows} | {:.1} | error: {e} | | | | |", bytes / 1e6),
    };
    // A single-thread CPU read of as many f32 (eight accumulators, so it
    // vectorises), best of five.
    let data: Vec<f32> = (0..(bytes as usize / 4))
        .map(|i| (i % 1000) as f32)
        .collect();
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t = Instant::now();
        let mut acc = [0f32; 8];
        for ch in data.chunks_exact(8) {
            for (a, v) in acc.iter_mut().zip(ch) {
                *a += v;
            }
        }
        std::hint::black_box(acc);
        best = best.min(t.elapsed().as_secs_f64());
    }
    let cpu_read = gb(bytes, best);
    let pct = |v: f64| format!("{:.0} %", 100.0 * v / spmv_cpu);
    format!(
        "| {rows} | {:.1} | {:.2} | {:.2} | {:.2} | {} | {} |",
        bytes / 1e6,
        c.bandwidth() / 1e9,
        cpu_read,
        spmv_cpu,
        iteration.map_or("-".into(), pct),
        pct(c.bandwidth() / 1e9)
    )
}

fn converged(out: &kernels::PcgOutput) -> String {
    let mark = if out.status[0] == 1 {
        ""
    } else {
        " (not converged)"
    };
    format!("{}{mark}", out.iterations[0])
}

fn gpu_run(
    g: &mut GpuSolver,
    a: &mut BlockSym3,
    fixed: &[bool],
    b: &[f64],
    b32: &[f32],
    matrix_bytes: f64,
    vec_bytes: &dyn Fn(usize) -> f64,
) -> Result<Vec<String>, String> {
    let n = b.len();
    g.prepare_blocks(a, fixed).map_err(|e| e.to_string())?;
    let mut cells = Vec::new();
    // Per-iteration time: fixed iteration counts (tolerance 0), after a
    // warm-up; the difference of an 80- and a 16-iteration run, so the set-up
    // (upload of b, first preconditioner application, read-back) cancels.
    let mut per_iter = [0.0; 2];
    for (slot, cols) in [1usize, 4].into_iter().enumerate() {
        let rhs: Vec<f32> = (0..cols).flat_map(|_| b32.iter().copied()).collect();
        kernels::pcg(g, &rhs, cols, 0.0, 16).map_err(|e| e.to_string())?;
        let mut run = |iters: usize| {
            let t = Instant::now();
            let out = kernels::pcg(g, &rhs, cols, 0.0, iters).map_err(|e| e.to_string())?;
            Ok::<_, String>((out.dispatched, t.elapsed().as_secs_f64()))
        };
        let (d16, t16) = run(16)?;
        let (d80, t80) = run(80)?;
        per_iter[slot] = (t80 - t16) / (d80 - d16) as f64;
    }
    for cols in [1usize, 4] {
        let prof = kernels::profile_iteration(g, cols, 20).map_err(|e| e.to_string())?;
        let parts: Vec<String> = prof
            .iter()
            .map(|(k, t)| format!("{k} {:.3}", 1e3 * t))
            .collect();
        eprintln!(
            "  {} rows, {cols} rhs, ms per dispatch: {}",
            a.n,
            parts.join(", ")
        );
    }
    cells.push(format!("{:.2}", 1e3 * per_iter[0]));
    cells.push(format!(
        "{:.2}",
        gb(matrix_bytes + vec_bytes(1), per_iter[0])
    ));
    cells.push(format!("{:.2}", 1e3 * per_iter[1]));
    // Plain f32 PCG to 1e-6.
    let out = kernels::pcg(g, b32, 1, 1e-6, 5000).map_err(|e| e.to_string())?;
    cells.push(converged(&out));
    // The refined solver to 1e-6: previous outer iteration, then perturbed values.
    g.set_tolerance(1e-6);
    let mut prev = vec![0.0; n];
    g.solve_with_guess(b, &mut prev, 1)
        .map_err(|e| e.to_string())?;
    let mut rng = Rng(7);
    for blk in a.blocks.iter_mut() {
        let f = 1.0 + 1e-3 * rng.next().abs();
        for v in blk.iter_mut() {
            *v *= f;
        }
    }
    g.prepare_blocks(a, fixed).map_err(|e| e.to_string())?;
    let mut x = vec![0.0; n];
    let t = Instant::now();
    let cold = g
        .solve_with_guess(b, &mut x, 1)
        .map_err(|e| e.to_string())?;
    let tc = t.elapsed().as_secs_f64();
    let mut x = prev;
    let t = Instant::now();
    let warm = g
        .solve_with_guess(b, &mut x, 1)
        .map_err(|e| e.to_string())?;
    let tw = t.elapsed().as_secs_f64();
    g.set_tolerance(1e-10);
    cells.push(format!("{} ({:.0})", cold.iterations, 1e3 * tc));
    cells.push(format!("{} ({:.0})", warm.iterations, 1e3 * tw));
    Ok(cells)
}
