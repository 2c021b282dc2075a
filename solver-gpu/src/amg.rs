//! Smoothed-aggregation algebraic multigrid (SA-AMG), built on the CPU in f64:
//! the hierarchy behind the GPU V-cycle preconditioner (`amg_gpu.rs`,
//! `shaders/amg.wgsl`), plus an f64 reference V-cycle and PCG for the tests.
//!
//! # Setup (per level, on the full symmetric block-CSR matrix, `bs` = 3 or 1)
//!
//! 1. **Strength**: off-diagonal block `(i, j)` is strong when
//!    `||A_ij||_F >= theta sqrt(||A_ii||_F ||A_jj||_F)` (`theta` = 0.08).
//!    Rows with no strong neighbour (held vertices: identity rows) belong to no
//!    aggregate: their row of `P` is zero and the smoother alone handles them.
//! 2. **Aggregation** (Vanek, Mandel, Brezina): pass 1 makes an aggregate of
//!    every node whose strong neighbourhood is still free; pass 2 attaches the
//!    leftovers to the pass-1 aggregate of their strongest aggregated neighbour;
//!    pass 3 groups whatever is left with its free strong neighbours.
//! 3. **Prolongator**: tentative `P0` = identity block per (node, its aggregate),
//!    smoothed `P = (I - omega D^-1 A) P0`, `omega = 4 / (3 rho(D^-1 A))` (`rho`
//!    from a few power iterations; `D` = block diagonal); `R = P^T` is stored.
//! 4. **Coarse operator** `A_c = R (A P)` (two row-parallel sparse products).
//!
//! **Affine near-null space** ([`Hierarchy::build_affine`], block size 3, given
//! the vertex positions): the tentative prolongator interpolates the 12 affine
//! motions `x -> M x + t` of each aggregate (a QR of the aggregate's rows of
//! those modes; `k = 12` coarse unknowns per aggregate, a mode the aggregate
//! cannot carry gives a zero column and a decoupled unit row of `A_c`), and the
//! coarse levels recurse with their QR factors as near-null space. `P`, `R` are
//! then scalar, coarse matrices 12x12-block.
//!
//! Coarsening stops at `max_coarse` unknowns (or when it stalls, more than 0.8 of
//! the rows left); the coarsest matrix is inverted densely (Cholesky, f64).
//!
//! # V-cycle (the preconditioner `z = M^-1 r`; symmetric, so PCG stays valid)
//!
//! ```text
//! vcycle(l, b):
//!   l coarsest: return C^-1 b                          (dense inverse)
//!   x = w D^-1 b; repeat sweeps-1: x += w D^-1 (b - A x)   (pre-smoothing)
//!   x += P vcycle(l+1, R (b - A x))                    (coarse correction)
//!   repeat sweeps: x += w D^-1 (b - A x)               (post-smoothing)
//! ```
//!
//! with damped block Jacobi `w = 4 / (3 rho(D^-1 A))`. The pre-smoother from
//! zero and the post-smoother are adjoint (same polynomial in `D^-1 A`), so `M`
//! is symmetric positive definite.

use rayon::prelude::*;

/// A block-CSR matrix (`bs` x `bs` blocks, row-major), possibly rectangular.
#[derive(Debug, Clone, PartialEq)]
pub struct Bsr {
    pub bs: usize,
    /// Block rows.
    pub rows: usize,
    /// Block columns.
    pub cols: usize,
    pub row_ptr: Vec<u32>,
    pub col_idx: Vec<u32>,
    /// `bs * bs` f64 per stored block.
    pub vals: Vec<f64>,
}

impl Bsr {
    /// A square scalar matrix from its rows of `(column, value)`, each row
    /// sorted by column here (stably: repeated columns keep their order).
    pub fn scalar_from_rows(rows: Vec<Vec<(u32, f64)>>) -> Bsr {
        let n = rows.len();
        let mut row_ptr = Vec::with_capacity(n + 1);
        row_ptr.push(0u32);
        let (mut col_idx, mut vals) = (Vec::new(), Vec::new());
        for mut r in rows {
            r.sort_by_key(|e| e.0);
            for (j, v) in r {
                col_idx.push(j);
                vals.push(v);
            }
            row_ptr.push(col_idx.len() as u32);
        }
        Bsr {
            bs: 1,
            rows: n,
            cols: n,
            row_ptr,
            col_idx,
            vals,
        }
    }

    pub fn nnz_blocks(&self) -> usize {
        self.col_idx.len()
    }

    pub fn same_pattern(&self, o: &Bsr) -> bool {
        self.bs == o.bs
            && self.rows == o.rows
            && self.cols == o.cols
            && self.row_ptr == o.row_ptr
            && self.col_idx == o.col_idx
    }

    fn range(&self, i: usize) -> std::ops::Range<usize> {
        self.row_ptr[i] as usize..self.row_ptr[i + 1] as usize
    }

    fn block(&self, k: usize) -> &[f64] {
        let bb = self.bs * self.bs;
        &self.vals[k * bb..(k + 1) * bb]
    }

    /// `y = A x` for one column (`x`: cols * bs, `y`: rows * bs).
    pub fn matvec(&self, x: &[f64], y: &mut [f64]) {
        let bs = self.bs;
        y.par_chunks_mut(bs).enumerate().for_each(|(i, out)| {
            out.fill(0.0);
            for k in self.range(i) {
                let j = self.col_idx[k] as usize;
                let m = self.block(k);
                for q in 0..bs {
                    for t in 0..bs {
                        out[q] += m[q * bs + t] * x[j * bs + t];
                    }
                }
            }
        });
    }

    /// `A^T`, blocks transposed.
    pub fn transpose(&self) -> Bsr {
        let bs = self.bs;
        let bb = bs * bs;
        let mut count = vec![0u32; self.cols + 1];
        for &j in &self.col_idx {
            count[j as usize + 1] += 1;
        }
        for j in 0..self.cols {
            count[j + 1] += count[j];
        }
        let row_ptr = count.clone();
        let mut next = count;
        let mut col_idx = vec![0u32; self.nnz_blocks()];
        let mut vals = vec![0f64; self.vals.len()];
        for i in 0..self.rows {
            for k in self.range(i) {
                let j = self.col_idx[k] as usize;
                let d = next[j] as usize;
                next[j] += 1;
                col_idx[d] = i as u32;
                let (src, dst) = (self.block(k), &mut vals[d * bb..(d + 1) * bb]);
                for q in 0..bs {
                    for t in 0..bs {
                        dst[t * bs + q] = src[q * bs + t];
                    }
                }
            }
        }
        Bsr {
            bs,
            rows: self.cols,
            cols: self.rows,
            row_ptr,
            col_idx,
            vals,
        }
    }

    /// Inverses of the diagonal blocks (f64), or `None` if one is missing or
    /// not positive definite.
    pub fn inverse_diagonal(&self) -> Option<Vec<f64>> {
        let bs = self.bs;
        let bb = bs * bs;
        let mut out = vec![0f64; self.rows * bb];
        let ok = out.par_chunks_mut(bb).enumerate().all(|(i, dst)| {
            let Some(k) = self.range(i).find(|&k| self.col_idx[k] as usize == i) else {
                return false;
            };
            let d = self.block(k);
            let inv = if bs == 1 {
                (d[0] > 0.0 && d[0].is_finite()).then(|| vec![1.0 / d[0]])
            } else if bs == 3 {
                crate::block_jacobi::invert_spd3(d).map(|m| m.to_vec())
            } else {
                dense_spd_inverse(d, bs)
            };
            match inv {
                Some(v) if v.iter().all(|a| a.is_finite()) => {
                    dst.copy_from_slice(&v);
                    true
                }
                _ => false,
            }
        });
        ok.then_some(out)
    }

