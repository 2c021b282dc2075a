//! Shape matrices in isotropic-plus-ring form: `A = K (x) I3 + sum_i R_i^T C_i R_i`.
//!
//! Every term of the shape energy but one has an isotropic Hessian
//! `(c c^T) (x) I3` (the frame, curvature and handle terms, paper Eqs. 4, 5 and
//! 19). The exception, the direction term of Eq. 6, is a sum over vertices of
//! `R_i^T C_i R_i`, with `R_i` the vertex's Laplacian row (its 1-ring) acting on
//! x, y and z alike and `C_i` a symmetric 3x3 matrix. [`IsoRingSym3`] stores the
//! scalar `K` (one value per 2-ring vertex pair) and the six entries of each
//! `C_i`, instead of the nine of every 3x3 block of `A`: about a seventh of the
//! memory. A product is one scalar product with `K` on three interleaved columns
//! and two passes over the rings.
//!
//! When every `C_i` is traceless (as the shape model builds them), `K` is the
//! isotropic part of `A` (`K_pq = tr(A_pq) / 3`), which is what the PCG of
//! [`crate::BlockPcgSolver`] factors as its preconditioner; it then needs no copy.
//! A backend that reads `K` apart no longer (its preconditioner of the kind
//! is made: [`crate::SpdSolver::wants_isotropic_part`]) gets the whole
//! direction term in the `C_i`: the same `A`, a different split.
//!
//! One more term may be named instead of stored: E_m's Hessian
//! `S Mt^-1 S (x) I3` ([`IsoRingSym3::laplacian_square`], `S` the input's
//! cotangent Laplacian). It is constant for a run, so a backend that keeps
//! its values itself ([`crate::SpdSolver::adds_laplacian_square`]) gets
//! matrices whose `K` goes without it; the products here add it from `S`.

use crate::{BlockRows, BlockSym3, ShapeOperatorModel, SolverError, SymCsc};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::Arc;

/// A placeholder among [`SparseRows::from_triplets`]' triplets, left out:
/// where a builder that makes a fixed number per face has fewer.
pub const NO_TRIPLET: (u32, u32, f64) = (u32::MAX, u32::MAX, 0.0);

/// Rows a task of [`SparseRows::from_triplets`] compresses at once.
const TRIPLET_ROWS: usize = 4096;

/// The distinct pairs of sorted triplets, each with its duplicates' sum,
/// `((v0 + v1) + v2) ...` in their order.
fn distinct(entries: &[(u32, u32, f64)]) -> impl Iterator<Item = (u32, u32, f64)> + '_ {
    entries
        .chunk_by(|a, b| (a.0, a.1) == (b.0, b.1))
        .map(|run| {
            (
                run[0].0,
                run[0].1,
                run[1..].iter().fold(run[0].2, |s, e| s + e.2),
            )
        })
}

/// Sparse rows in a graph Laplacian's layout:
/// `(R y)_i = diag_i y_i - sum_k w_k y_{idx_k}` over `k` in `start[i]..start[i + 1]`
/// (column indices sorted within a row, the diagonal kept apart).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SparseRows {
    pub start: Vec<usize>,
    pub idx: Vec<u32>,
    pub w: Vec<f64>,
    pub diag: Vec<f64>,
}

/// A row's diagonal from its summed weights `w`: their sum; with
/// `normalise`, 1 after the weights are scaled to sum 1 (0 for a row whose
/// sum is not positive, left as it is).
fn finish_row(w: &mut [f64], normalise: bool) -> f64 {
    let sum: f64 = w.iter().sum();
    if !normalise {
        sum
    } else if sum > 0.0 {
        w.iter_mut().for_each(|v| *v /= sum);
        1.0
    } else {
        0.0
    }
}