    /// `A B` (row-parallel Gustavson product; the pattern keeps structural zeros).
    pub fn mul(&self, b: &Bsr) -> Bsr {
        assert_eq!(self.cols, b.rows);
        assert_eq!(self.bs, b.bs);
        let bs = self.bs;
        let bb = bs * bs;
        let rows: Vec<(Vec<u32>, Vec<f64>)> = (0..self.rows)
            .into_par_iter()
            .map_init(
                || (vec![u32::MAX; b.cols], Vec::new(), Vec::new()),
                |(mark, cols, vals): &mut (Vec<u32>, Vec<u32>, Vec<f64>), i| {
                    cols.clear();
                    vals.clear();
                    for k in self.range(i) {
                        let ab = self.block(k);
                        for kk in b.range(self.col_idx[k] as usize) {
                            let c = b.col_idx[kk] as usize;
                            if mark[c] == u32::MAX {
                                mark[c] = cols.len() as u32;
                                cols.push(c as u32);
                                vals.resize(vals.len() + bb, 0.0);
                            }
                            let p = mark[c] as usize * bb;
                            gemm_acc(bs, ab, b.block(kk), &mut vals[p..p + bb]);
                        }
                    }
                    let mut order: Vec<usize> = (0..cols.len()).collect();
                    order.sort_unstable_by_key(|&p| cols[p]);
                    let oc: Vec<u32> = order.iter().map(|&p| cols[p]).collect();
                    let mut ov = Vec::with_capacity(vals.len());
                    for &p in &order {
                        ov.extend_from_slice(&vals[p * bb..(p + 1) * bb]);
                    }
                    for &c in cols.iter() {
                        mark[c as usize] = u32::MAX;
                    }
                    (oc, ov)
                },
            )
            .collect();
        assemble(bs, self.rows, b.cols, rows)
    }

    /// Dense row-major copy (`rows bs` x `cols bs`), symmetrised if square.
    fn dense_symmetric(&self) -> Vec<f64> {
        let bs = self.bs;
        let (nr, nc) = (self.rows * bs, self.cols * bs);
        let mut d = vec![0f64; nr * nc];
        for i in 0..self.rows {
            for k in self.range(i) {
                let j = self.col_idx[k] as usize;
                let m = self.block(k);
                for q in 0..bs {
                    for t in 0..bs {
                        d[(i * bs + q) * nc + j * bs + t] = m[q * bs + t];
                    }
                }
            }
        }
        for r in 0..nr {
            for c in 0..r {
                let s = 0.5 * (d[r * nc + c] + d[c * nc + r]);
                d[r * nc + c] = s;
                d[c * nc + r] = s;
            }
        }
        d
    }
}

fn assemble(bs: usize, rows: usize, cols: usize, parts: Vec<(Vec<u32>, Vec<f64>)>) -> Bsr {
    let mut row_ptr = Vec::with_capacity(rows + 1);
    row_ptr.push(0u32);
    let total: usize = parts.iter().map(|p| p.0.len()).sum();
    let mut col_idx = Vec::with_capacity(total);
    let mut vals = Vec::with_capacity(total * bs * bs);
    for (c, v) in parts {
        col_idx.extend_from_slice(&c);
        vals.extend_from_slice(&v);
        row_ptr.push(col_idx.len() as u32);
    }
    Bsr {
        bs,
        rows,
        cols,
        row_ptr,
        col_idx,
        vals,
    }
}

/// `c += a b` for `bs` x `bs` row-major blocks.
fn gemm_acc(bs: usize, a: &[f64], b: &[f64], c: &mut [f64]) {
    for q in 0..bs {
        for t in 0..bs {
            let aq = a[q * bs + t];
            for u in 0..bs {
                c[q * bs + u] += aq * b[t * bs + u];
            }
        }
    }
}

fn frob(m: &[f64]) -> f64 {
    m.iter().map(|v| v * v).sum::<f64>().sqrt()
}

/// Tuning of the hierarchy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AmgOptions {
    /// Strength threshold.
    pub theta: f64,
    /// Stop coarsening at or below this many unknowns (rows * bs).
    pub max_coarse: usize,
    /// Largest coarsest matrix (unknowns) that is inverted densely; a hierarchy
    /// whose coarsening stalls above it is refused.
    pub dense_max: usize,
    pub max_levels: usize,
    /// Smoothing sweeps before and after the coarse correction.
    pub sweeps: usize,
    /// Jacobi smoother weight times `rho(D^-1 A)`.
    pub smoother_weight: f64,
    /// Power iterations for `rho(D^-1 A)`.
    pub power_iterations: usize,
}

impl Default for AmgOptions {
    fn default() -> Self {
        AmgOptions {
            theta: 0.08,
            max_coarse: 600,
            dense_max: 2000,
            max_levels: 12,
            sweeps: 1,
            smoother_weight: 4.0 / 3.0,
            power_iterations: 15,
        }
    }
}

/// Columns of the affine near-null space: 3 translations and the 9 entries of
/// a linear map.
pub const AFFINE_MODES: usize = 12;

/// One level above the coarsest.
#[derive(Debug, Clone)]
pub struct Level {
    pub a: Bsr,
    /// Inverted diagonal blocks of `a`.
    pub dinv: Vec<f64>,
    /// Jacobi smoother weight.
    pub omega: f64,
    /// Aggregate of each row (`u32::MAX`: none).
    pub agg: Vec<u32>,
    pub naggs: usize,
    /// Prolongator (rows of `a` x next level's rows) and `R = P^T`; scalar
    /// (`bs` = 1) in an affine hierarchy.
    pub p: Bsr,
    pub r: Bsr,
    /// The tentative prolongator of an affine hierarchy (kept for rebuilds
    /// with new values).
    pub tentative: Option<Bsr>,
}

/// The SA-AMG hierarchy.
#[derive(Debug, Clone)]
pub struct Hierarchy {
    /// Block size of the finest level.
    pub bs: usize,
    /// Built with the affine near-null space ([`Hierarchy::build_affine`]):
    /// levels past the finest have [`AFFINE_MODES`]-square blocks.
    pub affine: bool,
    pub opts: AmgOptions,
    pub levels: Vec<Level>,
    /// The coarsest matrix and its dense inverse (row-major, `n x n`).
    pub coarse: Bsr,
    pub coarse_inv: Vec<f64>,
}

/// Why a hierarchy could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AmgError {
    #[error("a diagonal block is not positive definite")]
    NotPositiveDefinite,
    #[error("{0} vertex positions for an affine near-null space of {1} block rows of size {2} (3 needed)")]
    Positions(usize, usize, usize),
    #[error("coarsening stalled at {0} unknowns (dense coarse solve limited to {1})")]
    Stalled(usize, usize),
}

/// Strength graph (CSR, strong neighbours of each row, with their measures).
fn strength(a: &Bsr, theta: f64) -> (Vec<u32>, Vec<u32>, Vec<f64>) {
    let diag: Vec<f64> = (0..a.rows)
        .into_par_iter()
        .map(|i| {
            a.range(i)
                .find(|&k| a.col_idx[k] as usize == i)
                .map_or(0.0, |k| frob(a.block(k)))
        })
        .collect();
    let rows: Vec<(Vec<u32>, Vec<f64>)> = (0..a.rows)
        .into_par_iter()
        .map(|i| {
            let mut c = Vec::new();
            let mut v = Vec::new();
            for k in a.range(i) {
                let j = a.col_idx[k] as usize;
                if j == i {
                    continue;
                }
                let s = frob(a.block(k));
                if s > 0.0 && s >= theta * (diag[i] * diag[j]).sqrt() {
                    c.push(j as u32);
                    v.push(s / (diag[i] * diag[j]).sqrt());
                }
            }
            (c, v)
        })
        .collect();
    let mut ptr = vec![0u32];
    let mut idx = Vec::new();
    let mut val = Vec::new();
    for (c, v) in rows {
        idx.extend(c);
        val.extend(v);
        ptr.push(idx.len() as u32);
    }
    (ptr, idx, val)
}

/// Greedy aggregation; returns the aggregate of each row (`u32::MAX` for rows
/// without strong neighbours) and the number of aggregates.
pub fn aggregate(a: &Bsr, theta: f64) -> (Vec<u32>, usize) {
    const FREE: u32 = u32::MAX;
    let (sp, si, sv) = strength(a, theta);
    let n = a.rows;
    let nb = |i: usize| sp[i] as usize..sp[i + 1] as usize;
    let mut agg = vec![FREE; n];
    let mut next = 0u32;
    // Pass 1: whole free strong neighbourhoods.
    for i in 0..n {
        if agg[i] != FREE || sp[i] == sp[i + 1] {
            continue;
        }
        if nb(i).all(|k| agg[si[k] as usize] == FREE) {
            agg[i] = next;
            for k in nb(i) {
                agg[si[k] as usize] = next;
            }
            next += 1;
        }
    }
    // Pass 2: join the pass-1 aggregate of the strongest aggregated neighbour.
    let pass1 = agg.clone();
    for (i, slot) in agg.iter_mut().enumerate() {
        if *slot != FREE {
            continue;
        }
        let mut best = (0.0, FREE);
        for k in nb(i) {
            let g = pass1[si[k] as usize];
            if g != FREE && sv[k] > best.0 {
                best = (sv[k], g);
            }
        }
        *slot = best.1;
    }
    // Pass 3: leftovers with strong neighbours form aggregates with their free
    // strong neighbours.
    for i in 0..n {
        if agg[i] != FREE || sp[i] == sp[i + 1] {
            continue;
        }
        agg[i] = next;
        for k in nb(i) {
            let j = si[k] as usize;
            if agg[j] == FREE {
                agg[j] = next;
            }
        }
        next += 1;
    }
    (agg, next as usize)
}

/// `rho(D^-1 A)` by power iteration (Rayleigh quotient `x.Ax / x.Dx`).
fn spectral_radius(a: &Bsr, dinv: &[f64], iters: usize) -> f64 {
    let bs = a.bs;
    let bb = bs * bs;
    let n = a.rows * bs;
    // Deterministic, non-smooth start.
    let mut x: Vec<f64> = (0..n)
        .map(|i| {
            let h = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            ((h >> 11) as f64 / (1u64 << 53) as f64) + 0.5
        })
        .collect();
    let mut ax = vec![0f64; n];
    for _ in 0..iters.max(1) {
        a.matvec(&x, &mut ax);
        let y: Vec<f64> = ax
            .par_chunks(bs)
            .enumerate()
            .flat_map_iter(|(i, r)| {
                let m = &dinv[i * bb..(i + 1) * bb];
                (0..bs).map(move |q| (0..bs).map(|t| m[q * bs + t] * r[t]).sum::<f64>())
            })
            .collect();
        let ny = y.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(ny > 0.0 && ny.is_finite()) {
            break;
        }
        x = y.into_iter().map(|v| v / ny).collect();
    }
    // Rayleigh quotient of the generalised problem A x = lambda D x.
    a.matvec(&x, &mut ax);
    let xax: f64 = x.iter().zip(&ax).map(|(a, b)| a * b).sum();
    let xdx = d_norm2(a, &x);
    let rho = if xdx > 0.0 && xax.is_finite() {
        xax / xdx
    } else {
        1.0
    };
    rho.max(1e-12)
}

/// `x . D x` with `D` the block diagonal of `a`.
fn d_norm2(a: &Bsr, x: &[f64]) -> f64 {
    let bs = a.bs;
    (0..a.rows)
        .into_par_iter()
        .map(|i| {
            let Some(k) = a.range(i).find(|&k| a.col_idx[k] as usize == i) else {
                return 0.0;
            };
            let m = a.block(k);
            let mut s = 0.0;
            for q in 0..bs {
                for t in 0..bs {
                    s += x[i * bs + q] * m[q * bs + t] * x[i * bs + t];
                }
            }
            s
        })
        .sum()
}

/// `P = (I - omega D^-1 A) P0` for the aggregation `agg`.
fn smoothed_prolongator(a: &Bsr, dinv: &[f64], agg: &[u32], naggs: usize, omega: f64) -> Bsr {
    let bs = a.bs;
    let bb = bs * bs;
    let rows: Vec<(Vec<u32>, Vec<f64>)> = (0..a.rows)
        .into_par_iter()
        .map(|i| {
            // (A P0) row i: blocks A_ij summed per aggregate of j.
            let mut cols: Vec<u32> = Vec::new();
            let mut acc: Vec<f64> = Vec::new();
            for k in a.range(i) {
                let g = agg[a.col_idx[k] as usize];
                if g == u32::MAX {
                    continue;
                }
                let p = match cols.iter().position(|&c| c == g) {
                    Some(p) => p,
                    None => {
                        cols.push(g);
                        acc.resize(acc.len() + bb, 0.0);
                        cols.len() - 1
                    }
                };
                for (o, v) in acc[p * bb..(p + 1) * bb].iter_mut().zip(a.block(k)) {
                    *o += v;
                }
            }
            if agg[i] != u32::MAX && !cols.contains(&agg[i]) {
                cols.push(agg[i]);
                acc.resize(acc.len() + bb, 0.0);
            }
            let m = &dinv[i * bb..(i + 1) * bb];
            let mut order: Vec<usize> = (0..cols.len()).collect();
            order.sort_unstable_by_key(|&p| cols[p]);
            let mut oc = Vec::with_capacity(cols.len());
            let mut ov = Vec::with_capacity(acc.len());
            for p in order {
                let mut blk = vec![0f64; bb];
                gemm_acc(bs, m, &acc[p * bb..(p + 1) * bb], &mut blk);
                for v in blk.iter_mut() {
                    *v *= -omega;
                }
                if cols[p] == agg[i] {
                    for q in 0..bs {
                        blk[q * bs + q] += 1.0;
                    }
                }
                oc.push(cols[p]);
                ov.extend_from_slice(&blk);
            }
            (oc, ov)
        })
        .collect();
    assemble(bs, a.rows, naggs, rows)
}