impl SparseRows {
    /// Rows from `(row, column, weight)` triplets (duplicates summed, the diagonal
    /// given by `diag`). With `normalise`, each row's weights are scaled to sum 1
    /// and its diagonal is 1 (0 for an empty row); otherwise the diagonal is the
    /// row's weight sum (a Laplacian: rows sum to zero).
    /// Triplets whose row is `n` or more (such as a builder's placeholder
    /// [`NO_TRIPLET`]) are left out.
    pub fn from_triplets(n: usize, mut t: Vec<(u32, u32, f64)>, normalise: bool) -> SparseRows {
        // On rayon's threads; the values in the key make the order of a
        // pair's duplicates, and so their sum, the same on every run.
        use rayon::slice::ParallelSliceMut;
        t.par_sort_unstable_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)).then(a.2.total_cmp(&b.2)));
        // The sorted triplets cut at row starts, a group of rows each: each
        // group's distinct pairs counted, then summed into their places, on
        // rayon's threads, each pair's duplicates in the sorted order (the
        // same sums as one pass over them all).
        let at: Vec<usize> = (0..n.div_ceil(TRIPLET_ROWS) + 1)
            .map(|g| {
                let r = (g * TRIPLET_ROWS).min(n);
                t.partition_point(|e| (e.0 as usize) < r)
            })
            .collect();
        let groups: Vec<_> = at
            .windows(2)
            .enumerate()
            .map(|(g, w)| {
                let rows = g * TRIPLET_ROWS..((g + 1) * TRIPLET_ROWS).min(n);
                (rows, &t[w[0]..w[1]])
            })
            .collect();
        let mut start = vec![0usize; n + 1];
        start[1..]
            .par_chunks_mut(TRIPLET_ROWS)
            .zip(&groups)
            .for_each(|(counts, (rows, entries))| {
                for (i, _, _) in distinct(entries) {
                    counts[i as usize - rows.start] += 1;
                }
            });
        for i in 0..n {
            start[i + 1] += start[i];
        }
        let mut idx = vec![0u32; start[n]];
        let mut w = vec![0.0f64; start[n]];
        let mut diag = vec![0.0; n];
        let idx_groups = crate::row_groups_mut(&mut idx, n, |i| start[i], TRIPLET_ROWS);
        let w_groups = crate::row_groups_mut(&mut w, n, |i| start[i], TRIPLET_ROWS);
        idx_groups
            .into_par_iter()
            .zip(w_groups)
            .zip(diag.par_chunks_mut(TRIPLET_ROWS))
            .zip(&groups)
            .for_each(|((((rows, idx), (_, w)), diag), (_, entries))| {
                for (k, (_, j, v)) in distinct(entries).enumerate() {
                    idx[k] = j;
                    w[k] = v;
                }
                let base = start[rows.start];
                for (i, d) in rows.zip(diag) {
                    *d = finish_row(&mut w[start[i] - base..start[i + 1] - base], normalise);
                }
            });
        SparseRows {
            start,
            idx,
            w,
            diag,
        }
    }

    /// The rows [`SparseRows::from_triplets`] makes of the triplets `(i,
    /// column, weight)` that `row(i, out)` pushes as `(column, weight)` onto
    /// `out` (empty on the call), row by row, groups of rows on rayon's
    /// threads: the same bits, without one sort of all rows' triplets
    /// (each row's few are sorted apart, by column, then value: the order
    /// their duplicates are summed in there).
    pub fn from_rows(
        n: usize,
        row: impl Fn(usize, &mut Vec<(u32, f64)>) + Sync,
        normalise: bool,
    ) -> SparseRows {
        use rayon::prelude::*;
        // Each group's rows: their lengths, columns, weights and diagonals.
        type Group = (Vec<usize>, Vec<u32>, Vec<f64>, Vec<f64>);
        let groups: Vec<Group> = (0..n.div_ceil(TRIPLET_ROWS))
            .into_par_iter()
            .map(|g| {
                let rows = g * TRIPLET_ROWS..((g + 1) * TRIPLET_ROWS).min(n);
                let (mut lens, mut idx, mut w, mut diag) = (
                    Vec::with_capacity(rows.len()),
                    Vec::new(),
                    Vec::new(),
                    Vec::with_capacity(rows.len()),
                );
                let mut entries = Vec::new();
                for i in rows {
                    entries.clear();
                    row(i, &mut entries);
                    entries.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
                    let first = w.len();
                    for run in entries.chunk_by(|a, b| a.0 == b.0) {
                        idx.push(run[0].0);
                        w.push(run[1..].iter().fold(run[0].1, |s, e| s + e.1));
                    }
                    diag.push(finish_row(&mut w[first..], normalise));
                    lens.push(w.len() - first);
                }
                (lens, idx, w, diag)
            })
            .collect();
        let mut start = Vec::with_capacity(n + 1);
        start.push(0);
        for len in groups.iter().flat_map(|g| &g.0) {
            start.push(start.last().unwrap() + len);
        }
        let mut idx = vec![0u32; start[n]];
        let mut w = vec![0.0f64; start[n]];
        let mut diag = vec![0.0; n];
        crate::row_groups_mut(&mut idx, n, |i| start[i], TRIPLET_ROWS)
            .into_par_iter()
            .zip(crate::row_groups_mut(&mut w, n, |i| start[i], TRIPLET_ROWS))
            .zip(diag.par_chunks_mut(TRIPLET_ROWS))
            .zip(&groups)
            .for_each(|((((_, idx), (_, w)), diag), group)| {
                idx.copy_from_slice(&group.1);
                w.copy_from_slice(&group.2);
                diag.copy_from_slice(&group.3);
            });
        SparseRows {
            start,
            idx,
            w,
            diag,
        }
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.diag.len()
    }

    pub fn is_empty(&self) -> bool {
        self.diag.is_empty()
    }

    /// Row `i` as (column, coefficient), the diagonal first.
    #[inline]
    pub fn row(&self, i: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        std::iter::once((i, self.diag[i])).chain(
            (self.start[i]..self.start[i + 1]).map(move |k| (self.idx[k] as usize, -self.w[k])),
        )
    }

    /// The pairs `(p, q)` of row `i`'s entries with `p >= q`, each with its
    /// weight `R_ip R_iq`: the `(p, q)` blocks `R_i^T C_i R_i` adds to, in
    /// the order every sum of those blocks uses (row order twice nested).
    #[inline]
    pub fn pairs(&self, i: usize) -> impl Iterator<Item = (usize, usize, f64)> + '_ {
        self.row(i).flat_map(move |(p, wp)| {
            self.row(i)
                .filter(move |&(q, _)| p >= q)
                .map(move |(q, wq)| (p, q, wp * wq))
        })
    }

    /// The positions `(a, b)` in row `i` ([`Self::row`]'s order, the
    /// diagonal at 0) of the entries of each pair [`Self::pairs`] gives, in
    /// its order: what a pair is named by where its weight `R_ip R_iq` is
    /// formed from the row's weights later (the GPU's shape sum).
    #[inline]
    pub fn pair_positions(&self, i: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        let row = move || self.row(i).map(|(p, _)| p).enumerate();
        row().flat_map(move |(a, p)| {
            row()
                .filter(move |&(_, q)| p >= q)
                .map(move |(b, _)| (a, b))
        })
    }

    /// Coefficient `R_ij` (0 when `j` is not in row `i`).
    #[inline]
    pub fn coefficient(&self, i: usize, j: usize) -> f64 {
        if i == j {
            return self.diag[i];
        }
        let r = &self.idx[self.start[i]..self.start[i + 1]];
        match r.binary_search(&(j as u32)) {
            Ok(k) => -self.w[self.start[i] + k],
            Err(_) => 0.0,
        }
    }

    /// `(R x)_i`: the diagonal term, then the others in column order (the
    /// sum [`Self::row`] gives, read from the slices).
    #[inline]
    pub fn apply(&self, x: &[DVec3], i: usize) -> DVec3 {
        let r = self.start[i]..self.start[i + 1];
        let mut acc = DVec3::ZERO + self.diag[i] * x[i];
        for (&j, &w) in self.idx[r.clone()].iter().zip(&self.w[r]) {
            acc += -w * x[j as usize];
        }
        acc
    }

    /// [`Self::apply`] on a flat `x` (`3 j + c` for vertex `j`'s coordinate `c`).
    #[inline]
    pub fn apply_flat(&self, x: &[f64], i: usize) -> [f64; 3] {
        let r = self.start[i]..self.start[i + 1];
        let d = self.diag[i];
        let mut acc = [d * x[3 * i], d * x[3 * i + 1], d * x[3 * i + 2]];
        for (&j, &w) in self.idx[r.clone()].iter().zip(&self.w[r]) {
            let j = 3 * j as usize;
            acc[0] += -w * x[j];
            acc[1] += -w * x[j + 1];
            acc[2] += -w * x[j + 2];
        }
        acc
    }

    pub fn apply_all(&self, x: &[DVec3]) -> Vec<DVec3> {
        (0..self.len())
            .into_par_iter()
            .map(|i| self.apply(x, i))
            .collect()
    }

    /// Whether `j` is in row `i` exactly when `i` is in row `j` (as for the
    /// Laplacian of a mesh): then `R^T` can be gathered row by row.
    pub fn pattern_is_symmetric(&self) -> bool {
        (0..self.len()).into_par_iter().all(|i| {
            self.idx[self.start[i]..self.start[i + 1]].iter().all(|&j| {
                let j = j as usize;
                j < self.len()
                    && self.idx[self.start[j]..self.start[j + 1]]
                        .binary_search(&(i as u32))
                        .is_ok()
            })
        })
    }
}