/// Inverse of a dense SPD matrix (row-major `n x n`) by Cholesky, or `None`.
pub fn dense_spd_inverse(a: &[f64], n: usize) -> Option<Vec<f64>> {
    // L row-major, lower.
    let mut l = a.to_vec();
    for j in 0..n {
        let mut d = l[j * n + j];
        for k in 0..j {
            d -= l[j * n + k] * l[j * n + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        let d = d.sqrt();
        l[j * n + j] = d;
        let (head, tail) = l.split_at_mut((j + 1) * n);
        let lj = &head[j * n..j * n + j];
        tail.par_chunks_mut(n).for_each(|row| {
            let mut s = row[j];
            for k in 0..j {
                s -= row[k] * lj[k];
            }
            row[j] = s / d;
        });
    }
    // Columns of A^-1 = L^-T L^-1 e_c, in parallel.
    let cols: Vec<Vec<f64>> = (0..n)
        .into_par_iter()
        .map(|c| {
            let mut y = vec![0f64; n];
            y[c] = 1.0;
            for i in c..n {
                let mut s = y[i];
                for k in c..i {
                    s -= l[i * n + k] * y[k];
                }
                y[i] = s / l[i * n + i];
            }
            for i in (0..n).rev() {
                let mut s = y[i];
                for k in i + 1..n {
                    s -= l[k * n + i] * y[k];
                }
                y[i] = s / l[i * n + i];
            }
            y
        })
        .collect();
    let mut inv = vec![0f64; n * n];
    for (c, col) in cols.iter().enumerate() {
        for r in 0..n {
            inv[r * n + c] = col[r];
        }
    }
    Some(inv)
}

impl Hierarchy {
    /// Build the hierarchy of `a` (full symmetric BSR, held rows identity) with
    /// the translations (constants per component) as near-null space.
    /// `reuse`: a previous hierarchy of a matrix with the same pattern, whose
    /// aggregates are kept (only the values are recomputed; the level patterns
    /// then stay the same).
    pub fn build(
        a: Bsr,
        opts: &AmgOptions,
        reuse: Option<&Hierarchy>,
    ) -> Result<Hierarchy, AmgError> {
        Self::build_with(a, opts, None, reuse)
    }

    /// As [`Hierarchy::build`], with the 12 affine motions of the vertices at
    /// `positions` (one per block row, `bs` = 3) as near-null space: the coarse
    /// levels represent every affine motion of each aggregate exactly, which the
    /// translations alone do not (the fine-tune Hessian's membrane and bending
    /// terms are nearly blind to local rotations and stretches). A reused
    /// hierarchy keeps its tentative prolongators too, so `positions` only
    /// matter on a first build.
    pub fn build_affine(
        a: Bsr,
        opts: &AmgOptions,
        positions: &[[f64; 3]],
        reuse: Option<&Hierarchy>,
    ) -> Result<Hierarchy, AmgError> {
        if a.bs != 3 || positions.len() != a.rows {
            return Err(AmgError::Positions(positions.len(), a.rows, a.bs));
        }
        Self::build_with(a, opts, Some(positions), reuse)
    }

    fn build_with(
        a: Bsr,
        opts: &AmgOptions,
        positions: Option<&[[f64; 3]]>,
        reuse: Option<&Hierarchy>,
    ) -> Result<Hierarchy, AmgError> {
        let bs = a.bs;
        let affine = positions.is_some();
        let reuse = reuse.filter(|h| {
            h.bs == bs
                && h.affine == affine
                && h.opts == *opts
                && h.levels
                    .first()
                    .map_or(&h.coarse, |l| &l.a)
                    .same_pattern(&a)
        });
        // Near-null space of the current level (affine only, first build).
        let mut modes = match (positions, reuse) {
            (Some(x), None) => affine_modes(x),
            _ => Vec::new(),
        };
        let mut levels: Vec<Level> = Vec::new();
        let mut a = a;
        loop {
            let depth = levels.len();
            let t0 = std::time::Instant::now();
            let dinv = a.inverse_diagonal().ok_or(AmgError::NotPositiveDefinite)?;
            let coarse_bs = if affine { AFFINE_MODES } else { bs };
            let (agg, naggs) = match reuse {
                Some(h) => match h.levels.get(depth) {
                    Some(l) => (l.agg.clone(), l.naggs),
                    None => break,
                },
                None => {
                    if a.rows * a.bs <= opts.max_coarse || depth + 1 >= opts.max_levels {
                        break;
                    }
                    let (agg, naggs) = aggregate(&a, opts.theta);
                    if naggs == 0 || (naggs * coarse_bs) as f64 > 0.8 * (a.rows * a.bs) as f64 {
                        break;
                    }
                    (agg, naggs)
                }
            };
            let t1 = std::time::Instant::now();
            let rho = spectral_radius(&a, &dinv, opts.power_iterations);
            let omega = 4.0 / (3.0 * rho);
            let t2 = std::time::Instant::now();
            let (p, tentative) = if affine {
                let p0 = match reuse.and_then(|h| h.levels[depth].tentative.clone()) {
                    Some(p0) => p0,
                    None => {
                        let (p0, coarse_modes) =
                            tentative_nullspace(a.bs, &agg, naggs, &modes, AFFINE_MODES);
                        modes = coarse_modes;
                        p0
                    }
                };
                (smoothed_scalar_prolongator(&a, &dinv, &p0, omega), Some(p0))
            } else {
                (smoothed_prolongator(&a, &dinv, &agg, naggs, omega), None)
            };
            let t3 = std::time::Instant::now();
            let r = p.transpose();
            let ac = if affine {
                galerkin_blocks(&a, &p, &r, AFFINE_MODES)
            } else {
                r.mul(&a.mul(&p))
            };
            let secs = |a: std::time::Instant, b: std::time::Instant| (b - a).as_secs_f64();
            let t4 = std::time::Instant::now();
            log::trace!(
                "AMG level {depth}: diagonal+aggregates {:.3} s, rho {:.3} s, P {:.3} s, R A P {:.3} s",
                secs(t0, t1),
                secs(t1, t2),
                secs(t2, t3),
                secs(t3, t4)
            );
            levels.push(Level {
                a,
                dinv,
                omega: opts.smoother_weight / rho,
                agg,
                naggs,
                p,
                r,
                tentative,
            });
            a = ac;
        }
        let n = a.rows * a.bs;
        if n > opts.dense_max {
            return Err(AmgError::Stalled(n, opts.dense_max));
        }
        let t = std::time::Instant::now();
        let coarse_inv =
            dense_spd_inverse(&a.dense_symmetric(), n).ok_or(AmgError::NotPositiveDefinite)?;
        log::trace!(
            "AMG coarsest {n}: inverse {:.3} s",
            t.elapsed().as_secs_f64()
        );
        Ok(Hierarchy {
            bs,
            affine,
            opts: *opts,
            levels,
            coarse: a,
            coarse_inv,
        })
    }

    /// Unknowns per level, finest first (the coarsest last).
    pub fn sizes(&self) -> Vec<usize> {
        self.levels
            .iter()
            .map(|l| &l.a)
            .chain([&self.coarse])
            .map(|a| a.rows * a.bs)
            .collect()
    }

    /// Stored blocks of all levels over those of the finest (operator complexity).
    pub fn operator_complexity(&self) -> f64 {
        let all: usize =
            self.levels.iter().map(|l| l.a.vals.len()).sum::<usize>() + self.coarse.vals.len();
        let fine = self
            .levels
            .first()
            .map_or(self.coarse.vals.len(), |l| l.a.vals.len());
        all as f64 / fine.max(1) as f64
    }

    /// Unknowns of the finest level.
    pub fn n(&self) -> usize {
        self.sizes()[0]
    }

    /// `z = M^-1 b` (one V-cycle, f64) for one column.
    pub fn vcycle(&self, b: &[f64]) -> Vec<f64> {
        self.vcycle_at(0, b)
    }

    fn vcycle_at(&self, l: usize, b: &[f64]) -> Vec<f64> {
        let Some(lv) = self.levels.get(l) else {
            let n = b.len();
            return (0..n)
                .into_par_iter()
                .map(|r| {
                    let row = &self.coarse_inv[r * n..(r + 1) * n];
                    row.iter().zip(b).map(|(a, x)| a * x).sum()
                })
                .collect();
        };
        let n = b.len();
        let mut x = vec![0f64; n];
        let mut t = vec![0f64; n];
        jacobi(lv, b, &mut x, false);
        for _ in 1..self.opts.sweeps {
            residual(&lv.a, b, &x, &mut t);
            jacobi(lv, &t, &mut x, true);
        }
        residual(&lv.a, b, &x, &mut t);
        let mut bc = vec![0f64; lv.r.rows * lv.r.bs];
        lv.r.matvec(&t, &mut bc);
        let xc = self.vcycle_at(l + 1, &bc);
        lv.p.matvec(&xc, &mut t);
        for (a, b) in x.iter_mut().zip(&t) {
            *a += b;
        }
        for _ in 0..self.opts.sweeps {
            residual(&lv.a, b, &x, &mut t);
            jacobi(lv, &t, &mut x, true);
        }
        x
    }
}

/// `t = b - A x`.
fn residual(a: &Bsr, b: &[f64], x: &[f64], t: &mut [f64]) {
    a.matvec(x, t);
    t.par_iter_mut().zip(b).for_each(|(t, b)| *t = b - *t);
}

/// `x = w D^-1 t` (`add`: `x += w D^-1 t`).
fn jacobi(lv: &Level, t: &[f64], x: &mut [f64], add: bool) {
    let bs = lv.a.bs;
    let bb = bs * bs;
    x.par_chunks_mut(bs).enumerate().for_each(|(i, out)| {
        let m = &lv.dinv[i * bb..(i + 1) * bb];
        for q in 0..bs {
            let s: f64 = (0..bs).map(|u| m[q * bs + u] * t[i * bs + u]).sum();
            if add {
                out[q] += lv.omega * s;
            } else {
                out[q] = lv.omega * s;
            }
        }
    });
}

/// Plain f64 PCG with preconditioner `prec` (for the tests): iterations to
/// `||r|| <= tol ||b||`, or `None` past `max_iters`.
pub fn pcg(
    a: &Bsr,
    b: &[f64],
    tol: f64,
    max_iters: usize,
    prec: impl Fn(&[f64]) -> Vec<f64>,
) -> Option<(Vec<f64>, usize)> {
    pcg_op(|x, y| a.matvec(x, y), b, tol, max_iters, prec)
}

/// [`pcg`] for an operator `op(x, y)`: `y = A x` (for benchmarks and tests).
pub fn pcg_op(
    op: impl Fn(&[f64], &mut [f64]),
    b: &[f64],
    tol: f64,
    max_iters: usize,
    prec: impl Fn(&[f64]) -> Vec<f64>,
) -> Option<(Vec<f64>, usize)> {
    let dot = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(a, b)| a * b).sum::<f64>();
    let n = b.len();
    let mut x = vec![0f64; n];
    let mut r = b.to_vec();
    let bn = dot(b, b).sqrt();
    let mut z = prec(&r);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut ap = vec![0f64; n];
    for it in 1..=max_iters {
        op(&p, &mut ap);
        let alpha = rz / dot(&p, &ap);
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * ap[i];
        }
        if dot(&r, &r).sqrt() <= tol * bn {
            return Some((x, it));
        }
        z = prec(&r);
        let rz1 = dot(&r, &z);
        let beta = rz1 / rz;
        rz = rz1;
        for i in 0..n {
            p[i] = z[i] + beta * p[i];
        }
    }
    None
}