/// Vertices per run of [`IsoRingSym3::quadratic_form`]'s sum: each run is
/// one task, its sum added to the others' in order.
pub const QUADRATIC_FORM_RUN: usize = 4096;

/// The symmetric 3x3 `C` stored as (xx, yy, zz, xy, xz, yz), as a row-major
/// 3x3 block.
#[inline]
pub fn sym3_block(c: &[f64; 6]) -> [f64; 9] {
    [c[0], c[3], c[4], c[3], c[1], c[5], c[4], c[5], c[2]]
}

/// `C x` for a symmetric 3x3 `C` stored as (xx, yy, zz, xy, xz, yz).
#[inline]
fn sym3_mul(c: &[f64; 6], x: [f64; 3]) -> [f64; 3] {
    [
        c[0] * x[0] + c[3] * x[1] + c[4] * x[2],
        c[3] * x[0] + c[1] * x[1] + c[5] * x[2],
        c[4] * x[0] + c[5] * x[1] + c[2] * x[2],
    ]
}

/// A symmetric `3n x 3n` matrix `K (x) I3 + sum_i R_i^T C_i R_i`, plus
/// `S Mt^-1 S (x) I3` where [`Self::laplacian_square`] names it (see module
/// docs).
#[derive(Debug, Clone, Default)]
pub struct IsoRingSym3 {
    /// `K`: lower-triangular CSC on the vertex pattern, diagonal first in each column.
    pub iso: SymCsc,
    /// The rows `R_i`; their pairs `(p, q)` must lie in the pattern of `iso`.
    pub rings: Arc<SparseRows>,
    /// `C_i` as (xx, yy, zz, xy, xz, yz), one per row of `rings`.
    pub ring_c: Vec<[f64; 6]>,
    /// When the rings' pattern is symmetric: `R_ip` for the `k`-th off-diagonal
    /// entry `i = idx[k]` of row `p` (the transpose's weights in `rings`' layout),
    /// for a gather-only parallel `R^T t`. Empty otherwise (sequential scatter).
    ring_t: Vec<f64>,
    /// E_m's Hessian `S Mt^-1 S (x) I3` of this model, when it is part of
    /// the matrix but not of `K` (`None`: `K` holds every isotropic term).
    /// Its pairs `(p, q)` must lie in the pattern of `iso`.
    pub laplacian_square: Option<Arc<ShapeOperatorModel>>,
    /// The slot in `iso`'s pattern of each pair of each row of `rings`, in
    /// the order of [`SparseRows::pairs`], row after row, where the matrix's
    /// maker has them (the shape model keeps them for its own assembly): a
    /// solver that adds the rings' pairs into the pattern may take them,
    /// checked, instead of searching for each (homer 1.2M: 16.8M pairs,
    /// 67 MB). `None` from [`Self::new`].
    pub ring_slots: Option<Arc<[u32]>>,
}

impl IsoRingSym3 {
    /// Zero matrix on the lower pattern `(col_ptr, row_idx)` (diagonal first in
    /// every column) with the rows `rings`.
    pub fn new(n: usize, col_ptr: Vec<usize>, row_idx: Vec<usize>, rings: Arc<SparseRows>) -> Self {
        assert_eq!(rings.len(), n, "one ring per vertex");
        let nnz = row_idx.len();
        let ring_t = if rings.pattern_is_symmetric() {
            (0..rings.len())
                .into_par_iter()
                .flat_map_iter(|p| {
                    let rings = &rings;
                    (rings.start[p]..rings.start[p + 1])
                        .map(move |k| rings.coefficient(rings.idx[k] as usize, p))
                })
                .collect()
        } else {
            Vec::new()
        };
        IsoRingSym3 {
            iso: SymCsc {
                n,
                col_ptr,
                row_idx,
                values: vec![0.0; nnz],
            },
            ring_c: vec![[0.0; 6]; n],
            rings,
            ring_t,
            laplacian_square: None,
            ring_slots: None,
        }
    }