/// Block-Jacobi preconditioner of `a` (for comparisons in the tests).
pub fn block_jacobi(a: &Bsr) -> impl Fn(&[f64]) -> Vec<f64> + '_ {
    let dinv = a.inverse_diagonal().expect("SPD diagonal blocks");
    let bs = a.bs;
    move |r: &[f64]| {
        let mut z = vec![0f64; r.len()];
        for i in 0..a.rows {
            let m = &dinv[i * bs * bs..(i + 1) * bs * bs];
            for q in 0..bs {
                z[i * bs + q] = (0..bs).map(|u| m[q * bs + u] * r[i * bs + u]).sum();
            }
        }
        z
    }
}

// ---------------------------------------------------------------------------
// SA with a general near-null space `B` (`k` columns; the 12 affine motions of
// the vertices): the tentative prolongator has `k` columns per aggregate (a QR
// of the aggregate's rows of `B`), so coarse levels have `k x k` blocks. `P`,
// `R` are scalar (bs = 1; the finest `P` is made of 3 x k blocks).

/// A matrix regrouped into `br` x `bc` blocks (row-major, zeros where nothing
/// is stored): the wide-block layout of the GPU V-cycle (`spmv_wide`).
#[derive(Debug, Clone, PartialEq)]
pub struct WideBlocks {
    pub br: usize,
    pub bc: usize,
    /// Block rows.
    pub rows: usize,
    pub row_ptr: Vec<u32>,
    pub col_idx: Vec<u32>,
    /// `br * bc` f64 per stored block.
    pub vals: Vec<f64>,
}

impl Bsr {
    /// This matrix (any `bs`) in `br` x `bc` blocks; its scalar rows and
    /// columns must divide into them.
    pub fn regroup(&self, br: usize, bc: usize) -> WideBlocks {
        let bs = self.bs;
        let (srows, scols) = (self.rows * bs, self.cols * bs);
        assert!(
            srows % br == 0 && scols % bc == 0,
            "{srows} x {scols} in {br} x {bc} blocks"
        );
        let bb = br * bc;
        let parts: Vec<(Vec<u32>, Vec<f64>)> = (0..srows / br)
            .into_par_iter()
            .map(|i| {
                let rows = i * br..(i + 1) * br;
                let mut cols: Vec<u32> = Vec::new();
                for r in rows.clone() {
                    for k in self.range(r / bs) {
                        let j = self.col_idx[k] as usize;
                        cols.extend((0..bs).map(|t| ((j * bs + t) / bc) as u32));
                    }
                }
                cols.sort_unstable();
                cols.dedup();
                let mut vals = vec![0f64; cols.len() * bb];
                for r in rows {
                    let q = r % bs;
                    for k in self.range(r / bs) {
                        let j = self.col_idx[k] as usize;
                        let m = self.block(k);
                        for t in 0..bs {
                            let c = j * bs + t;
                            let p = cols.binary_search(&((c / bc) as u32)).unwrap();
                            vals[p * bb + (r % br) * bc + c % bc] = m[q * bs + t];
                        }
                    }
                }
                (cols, vals)
            })
            .collect();
        let mut row_ptr = vec![0u32];
        let mut col_idx = Vec::new();
        let mut vals = Vec::new();
        for (c, v) in parts {
            col_idx.extend_from_slice(&c);
            vals.extend_from_slice(&v);
            row_ptr.push(col_idx.len() as u32);
        }
        WideBlocks {
            br,
            bc,
            rows: srows / br,
            row_ptr,
            col_idx,
            vals,
        }
    }
}

/// Tentative prolongator (scalar, `n bs` x `naggs k`) and coarse near-null space
/// (`naggs k` x `k`, row-major) by a modified Gram-Schmidt QR of each
/// aggregate's rows of `b` (`n bs` x `k`, row-major). Dependent columns give
/// zero columns of `P0` (their coarse unknowns are decoupled dummies).
fn tentative_nullspace(
    bs: usize,
    agg: &[u32],
    naggs: usize,
    b: &[f64],
    k: usize,
) -> (Bsr, Vec<f64>) {
    let n = agg.len();
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); naggs];
    for i in 0..n {
        if agg[i] != u32::MAX {
            members[agg[i] as usize].push(i);
        }
    }
    // Per aggregate: Q (rows = members * bs, k columns) and R (k x k).
    let qr: Vec<(Vec<f64>, Vec<f64>)> = members
        .par_iter()
        .map(|mem| {
            let m = mem.len() * bs;
            let mut q = vec![0f64; m * k];
            for (a, &i) in mem.iter().enumerate() {
                for s in 0..bs {
                    q[(a * bs + s) * k..(a * bs + s + 1) * k]
                        .copy_from_slice(&b[(i * bs + s) * k..(i * bs + s + 1) * k]);
                }
            }
            let mut r = vec![0f64; k * k];
            for j in 0..k {
                let n0: f64 = (0..m).map(|row| q[row * k + j].powi(2)).sum::<f64>().sqrt();
                for _pass in 0..2 {
                    for i in 0..j {
                        let d: f64 = (0..m).map(|row| q[row * k + i] * q[row * k + j]).sum();
                        r[i * k + j] += d;
                        for row in 0..m {
                            q[row * k + j] -= d * q[row * k + i];
                        }
                    }
                }
                let nj: f64 = (0..m).map(|row| q[row * k + j].powi(2)).sum::<f64>().sqrt();
                if n0 == 0.0 || nj < 1e-6 * n0 {
                    for row in 0..m {
                        q[row * k + j] = 0.0;
                    }
                } else {
                    r[j * k + j] = nj;
                    for row in 0..m {
                        q[row * k + j] /= nj;
                    }
                }
            }
            (q, r)
        })
        .collect();
    let mut pos = vec![0usize; n];
    for mem in &members {
        for (a, &i) in mem.iter().enumerate() {
            pos[i] = a;
        }
    }
    let mut parts = Vec::with_capacity(n * bs);
    for i in 0..n {
        for s in 0..bs {
            if agg[i] == u32::MAX {
                parts.push((Vec::new(), Vec::new()));
                continue;
            }
            let g = agg[i] as usize;
            let row = pos[i] * bs + s;
            let c: Vec<u32> = (0..k).map(|j| (g * k + j) as u32).collect();
            let v = qr[g].0[row * k..(row + 1) * k].to_vec();
            parts.push((c, v));
        }
    }
    let p0 = assemble(1, n * bs, naggs * k, parts);
    let mut bc = vec![0f64; naggs * k * k];
    for g in 0..naggs {
        bc[g * k * k..(g + 1) * k * k].copy_from_slice(&qr[g].1);
    }
    (p0, bc)
}

/// The `bs` scalar rows `i bs + q` of `A X` (`x` scalar, `a.cols bs` rows)
/// over one column set: `cols` (in order of appearance) and
/// `acc[slot bs + q]`. `mark` (one per column of `x`, `u32::MAX` when free)
/// holds each column's slot; the caller frees it after reading.
fn block_row_product(
    a: &Bsr,
    x: &Bsr,
    i: usize,
    mark: &mut [u32],
    cols: &mut Vec<u32>,
    acc: &mut Vec<f64>,
) {
    let bs = a.bs;
    cols.clear();
    acc.clear();
    for k in a.range(i) {
        let j = a.col_idx[k] as usize;
        let m = a.block(k);
        for t in 0..bs {
            for kk in x.range(j * bs + t) {
                let c = x.col_idx[kk] as usize;
                if mark[c] == u32::MAX {
                    mark[c] = cols.len() as u32;
                    cols.push(c as u32);
                    acc.resize(acc.len() + bs, 0.0);
                }
                let s = mark[c] as usize * bs;
                let v = x.vals[kk];
                for q in 0..bs {
                    acc[s + q] += m[q * bs + t] * v;
                }
            }
        }
    }
}