    /// `K` with the held rows and columns made identity (`fixed` per vertex):
    /// the matrix whose factor preconditions a system with held vertices
    /// (`K` alone: without [`Self::laplacian_square`]).
    pub fn iso_held_identity(&self, fixed: &[bool]) -> SymCsc {
        let mut k = self.iso.clone();
        k.set_held_identity(fixed);
        k
    }

    /// Block rows (vertices).
    pub fn n(&self) -> usize {
        self.iso.n
    }

    pub fn clear(&mut self) {
        self.iso.values.iter_mut().for_each(|v| *v = 0.0);
        self.ring_c.iter_mut().for_each(|c| *c = [0.0; 6]);
        self.laplacian_square = None;
    }

    /// Slot of the diagonal entry of vertex `v` in `iso.values`.
    #[inline]
    pub fn diagonal_slot(&self, v: usize) -> usize {
        self.iso.col_ptr[v]
    }

    /// Row-wise index of the strictly lower entries of `K` (as [`BlockSym3::row_index`]).
    pub fn row_index(&self) -> BlockRows {
        BlockRows::of_pattern(self.iso.n, &self.iso.col_ptr, &self.iso.row_idx)
    }

    /// `t_i = C_i (R_i x)` for every ring.
    fn ring_terms(&self, x: &[f64]) -> Vec<[f64; 3]> {
        (0..self.n())
            .into_par_iter()
            .map(|i| {
                let c = &self.ring_c[i];
                if *c == [0.0; 6] {
                    return [0.0; 3];
                }
                let mut r = [0.0; 3];
                for (q, w) in self.rings.row(i) {
                    r[0] += w * x[3 * q];
                    r[1] += w * x[3 * q + 1];
                    r[2] += w * x[3 * q + 2];
                }
                sym3_mul(c, r)
            })
            .collect()
    }

    /// `y = A x`, parallel over vertices; `rows` is this pattern's [`Self::row_index`].
    pub fn mul_vec_rows(&self, rows: &BlockRows, x: &[f64], y: &mut [f64]) {
        let (col_ptr, row_idx, k) = (&self.iso.col_ptr, &self.iso.row_idx, &self.iso.values);
        y.par_chunks_mut(3).enumerate().for_each(|(v, out)| {
            let mut acc = [0.0f64; 3];
            for s in col_ptr[v]..col_ptr[v + 1] {
                let i = row_idx[s];
                for c in 0..3 {
                    acc[c] += k[s] * x[3 * i + c];
                }
            }
            for &(s, j) in &rows.entries[rows.row_ptr[v]..rows.row_ptr[v + 1]] {
                let (kv, j) = (k[s as usize], j as usize);
                for c in 0..3 {
                    acc[c] += kv * x[3 * j + c];
                }
            }
            out.copy_from_slice(&acc);
        });
        let t = self.ring_terms(x);
        if !self.ring_t.is_empty() || self.rings.idx.is_empty() {
            // (R^T t)_p = sum over the rings i containing p, i.e. over row p's own
            // columns (symmetric pattern), of R_ip t_i.
            let r = &*self.rings;
            y.par_chunks_mut(3).enumerate().for_each(|(p, out)| {
                let d = r.diag[p];
                for c in 0..3 {
                    out[c] += d * t[p][c];
                }
                for k in r.start[p]..r.start[p + 1] {
                    let (i, w) = (r.idx[k] as usize, self.ring_t[k]);
                    for c in 0..3 {
                        out[c] += w * t[i][c];
                    }
                }
            });
        } else {
            self.scatter_rings(&t, y);
        }
        self.add_laplacian_square(x, y);
    }

    /// `y += S^T diag(m) S x` on x, y and z alike, for the term
    /// [`Self::laplacian_square`] names (`m_i = 1 / Mt_i`); nothing without it.
    fn add_laplacian_square(&self, x: &[f64], y: &mut [f64]) {
        let Some(model) = &self.laplacian_square else {
            return;
        };
        let s = &*model.laplacian;
        let t: Vec<[f64; 3]> = (0..s.len())
            .into_par_iter()
            .map(|i| {
                let m = model.square_weight(i);
                if m == 0.0 {
                    return [0.0; 3];
                }
                let mut r = [0.0; 3];
                for (q, w) in s.row(i) {
                    for c in 0..3 {
                        r[c] += w * x[3 * q + c];
                    }
                }
                r.map(|v| m * v)
            })
            .collect();
        for (i, ti) in t.iter().enumerate() {
            if *ti == [0.0; 3] {
                continue;
            }
            for (p, w) in s.row(i) {
                for c in 0..3 {
                    y[3 * p + c] += w * ti[c];
                }
            }
        }
    }

    fn scatter_rings(&self, t: &[[f64; 3]], y: &mut [f64]) {
        for (i, ti) in t.iter().enumerate() {
            if *ti == [0.0; 3] {
                continue;
            }
            for (p, w) in self.rings.row(i) {
                for c in 0..3 {
                    y[3 * p + c] += w * ti[c];
                }
            }
        }
    }

    /// `x^T A x`, on rayon's threads and without a product vector: `K`'s
    /// lower entries (`k_s x_i . x_j`, twice off the diagonal), each ring's
    /// `(R_i x)^T C_i (R_i x)` and each row's `m_i |S_i x|^2` of a named
    /// Laplacian square. The vertices are summed in fixed runs of
    /// [`QUADRATIC_FORM_RUN`], the runs one after the other, so the value is
    /// the same on any number of threads. The fine-tune's merit reads it at
    /// every trial step (Eq. 8's energy): the sequential product and dot
    /// took 0.04-0.06 s each at homer 1.2M on the development machine.
    pub fn quadratic_form(&self, x: &[f64]) -> f64 {
        let n = self.n();
        let (col_ptr, row_idx, k) = (&self.iso.col_ptr, &self.iso.row_idx, &self.iso.values);
        let dot3 = |i: usize, j: usize| {
            x[3 * i] * x[3 * j] + x[3 * i + 1] * x[3 * j + 1] + x[3 * i + 2] * x[3 * j + 2]
        };
        let square = self.laplacian_square.as_deref();
        let run = |start: usize| -> f64 {
            let mut sum = 0.0;
            for j in start..(start + QUADRATIC_FORM_RUN).min(n) {
                for s in col_ptr[j]..col_ptr[j + 1] {
                    let i = row_idx[s];
                    let v = k[s] * dot3(i, j);
                    sum += if i == j { v } else { 2.0 * v };
                }
                let c = &self.ring_c[j];
                if *c != [0.0; 6] {
                    let r = self.rings.apply_flat(x, j);
                    let t = sym3_mul(c, r);
                    sum += r[0] * t[0] + r[1] * t[1] + r[2] * t[2];
                }
                if let Some(model) = square {
                    let m = model.square_weight(j);
                    if m != 0.0 {
                        let r = model.laplacian.apply_flat(x, j);
                        sum += m * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
                    }
                }
            }
            sum
        };
        let runs: Vec<f64> = (0..n.div_ceil(QUADRATIC_FORM_RUN))
            .into_par_iter()
            .map(|r| run(r * QUADRATIC_FORM_RUN))
            .collect();
        runs.iter().sum()
    }

    /// `y = A x`, sequential and without a row index (for occasional products).
    pub fn mul_vec(&self, x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        let (col_ptr, row_idx, k) = (&self.iso.col_ptr, &self.iso.row_idx, &self.iso.values);
        for j in 0..self.n() {
            for s in col_ptr[j]..col_ptr[j + 1] {
                let i = row_idx[s];
                for c in 0..3 {
                    y[3 * i + c] += k[s] * x[3 * j + c];
                    if i != j {
                        y[3 * j + c] += k[s] * x[3 * i + c];
                    }
                }
            }
        }
        let t = self.ring_terms(x);
        self.scatter_rings(&t, y);
        self.add_laplacian_square(x, y);
    }

    /// The values on `K`'s lower pattern of the term
    /// [`Self::laplacian_square`] names (`None` without one): `m_i S_ip S_iq`
    /// summed over each row `i` of `S` and its pairs `(p, q)`, in
    /// [`SparseRows::pairs`] order, each found by search; an error names a
    /// pair outside the pattern.
    pub fn laplacian_square_values(&self) -> Result<Option<Vec<f64>>, SolverError> {
        let Some(model) = &self.laplacian_square else {
            return Ok(None);
        };
        let mut values = vec![0.0; self.iso.values.len()];
        for i in 0..model.laplacian.len() {
            let m = model.square_weight(i);
            if m == 0.0 {
                continue;
            }
            for (p, q, f) in model.laplacian.pairs(i) {
                let Some(s) = self.iso.slot(p, q) else {
                    return Err(SolverError::DimensionMismatch(format!(
                        "Laplacian pair ({p}, {q}) of row {i} is outside the matrix pattern"
                    )));
                };
                values[s] += m * f;
            }
        }
        Ok(Some(values))
    }