/// The `bs` scalar rows (sorted columns) of one block row from
/// [`block_row_product`]'s column set and `acc`; frees `mark`.
fn scalar_rows(
    bs: usize,
    mark: &mut [u32],
    cols: &[u32],
    acc: &[f64],
) -> Vec<(Vec<u32>, Vec<f64>)> {
    let mut order: Vec<usize> = (0..cols.len()).collect();
    order.sort_unstable_by_key(|&s| cols[s]);
    let sorted: Vec<u32> = order.iter().map(|&s| cols[s]).collect();
    for &c in cols {
        mark[c as usize] = u32::MAX;
    }
    (0..bs)
        .map(|q| {
            (
                sorted.clone(),
                order.iter().map(|&s| acc[s * bs + q]).collect(),
            )
        })
        .collect()
}

/// Smoothed prolongator `P = (I - omega D^-1 A) P0` of a scalar tentative `P0`
/// (`a.rows bs` rows), scalar; structural zeros kept, so the pattern depends
/// on the patterns of `a` and `P0` only.
fn smoothed_scalar_prolongator(a: &Bsr, dinv: &[f64], p0: &Bsr, omega: f64) -> Bsr {
    let bs = a.bs;
    let bb = bs * bs;
    let rows: Vec<Vec<(Vec<u32>, Vec<f64>)>> = (0..a.rows)
        .into_par_iter()
        .map_init(
            || (vec![u32::MAX; p0.cols], Vec::new(), Vec::new()),
            |(mark, cols, acc): &mut (Vec<u32>, Vec<u32>, Vec<f64>), i| {
                block_row_product(a, p0, i, mark, cols, acc);
                let m = &dinv[i * bb..(i + 1) * bb];
                let mut out = vec![0f64; acc.len()];
                for s in 0..cols.len() {
                    for q in 0..bs {
                        let d: f64 = (0..bs).map(|t| m[q * bs + t] * acc[s * bs + t]).sum();
                        out[s * bs + q] = -omega * d;
                    }
                }
                for q in 0..bs {
                    for kk in p0.range(i * bs + q) {
                        let c = p0.col_idx[kk] as usize;
                        if mark[c] == u32::MAX {
                            mark[c] = cols.len() as u32;
                            cols.push(c as u32);
                            out.resize(out.len() + bs, 0.0);
                        }
                        out[mark[c] as usize * bs + q] += p0.vals[kk];
                    }
                }
                scalar_rows(bs, mark, cols, &out)
            },
        )
        .collect();
    assemble(
        1,
        a.rows * bs,
        p0.cols,
        rows.into_iter().flatten().collect(),
    )
}

/// The coarse operator `R A P` (`p` scalar, `r = P^T`) in `k x k` blocks. A
/// coarse unknown whose column of `P` is zero (an aggregate too small for
/// all `k` modes) gets a unit diagonal: it is decoupled and never excited.
fn galerkin_blocks(a: &Bsr, p: &Bsr, r: &Bsr, k: usize) -> Bsr {
    let bs = a.bs;
    let ap_rows: Vec<Vec<(Vec<u32>, Vec<f64>)>> = (0..a.rows)
        .into_par_iter()
        .map_init(
            || (vec![u32::MAX; p.cols], Vec::new(), Vec::new()),
            |(mark, cols, acc): &mut (Vec<u32>, Vec<u32>, Vec<f64>), i| {
                block_row_product(a, p, i, mark, cols, acc);
                scalar_rows(bs, mark, cols, acc)
            },
        )
        .collect();
    let ap = assemble(
        1,
        a.rows * bs,
        p.cols,
        ap_rows.into_iter().flatten().collect(),
    );
    let nc = p.cols / k;
    let kk = k * k;
    let rows: Vec<(Vec<u32>, Vec<f64>)> = (0..nc)
        .into_par_iter()
        .map_init(
            || (vec![u32::MAX; nc], Vec::new(), Vec::new()),
            |(mark, cols, acc): &mut (Vec<u32>, Vec<u32>, Vec<f64>), g| {
                cols.clear();
                acc.clear();
                for q in 0..k {
                    for kr in r.range(g * k + q) {
                        let (m, rv) = (r.col_idx[kr] as usize, r.vals[kr]);
                        for ka in ap.range(m) {
                            let c = ap.col_idx[ka] as usize;
                            let cb = c / k;
                            if mark[cb] == u32::MAX {
                                mark[cb] = cols.len() as u32;
                                cols.push(cb as u32);
                                acc.resize(acc.len() + kk, 0.0);
                            }
                            acc[mark[cb] as usize * kk + q * k + c % k] += rv * ap.vals[ka];
                        }
                    }
                }
                let mut order: Vec<usize> = (0..cols.len()).collect();
                order.sort_unstable_by_key(|&s| cols[s]);
                let oc: Vec<u32> = order.iter().map(|&s| cols[s]).collect();
                let mut ov = Vec::with_capacity(acc.len());
                for &s in &order {
                    ov.extend_from_slice(&acc[s * kk..(s + 1) * kk]);
                }
                for &c in cols.iter() {
                    mark[c as usize] = u32::MAX;
                }
                let diag = oc.binary_search(&(g as u32)).ok();
                for q in 0..k {
                    let zero = (0..oc.len()).all(|b| (0..k).all(|t| ov[b * kk + q * k + t] == 0.0));
                    if let (true, Some(d)) = (zero, diag) {
                        ov[d * kk + q * k + q] = 1.0;
                    }
                }
                (oc, ov)
            },
        )
        .collect();
    assemble(k, nc, nc, rows)
}

/// The near-null space of the affine motions `x -> M x + t` of vertices at
/// `x` (block size 3): row-major `3 n` x [`AFFINE_MODES`], `r` taken from the
/// centroid. Held rows are harmless (they belong to no aggregate).
fn affine_modes(x: &[[f64; 3]]) -> Vec<f64> {
    const K: usize = AFFINE_MODES;
    let n = x.len().max(1) as f64;
    let mut c = [0.0; 3];
    for p in x {
        for d in 0..3 {
            c[d] += p[d] / n;
        }
    }
    let mut b = vec![0f64; 3 * x.len() * K];
    for (i, p) in x.iter().enumerate() {
        let r = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
        for a in 0..3 {
            let row = &mut b[(3 * i + a) * K..(3 * i + a + 1) * K];
            row[a] = 1.0;
            row[3 + 3 * a..6 + 3 * a].copy_from_slice(&r);
        }
    }
    b
}

// ---------------------------------------------------------------------------
// The squared-Laplacian preconditioner of shape systems: a scalar hierarchy of
// `B = S + eps Mt`, applied to x, y and z at once as `B (x) I3`.

/// Estimate of the smallest nonzero eigenvalue of `(S, Mt)` times `sum(Mt)`
/// behind the screening of [`squared_laplacian`] (a sphere's is 8 pi; measured
/// best on spot between 25 and 50, `benches/shape_preconditioner.rs`).
pub const SQUARED_LAPLACIAN_TAU: f64 = 50.0;

/// The screened Laplacian `B = S + eps Mt` of the squared-Laplacian
/// preconditioner `P = B^-1 Mt B^-1` of a shape matrix whose isotropic part is
/// close to `S Mt^-1 S + c S` ([`solver_cpu::ShapeOperatorModel`]): then
/// `P^-1 = S Mt^-1 S + 2 eps S + eps^2 Mt`, and in the eigenbasis of
/// `(S, Mt)` the ratio `(l^2 + c l) / (l + eps)^2` stays within a band that
/// does not depend on the mesh for `eps = max(sqrt(c lambda), lambda)`,
/// `lambda = tau / sum(Mt)` an estimate of the smallest nonzero eigenvalue.
/// Held vertices get identity rows and columns (Dirichlet rows: the pinned
/// squared Laplacian differs from the squared pinned one by rank one per held
/// vertex). Returns `B` (full symmetric, scalar) and `Mt` with 1 at held rows.
pub fn squared_laplacian(
    model: &solver_cpu::ShapeOperatorModel,
    fixed: &[bool],
    tau: f64,
) -> (Bsr, Vec<f64>) {
    let s = &model.laplacian;
    let n = s.len();
    let sum: f64 = model.mt.iter().sum();
    let lambda = if sum > 0.0 { tau / sum } else { 0.0 };
    let eps = (model.c.max(0.0) * lambda).sqrt().max(lambda);
    let held = |v: usize| fixed.get(v).copied().unwrap_or(true) || model.mt[v] <= 0.0;
    let mut mt = Vec::with_capacity(n);
    let rows = (0..n)
        .map(|i| {
            if held(i) {
                mt.push(1.0);
                return vec![(i as u32, 1.0)];
            }
            mt.push(model.mt[i]);
            s.row(i)
                .filter(|&(j, _)| j == i || !held(j))
                .map(|(j, v)| (j as u32, if j == i { v + eps * model.mt[i] } else { v }))
                .collect()
        })
        .collect();
    (Bsr::scalar_from_rows(rows), mt)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 2-D grid Laplacian (x) I_bs on nx x ny (5-point, plus one diagonal),
    /// weights varying smoothly, with weak random-ish 3x3 couplings, a small
    /// mass term, and every `held`-th node an identity row.
    pub(crate) fn grid(nx: usize, ny: usize, bs: usize, held: usize) -> Bsr {
        let n = nx * ny;
        let id = |i: usize, j: usize| j * nx + i;
        let mut nbrs: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
        for j in 0..ny {
            for i in 0..nx {
                let mut link = |a: usize, b: usize, w: f64| {
                    nbrs[a].push((b, w));
                    nbrs[b].push((a, w));
                };
                let w = 1.0 + 0.5 * ((i as f64 * 0.37).sin() * (j as f64 * 0.23).cos());
                if i + 1 < nx {
                    link(id(i, j), id(i + 1, j), w);
                }
                if j + 1 < ny {
                    // Anisotropic: the vertical couplings are weaker.
                    link(id(i, j), id(i, j + 1), 0.3 * w);
                }
                if i + 1 < nx && j + 1 < ny {
                    link(id(i, j), id(i + 1, j + 1), 0.02 * w);
                }
            }
        }
        let is_held = |v: usize| held > 0 && v % held == 7;
        let bb = bs * bs;
        let mut parts = Vec::new();
        for (v, nb) in nbrs.iter_mut().enumerate() {
            nb.sort_by_key(|e| e.0);
            let mut cols = Vec::new();
            let mut vals = Vec::new();
            let mut diag = 0.0;
            for &(_, w) in nb.iter() {
                diag += w;
            }
            let mut entries: Vec<(usize, Vec<f64>)> = Vec::new();
            for &(u, w) in nb.iter() {
                let mut b = vec![0f64; bb];
                for q in 0..bs {
                    b[q * bs + q] = -w;
                }
                if bs == 3 {
                    // Weak coupling between components: L (x) K, K SPD.
                    b[1] = -0.05 * w;
                    b[3] = -0.05 * w;
                }
                if is_held(v) || is_held(u) {
                    b.fill(0.0);
                }
                entries.push((u, b));
            }
            let mut d = vec![0f64; bb];
            for q in 0..bs {
                d[q * bs + q] = if is_held(v) { 1.0 } else { diag + 1e-3 };
            }
            if bs == 3 && !is_held(v) {
                d[1] = 0.05 * diag;
                d[3] = 0.05 * diag;
            }
            entries.push((v, d));
            entries.sort_by_key(|e| e.0);
            for (u, b) in entries {
                cols.push(u as u32);
                vals.extend(b);
            }
            parts.push((cols, vals));
        }
        assemble(bs, n, n, parts)
    }

    fn rhs(n: usize) -> Vec<f64> {
        (0..n)
            .map(|i| ((i as f64) * 0.731).sin() + 0.3 * ((i * i % 17) as f64 - 8.0) / 8.0)
            .collect()
    }

    #[test]
    fn transpose_and_product_match_dense() {
        let a = grid(7, 5, 3, 11);
        let (agg, naggs) = aggregate(&a, 0.08);
        let dinv = a.inverse_diagonal().unwrap();
        let p = smoothed_prolongator(&a, &dinv, &agg, naggs, 0.5);
        let r = p.transpose();
        let ac = r.mul(&a.mul(&p));
        let n = a.rows * 3;
        let nc = naggs * 3;
        let x: Vec<f64> = rhs(nc);
        // Ac x == R (A (P x))
        let mut px = vec![0.0; n];
        p.matvec(&x, &mut px);
        let mut apx = vec![0.0; n];
        a.matvec(&px, &mut apx);
        let mut want = vec![0.0; nc];
        r.matvec(&apx, &mut want);
        let mut got = vec![0.0; nc];
        ac.matvec(&x, &mut got);
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-12 * (1.0 + w.abs()), "{g} vs {w}");
        }
        // R == P^T entrywise: x . (P y) == (R x) . y
        let y = rhs(n);
        let mut ry = vec![0.0; nc];
        r.matvec(&y, &mut ry);
        let lhs: f64 = y.iter().zip(&px).map(|(a, b)| a * b).sum();
        let rhs_: f64 = ry.iter().zip(&x).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs_).abs() < 1e-10 * lhs.abs().max(1.0));
    }

    #[test]
    fn aggregation_covers_connected_rows_and_skips_held_ones() {
        let a = grid(30, 20, 1, 13);
        let (agg, naggs) = aggregate(&a, 0.08);
        assert!(naggs > 0 && naggs < a.rows / 3, "{naggs} aggregates");
        for (v, &g) in agg.iter().enumerate() {
            if v % 13 == 7 {
                assert_eq!(g, u32::MAX);
            } else {
                assert!((g as usize) < naggs);
            }
        }
    }

    #[test]
    fn dense_inverse() {
        let a = grid(6, 5, 3, 0);
        let n = a.rows * 3;
        let d = a.dense_symmetric();
        let inv = dense_spd_inverse(&d, n).unwrap();
        for r in 0..n {
            for c in 0..n {
                let s: f64 = (0..n).map(|k| d[r * n + k] * inv[k * n + c]).sum();
                assert!((s - if r == c { 1.0 } else { 0.0 }).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn vcycle_is_symmetric() {
        let a = grid(40, 30, 3, 17);
        let h = Hierarchy::build(
            a,
            &AmgOptions {
                max_coarse: 60,
                ..Default::default()
            },
            None,
        )
        .unwrap();
        assert!(h.levels.len() >= 2, "{:?}", h.sizes());
        let n = h.n();
        let u = rhs(n);
        let v: Vec<f64> = (0..n).map(|i| ((i as f64) * 1.3).cos()).collect();
        let (mu, mv) = (h.vcycle(&u), h.vcycle(&v));
        let a1: f64 = v.iter().zip(&mu).map(|(a, b)| a * b).sum();
        let a2: f64 = u.iter().zip(&mv).map(|(a, b)| a * b).sum();
        assert!((a1 - a2).abs() < 1e-10 * a1.abs(), "{a1} vs {a2}");
        let pos: f64 = u.iter().zip(&mu).map(|(a, b)| a * b).sum();
        assert!(pos > 0.0);
    }

    /// Positions of `grid`'s nodes on a gently curved sheet.
    fn grid_positions(nx: usize, ny: usize) -> Vec<[f64; 3]> {
        (0..nx * ny)
            .map(|v| {
                let (x, y) = ((v % nx) as f64, (v / nx) as f64);
                [x, y, 0.02 * (x * x + y * y)]
            })
            .collect()
    }

    #[test]
    fn affine_vcycle_is_symmetric_with_wide_coarse_blocks() {
        let (nx, ny) = (40, 30);
        let opts = AmgOptions {
            max_coarse: 300,
            ..Default::default()
        };
        let h = Hierarchy::build_affine(grid(nx, ny, 3, 17), &opts, &grid_positions(nx, ny), None)
            .unwrap();
        assert!(h.affine && h.levels.len() >= 2, "{:?}", h.sizes());
        assert_eq!(h.levels[1].a.bs, AFFINE_MODES);
        assert_eq!(h.levels[0].p.cols, h.levels[1].a.rows * AFFINE_MODES);
        let n = h.n();
        let u = rhs(n);
        let v: Vec<f64> = (0..n).map(|i| ((i as f64) * 1.3).cos()).collect();
        let (mu, mv) = (h.vcycle(&u), h.vcycle(&v));
        let a1: f64 = v.iter().zip(&mu).map(|(a, b)| a * b).sum();
        let a2: f64 = u.iter().zip(&mv).map(|(a, b)| a * b).sum();
        assert!((a1 - a2).abs() < 1e-10 * a1.abs(), "{a1} vs {a2}");
        assert!(u.iter().zip(&mu).map(|(a, b)| a * b).sum::<f64>() > 0.0);
        // A rebuild with new values keeps every pattern and the tentative P.
        let mut a2 = grid(nx, ny, 3, 17);
        a2.vals.iter_mut().for_each(|v| *v *= 2.0);
        let h2 = Hierarchy::build_affine(a2, &opts, &[], Some(&h));
        assert!(h2.is_err(), "positions are checked even when reused");
        let mut a2 = grid(nx, ny, 3, 17);
        a2.vals.iter_mut().for_each(|v| *v *= 2.0);
        let h2 = Hierarchy::build_affine(a2, &opts, &grid_positions(nx, ny), Some(&h)).unwrap();
        for (x, y) in h.levels.iter().zip(&h2.levels) {
            assert!(x.a.same_pattern(&y.a) && x.p.same_pattern(&y.p));
            assert_eq!(x.tentative, y.tentative);
        }
        // Twice the matrix: half the preconditioned vector.
        let mu2 = h2.vcycle(&u);
        for (a, b) in mu.iter().zip(&mu2) {
            assert!(
                (a - 2.0 * b).abs() <= 1e-9 * (1.0 + a.abs()),
                "{a} vs 2 x {b}"
            );
        }
    }

    #[test]
    fn tentative_prolongator_interpolates_the_affine_motions() {
        let (nx, ny) = (20, 15);
        let a = grid(nx, ny, 3, 11);
        let (agg, naggs) = aggregate(&a, 0.08);
        let b = affine_modes(&grid_positions(nx, ny));
        let k = AFFINE_MODES;
        let (p0, bc) = tentative_nullspace(3, &agg, naggs, &b, k);
        assert_eq!((p0.rows, p0.cols), (3 * a.rows, k * naggs));
        // P0 Bc = B on every aggregated row, column by column.
        for j in 0..k {
            let col: Vec<f64> = (0..naggs * k).map(|r| bc[r * k + j]).collect();
            let mut y = vec![0f64; p0.rows];
            p0.matvec(&col, &mut y);
            for (r, yr) in y.iter().enumerate() {
                let want = if agg[r / 3] == u32::MAX {
                    0.0
                } else {
                    b[r * k + j]
                };
                assert!(
                    (yr - want).abs() < 1e-9 * (1.0 + want.abs()),
                    "mode {j} row {r}: {yr} vs {want}"
                );
            }
        }
    }

    #[test]
    fn regrouped_blocks_hold_every_entry() {
        let g = grid(9, 8, 3, 5);
        let w = g.regroup(1, 1);
        let a = Bsr {
            bs: 1,
            rows: w.rows,
            cols: 3 * g.cols,
            row_ptr: w.row_ptr,
            col_idx: w.col_idx,
            vals: w.vals,
        };
        for (br, bc) in [(3, 12), (12, 3), (12, 12), (4, 4)] {
            let (rows, cols) = (a.rows - a.rows % br, a.cols - a.cols % bc);
            // Trim to a multiple of the block shape.
            let parts = (0..rows)
                .map(|i| {
                    let ks = a.range(i).filter(|&k| (a.col_idx[k] as usize) < cols);
                    let ks: Vec<usize> = ks.collect();
                    (
                        ks.iter().map(|&k| a.col_idx[k]).collect(),
                        ks.iter().map(|&k| a.vals[k]).collect(),
                    )
                })
                .collect();
            let t = assemble(1, rows, cols, parts);
            let w = t.regroup(br, bc);
            let mut dense = vec![0f64; rows * cols];
            for i in 0..w.rows {
                for k in w.row_ptr[i] as usize..w.row_ptr[i + 1] as usize {
                    let j = w.col_idx[k] as usize;
                    for q in 0..br {
                        for u in 0..bc {
                            dense[(i * br + q) * cols + j * bc + u] +=
                                w.vals[k * br * bc + q * bc + u];
                        }
                    }
                }
            }
            let mut want = vec![0f64; rows * cols];
            for i in 0..rows {
                for k in t.range(i) {
                    want[i * cols + t.col_idx[k] as usize] = t.vals[k];
                }
            }
            assert_eq!(dense, want, "{br} x {bc}");
        }
    }

    #[test]
    fn amg_pcg_needs_far_fewer_iterations_than_block_jacobi() {
        for bs in [3, 1] {
            let a = grid(120, 100, bs, 97);
            let b = rhs(a.rows * bs);
            let t = std::time::Instant::now();
            let h = Hierarchy::build(a.clone(), &AmgOptions::default(), None).unwrap();
            let setup = t.elapsed();
            let (xa, ia) = pcg(&a, &b, 1e-8, 2000, |r| h.vcycle(r)).unwrap();
            let (xj, ij) = pcg(&a, &b, 1e-8, 5000, block_jacobi(&a)).unwrap();
            eprintln!(
                "bs {bs}: {} unknowns, levels {:?}, complexity {:.2}, setup {setup:?}: \
                 AMG {ia} iterations, block Jacobi {ij}",
                a.rows * bs,
                h.sizes(),
                h.operator_complexity()
            );
            let e: f64 = xa
                .iter()
                .zip(&xj)
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f64>()
                .sqrt()
                / xj.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!(e < 1e-6, "{e}");
            assert!(ia * 5 < ij, "AMG {ia} vs Jacobi {ij}");
            // Same pattern: the aggregates are reused and the patterns repeat.
            let h2 = Hierarchy::build(a.clone(), &AmgOptions::default(), Some(&h)).unwrap();
            assert_eq!(h2.sizes(), h.sizes());
            for (l1, l2) in h.levels.iter().zip(&h2.levels) {
                assert!(l1.p.same_pattern(&l2.p) && l1.a.same_pattern(&l2.a));
            }
        }
    }

    /// `B = S + eps Mt` with held rows and columns identity, symmetric, and
    /// `Mt` 1 on held rows.
    #[test]
    fn squared_laplacian_screens_and_holds() {
        use solver_cpu::{ShapeOperatorModel, SparseRows};
        // A path 0-1-2-3 with unit weights; vertex 3 outside every face.
        let t = vec![
            (0, 1, 1.0),
            (1, 0, 1.0),
            (1, 2, 1.0),
            (2, 1, 1.0),
            (2, 3, 1.0),
            (3, 2, 1.0),
        ];
        let s = SparseRows::from_triplets(4, t, false);
        let model = ShapeOperatorModel {
            laplacian: std::sync::Arc::new(s),
            mt: vec![2.0, 1.0, 1.0, 0.0],
            c: 8.0,
        };
        let fixed = [true, false, false, false];
        let (b, mt) = squared_laplacian(&model, &fixed, 4.0);
        // lambda = 4 / 4 = 1, eps = max(sqrt(8), 1).
        let eps = 8f64.sqrt();
        let dense = |i: usize, j: usize| -> f64 {
            (b.row_ptr[i] as usize..b.row_ptr[i + 1] as usize)
                .find(|&k| b.col_idx[k] as usize == j)
                .map_or(0.0, |k| b.vals[k])
        };
        assert_eq!(dense(0, 0), 1.0);
        assert_eq!(dense(3, 3), 1.0);
        assert_eq!((dense(0, 1), dense(1, 0), dense(2, 3)), (0.0, 0.0, 0.0));
        assert!((dense(1, 1) - (2.0 + eps)).abs() < 1e-12);
        assert_eq!((dense(1, 2), dense(2, 1)), (-1.0, -1.0));
        assert_eq!(mt, vec![1.0, 1.0, 1.0, 1.0]);
    }
}