    /// The same matrix as explicit 3x3 blocks (for backends that take blocks).
    /// Panics if a ring pair (or a pair of [`Self::laplacian_square`]'s rows)
    /// lies outside the pattern of `K`.
    pub fn to_blocks(&self) -> BlockSym3 {
        // K's value per lower entry plus the Laplacian square's (summed
        // apart, over its rows' pairs in order), then the rings: the order
        // of every sum of these blocks.
        let mut k = self.iso.values.clone();
        let square = self
            .laplacian_square_values()
            .expect("Laplacian pair inside the pattern");
        if let Some(square) = square {
            k.iter_mut().zip(&square).for_each(|(v, q)| *v += q);
        }
        let mut b = BlockSym3 {
            n: self.n(),
            col_ptr: self.iso.col_ptr.clone(),
            row_idx: self.iso.row_idx.clone(),
            blocks: k
                .iter()
                .map(|&v| [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v])
                .collect(),
        };
        for (i, c) in self.ring_c.iter().enumerate() {
            if *c == [0.0; 6] {
                continue;
            }
            let m = sym3_block(c);
            for (p, q, f) in self.rings.pairs(i) {
                let (s, _) = b.slot(p, q).expect("ring pair inside the pattern");
                for (o, me) in b.blocks[s].iter_mut().zip(&m) {
                    *o += f * me;
                }
            }
        }
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    impl IsoRingSym3 {
        fn with_values_of(mut self, other: &IsoRingSym3) -> Self {
            self.iso.values = other.iso.values.clone();
            self.ring_c = other.ring_c.clone();
            self
        }
    }

    /// [`SparseRows::from_triplets`] as one pass over the sorted triplets
    /// (the form it had before its groups of rows on rayon's threads).
    fn from_triplets_in_one_pass(
        n: usize,
        mut t: Vec<(u32, u32, f64)>,
        normalise: bool,
    ) -> SparseRows {
        t.retain(|e| (e.0 as usize) < n);
        t.sort_unstable_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)).then(a.2.total_cmp(&b.2)));
        let mut start = vec![0usize; n + 1];
        let (mut idx, mut w) = (Vec::new(), Vec::<f64>::new());
        let mut last = None;
        for (i, j, v) in t {
            if last == Some((i, j)) {
                *w.last_mut().unwrap() += v;
            } else {
                idx.push(j);
                w.push(v);
                start[i as usize + 1] += 1;
                last = Some((i, j));
            }
        }
        for i in 0..n {
            start[i + 1] += start[i];
        }
        let mut diag = vec![0.0; n];
        for i in 0..n {
            let r = start[i]..start[i + 1];
            let sum: f64 = w[r.clone()].iter().sum();
            if !normalise {
                diag[i] = sum;
            } else if sum > 0.0 {
                w[r].iter_mut().for_each(|v| *v /= sum);
                diag[i] = 1.0;
            }
        }
        SparseRows {
            start,
            idx,
            w,
            diag,
        }
    }

    /// Each pair's positions name the row entries whose columns and
    /// product it is, in the pairs' order; rows of several lengths, columns
    /// on either side of the diagonal.
    #[test]
    fn pair_positions_name_each_pairs_entries() {
        let t = vec![
            (0, 3, 1.0),
            (0, 1, 2.0),
            (1, 0, 0.5),
            (2, 0, 1.0),
            (2, 1, 3.0),
            (2, 3, 1.0),
        ];
        let rows = SparseRows::from_triplets(4, t, false);
        let mut seen = 0;
        for i in 0..rows.len() {
            let entries: Vec<(usize, f64)> = rows.row(i).collect();
            let n = entries.len();
            assert_eq!(rows.pair_positions(i).count(), rows.pairs(i).count());
            for ((a, b), (p, q, f)) in rows.pair_positions(i).zip(rows.pairs(i)) {
                assert_eq!((entries[a].0, entries[b].0), (p, q), "row {i}");
                assert_eq!((entries[a].1 * entries[b].1).to_bits(), f.to_bits());
                assert!(a < n && b < n);
                seen += 1;
            }
        }
        // Rows of 3, 2, 4 and 1 entries: k (k + 1) / 2 pairs each.
        assert_eq!(seen, 6 + 3 + 10 + 1);
    }

    /// Rows in several groups of [`TRIPLET_ROWS`], with duplicates (up to
    /// three of a pair, in scrambled order), empty rows, a zero-sum row and
    /// placeholders: the same rows, to the bit, as one pass over them all,
    /// on one thread and on four, from the triplets and row by row.
    #[test]
    fn triplets_give_the_rows_of_one_pass_on_any_thread_count() {
        let n = 3 * TRIPLET_ROWS + 17;
        let mut t = Vec::new();
        for i in 0..n {
            if i % 7 == 3 {
                continue; // an empty row
            }
            for d in 1..=(i % 4 + 1) {
                let j = ((i * 31 + d * 977) % n) as u32;
                let v = ((i * d) as f64 * 0.37).sin();
                t.push((i as u32, j, v));
                if d % 2 == 0 {
                    t.push((i as u32, j, 0.1 * v + 1e-3));
                }
            }
            if i % 11 == 0 {
                t.push(NO_TRIPLET);
            }
            if i % 5 == 0 {
                // Three terms whose sum depends on their order: (1e-16 +
                // 1e-16) + 1 is above 1, (1 + 1e-16) + 1e-16 is 1.
                let j = ((i + 1) % n) as u32;
                t.extend([1.0, 1e-16, 1e-16].map(|v| (i as u32, j, v)));
            }
        }
        t.push((5, 9, 1.0));
        t.push((5, 10, -1.0)); // row 5 may sum to zero
                               // Scrambled: the order of a pair's duplicates is the sort's.
        let len = t.len();
        for k in 0..len {
            t.swap(k, (k * 7919 + 13) % len);
        }
        let mut per_row = vec![Vec::new(); n];
        for &(i, j, v) in t.iter().filter(|e| (e.0 as usize) < n) {
            per_row[i as usize].push((j, v));
        }
        for normalise in [false, true] {
            let want = from_triplets_in_one_pass(n, t.clone(), normalise);
            for threads in [1, 4] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let by_triplets =
                    pool.install(|| SparseRows::from_triplets(n, t.clone(), normalise));
                // Each row's triplets pushed in their scrambled order.
                let by_rows = pool.install(|| {
                    SparseRows::from_rows(n, |i, out| out.extend(&per_row[i]), normalise)
                });
                for (how, got) in [("triplets", by_triplets), ("rows", by_rows)] {
                    assert_eq!(got.start, want.start, "{how}, {threads} threads");
                    assert_eq!(got.idx, want.idx, "{how}");
                    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(
                        bits(&got.w),
                        bits(&want.w),
                        "{how}, {threads} threads, {normalise}"
                    );
                    assert_eq!(bits(&got.diag), bits(&want.diag), "{how}");
                }
            }
        }
    }

    /// Rings of a cycle of `n` vertices (each with its two neighbours), and a
    /// random-ish matrix on their 2-ring pattern.
    fn sample(n: usize) -> IsoRingSym3 {
        let mut t = Vec::new();
        for i in 0..n {
            let (a, b) = ((i + 1) % n, (i + n - 1) % n);
            t.push((i as u32, a as u32, 1.0 + 0.3 * (i as f64).sin().abs()));
            t.push((i as u32, b as u32, 0.5 + 0.2 * (i as f64 * 1.7).cos().abs()));
        }
        let rings = Arc::new(SparseRows::from_triplets(n, t, true));
        let pairs = (0..n).flat_map(|i| [(i, (i + 1) % n), (i, (i + 2) % n)]);
        let pat = SymCsc::from_pattern(n, pairs);
        let mut a = IsoRingSym3::new(n, pat.col_ptr, pat.row_idx, rings);
        for j in 0..n {
            for s in a.iso.col_ptr[j]..a.iso.col_ptr[j + 1] {
                let i = a.iso.row_idx[s];
                a.iso.values[s] = if i == j {
                    4.0 + (j as f64).cos()
                } else {
                    -0.3 - 0.1 * (s as f64 * 0.9).sin()
                };
            }
        }
        for (i, c) in a.ring_c.iter_mut().enumerate() {
            let d = [(i as f64).sin(), (i as f64 * 0.3).cos(), 0.5];
            let dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            *c = [
                dd / 3.0 - d[0] * d[0],
                dd / 3.0 - d[1] * d[1],
                dd / 3.0 - d[2] * d[2],
                -d[0] * d[1],
                -d[0] * d[2],
                -d[1] * d[2],
            ];
        }
        a
    }

    #[test]
    fn products_agree_with_the_explicit_blocks() {
        let a = sample(40);
        let b = a.to_blocks();
        let x: Vec<f64> = (0..120).map(|i| (i as f64 * 0.37).sin() + 0.1).collect();
        let mut want = vec![0.0; 120];
        b.mul_vec(&x, &mut want);
        let mut seq = vec![f64::NAN; 120];
        a.mul_vec(&x, &mut seq);
        let mut par = vec![f64::NAN; 120];
        a.mul_vec_rows(&a.row_index(), &x, &mut par);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.1);
        for i in 0..120 {
            assert!((seq[i] - want[i]).abs() < 1e-12 * scale, "sequential {i}");
            assert!((par[i] - want[i]).abs() < 1e-12 * scale, "parallel {i}");
        }
        // The ring terms are traceless, so K is the blocks' isotropic part.
        for (s, blk) in b.blocks.iter().enumerate() {
            let tr = (blk[0] + blk[4] + blk[8]) / 3.0;
            assert!((tr - a.iso.values[s]).abs() < 1e-12);
        }
        // Off-diagonal ring coupling is present (the blocks are not isotropic).
        assert!(b.blocks.iter().any(|blk| blk[1].abs() > 1e-3));
    }

    /// A row's product read from the slices is the sum `row` gives, in its
    /// order, to the bit.
    #[test]
    fn apply_is_the_rows_sum_to_the_bit() {
        let a = sample(30);
        let x: Vec<DVec3> = (0..30)
            .map(|i| DVec3::new((i as f64 * 0.7).sin(), 1e-3 * i as f64, -(i as f64).cos()))
            .collect();
        for i in 0..30 {
            let want = a
                .rings
                .row(i)
                .fold(DVec3::ZERO, |acc, (j, c)| acc + c * x[j]);
            let got = a.rings.apply(&x, i);
            assert_eq!(
                got.to_array().map(f64::to_bits),
                want.to_array().map(f64::to_bits),
                "row {i}"
            );
        }
    }

    /// A Laplacian square term the matrix names is in every product and in
    /// its blocks, as if its values were added to `K` (here by hand).
    /// `plain` with a Laplacian square term named: a Laplacian on its rings'
    /// pattern with other weights, and `Mt` 0 at vertex 3 (no weight there).
    fn with_square(plain: &IsoRingSym3) -> IsoRingSym3 {
        let n = plain.n();
        let r = &plain.rings;
        let w: Vec<f64> = (0..r.w.len())
            .map(|k| r.w[k] * (1.5 + (k as f64).cos()))
            .collect();
        let diag = (0..n)
            .map(|i| w[r.start[i]..r.start[i + 1]].iter().sum())
            .collect();
        let laplacian = Arc::new(SparseRows {
            start: r.start.clone(),
            idx: r.idx.clone(),
            w,
            diag,
        });
        let mt: Vec<f64> = (0..n)
            .map(|i| if i == 3 { 0.0 } else { 0.2 + 0.01 * i as f64 })
            .collect();
        let mut named = plain.clone();
        named.laplacian_square = Some(Arc::new(ShapeOperatorModel {
            laplacian,
            mt,
            c: 0.0,
        }));
        named
    }

    #[test]
    fn a_named_laplacian_square_is_in_every_product() {
        let n = 40;
        let plain = sample(n);
        let named = with_square(&plain);
        let model = named.laplacian_square.clone().unwrap();
        let (laplacian, mt) = (&model.laplacian, &model.mt);
        let mut explicit = plain.clone();
        for (i, &mti) in mt.iter().enumerate() {
            if mti == 0.0 {
                continue;
            }
            for (p, wp) in laplacian.row(i) {
                for (q, wq) in laplacian.row(i) {
                    if p >= q {
                        let s = explicit.iso.slot(p, q).unwrap();
                        explicit.iso.values[s] += wp * wq / mti;
                    }
                }
            }
        }
        let x: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.37).sin() + 0.1).collect();
        let mut want = vec![0.0; 3 * n];
        explicit.mul_vec(&x, &mut want);
        let (mut seq, mut par, mut blk, mut without) = (
            vec![f64::NAN; 3 * n],
            vec![f64::NAN; 3 * n],
            vec![0.0; 3 * n],
            vec![0.0; 3 * n],
        );
        named.mul_vec(&x, &mut seq);
        named.mul_vec_rows(&named.row_index(), &x, &mut par);
        named.to_blocks().mul_vec(&x, &mut blk);
        plain.mul_vec(&x, &mut without);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let far = (0..3 * n).fold(0.0f64, |m, i| m.max((without[i] - want[i]).abs()));
        assert!(far > 0.1 * scale, "the term matters: {far} of {scale}");
        for i in 0..3 * n {
            assert!((seq[i] - want[i]).abs() < 1e-12 * scale, "sequential {i}");
            assert!((par[i] - want[i]).abs() < 1e-12 * scale, "parallel {i}");
            assert!((blk[i] - want[i]).abs() < 1e-12 * scale, "blocks {i}");
        }
    }

    /// `x^T A x` is `x . (A x)`, with and without a named Laplacian
    /// square, and the same to the bit on one thread and on four.
    #[test]
    fn the_quadratic_form_is_x_dot_ax_on_any_number_of_threads() {
        let n = 2 * QUADRATIC_FORM_RUN + 100;
        let plain = sample(n);
        let x: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.37).sin() + 0.1).collect();
        for a in [plain.clone(), with_square(&plain)] {
            let mut ax = vec![0.0; 3 * n];
            a.mul_vec(&x, &mut ax);
            let want: f64 = x.iter().zip(&ax).map(|(p, q)| p * q).sum();
            let on = |threads| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                pool.install(|| a.quadratic_form(&x))
            };
            let (one, four) = (on(1), on(4));
            assert!(want > 1.0, "a positive form: {want}");
            assert!((one - want).abs() < 1e-12 * want, "{one} against {want}");
            assert_eq!(one.to_bits(), four.to_bits());
        }
        // The square term is in it: the two forms differ.
        let (p, q) = (
            plain.quadratic_form(&x),
            with_square(&plain).quadratic_form(&x),
        );
        assert!((p - q).abs() > 1e-3 * p, "{p} and {q}");
    }

    #[test]
    fn unsymmetric_ring_patterns_fall_back_to_the_scatter() {
        let mut a = sample(12);
        // Drop one neighbour from one row: the pattern is no longer symmetric.
        let mut rings = (*a.rings).clone();
        rings.idx.remove(0);
        rings.w.remove(0);
        for s in rings.start.iter_mut().skip(1) {
            *s -= 1;
        }
        assert!(!rings.pattern_is_symmetric());
        a = IsoRingSym3::new(
            a.n(),
            a.iso.col_ptr.clone(),
            a.iso.row_idx.clone(),
            Arc::new(rings),
        )
        .with_values_of(&a);
        assert!(a.ring_t.is_empty());
        let b = a.to_blocks();
        let x: Vec<f64> = (0..36).map(|i| (i as f64 * 0.61).cos()).collect();
        let (mut want, mut got) = (vec![0.0; 36], vec![0.0; 36]);
        b.mul_vec(&x, &mut want);
        a.mul_vec_rows(&a.row_index(), &x, &mut got);
        for i in 0..36 {
            assert!((got[i] - want[i]).abs() < 1e-12, "{i}");
        }
    }

    #[test]
    fn an_isotropic_analysis_made_ahead_on_another_thread_is_adopted() {
        use crate::{BlockPcgSolver, FillOrdering, SpdSolver};
        let n = 300;
        let mut a = sample(n);
        for j in 0..n {
            let s = a.diagonal_slot(j);
            a.iso.values[s] += 4.0;
        }
        let mut fixed = vec![false; n];
        fixed[11] = true;
        let ordering: Vec<usize> = (0..n).rev().collect();
        let b: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.41).cos() + 0.3).collect();
        let solve = |ahead: bool| {
            let mut pcg = BlockPcgSolver::new();
            pcg.set_fill_ordering(FillOrdering::Given(ordering.clone().into()));
            if ahead {
                let analyser = pcg.isotropic_analyser().expect("a factor of K to analyse");
                let ((), analysed, _) = crate::analyse_beside(analyser, &a.iso, || ());
                let analysed = analysed.unwrap();
                assert_eq!(analysed.symbolic_count, 1);
                pcg.adopt_isotropic_analysis(analysed);
                assert!(pcg.isotropic_analyser().is_none(), "analysed already");
            }
            pcg.prepare_shape_owned(a.clone(), &fixed).unwrap();
            let mut x = b.clone();
            pcg.solve_in_place(&mut x, 1).unwrap();
            (x, pcg.analyses(), pcg.factorizations())
        };
        let (plain, analyses, factorizations) = solve(false);
        let (ahead, analyses_ahead, factorizations_ahead) = solve(true);
        // One analysis either way (made ahead, not again), one factorization,
        // and the same solve to the bit: the given ordering served the
        // analysis made ahead.
        assert_eq!((analyses, factorizations), (1, 1));
        assert_eq!((analyses_ahead, factorizations_ahead), (1, 1));
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&plain), bits(&ahead));
        // A solver that has analysed already offers nothing and keeps its own.
        let mut pcg = BlockPcgSolver::new();
        pcg.prepare_shape_owned(a.clone(), &fixed).unwrap();
        assert!(pcg.isotropic_analyser().is_none());
        let mut other = crate::CholeskySolver::new();
        other.analyse(&a.iso).unwrap();
        pcg.adopt_isotropic_analysis(other);
        assert_eq!((pcg.analyses(), pcg.factorizations()), (1, 1));
    }

    #[test]
    fn pcg_on_the_iso_ring_form_matches_the_direct_solve_of_its_blocks() {
        use crate::{BlockPcgSolver, CholeskySolver, SpdSolver};
        let n = 60;
        let mut a = sample(n);
        for j in 0..n {
            let s = a.diagonal_slot(j);
            a.iso.values[s] += 4.0;
        }
        let mut fixed = vec![false; n];
        fixed[7] = true;
        fixed[8] = true;
        let b: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.53).sin() + 0.2).collect();
        let mut direct = CholeskySolver::new();
        direct.prepare_blocks(&a.to_blocks(), &fixed).unwrap();
        let mut want = b.clone();
        direct.solve_in_place(&mut want, 1).unwrap();
        let mut pcg = BlockPcgSolver::new();
        let before = a.iso.values.clone();
        assert!(pcg.prepare_shape_owned(a, &fixed).unwrap().is_none());
        // Kept as handed over: the held rows are masked for the factor only.
        assert_eq!(pcg.shape_matrix().unwrap().iso.values, before);
        let mut got = b.clone();
        let info = pcg.solve_in_place(&mut got, 1).unwrap();
        assert!(
            info.iterations > 1,
            "the ring terms are not in the preconditioner"
        );
        for i in 0..3 * n {
            assert!(
                (got[i] - want[i]).abs() < 1e-8,
                "{i}: {} vs {}",
                got[i],
                want[i]
            );
        }
        // Held vertices take their right-hand side.
        assert_eq!(&got[21..27], &b[21..27]);
        let back = pcg.take_shape_matrix().unwrap();
        assert_eq!(back.iso.values, before);
        assert!(pcg.take_shape_matrix().is_none());
    }
}
