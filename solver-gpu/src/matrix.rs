//! The prepared matrix: the lower-triangle CSC input expanded to a full
//! (both triangles) block-CSR with block size 3 (vertex systems) or 1 (scalar
//! system). The host keeps what the f64 residuals of iterative refinement
//! need: a scalar matrix's values, a block matrix's lower triangle and where
//! each full block comes from, or a shape matrix in its isotropic-plus-ring
//! form (its blocks summed on the GPU only) with its diagonal blocks; f32
//! values and the inverted diagonal blocks go to the GPU.

use crate::device::Context;
use crate::expand_blocks::{IDENTITY, TRANSPOSE, ZERO};
use crate::precision::Precision;
use crate::GpuError;
use rayon::prelude::*;
use solver_cpu::{
    sym3_block, BlockRows, BlockSym3, IsoRingSym3, ShapeOperatorModel, SolverError, SparseRows,
    SymCsc,
};
use std::sync::{Arc, OnceLock};

/// Full block-CSR pattern and f64 values (host side). A scalar matrix keeps
/// its values for both triangles; a block matrix keeps only its lower
/// triangle in input order and, per block of both triangles, where its
/// values come from ([`Self::map`], as `expand_blocks.wgsl` reads it): half
/// the bytes, and nothing written per fill beyond the lower blocks.
pub(crate) struct HostMatrix {
    pub bs: usize,
    pub rows: usize,
    pub row_ptr: Vec<u32>,
    pub col_idx: Vec<u32>,
    /// Scalar matrices: one value per stored entry; empty for block ones.
    vals: Vec<f64>,
    /// Block matrices: the lower-triangle blocks (row-major), in the order of
    /// the input's lower CSC.
    lower: Vec<[f64; 9]>,
    /// Block matrices whose lower blocks are summed on the GPU: the matrix in
    /// its isotropic-plus-ring form instead of [`Self::lower`].
    shape: Option<ShapeForm>,
    /// The pattern's row index, for products in the isotropic-plus-ring form.
    shape_rows: OnceLock<BlockRows>,
    /// Block matrices: per block of the full pattern, its lower source, see
    /// [`Self::map`]; made for the held vertices `map_fixed` when first
    /// asked for, and dropped once the GPU's expansion holds it
    /// ([`Self::release_map`]).
    map: OnceLock<Vec<u32>>,
    map_fixed: Vec<bool>,
    /// Full position of each row's diagonal block.
    pub diag: Vec<u32>,
    /// The input pattern's (lower CSC) fingerprint, to recognise a repeated
    /// pattern, and its column pointers: not a copy of the pattern (48 MB
    /// at 1.2M faces). The full rows are sorted, so row `j` from its
    /// diagonal on lists lower column `j`'s rows in their order: each full
    /// block's lower entry is found from them ([`Self::lower_source`]), no
    /// map of them kept (8 bytes a lower entry).
    key: solver_cpu::PatternKey,
    lower_col_ptr: Vec<u32>,
    /// [`Self::norm_inf`] of the current values (reset by every fill).
    norm: OnceLock<f64>,
}

/// A shape matrix `K (x) I3 + sum_i R_i^T C_i R_i` kept in that form.
struct ShapeForm {
    a: IsoRingSym3,
    slots: Arc<RingSlots>,
    /// Its diagonal blocks (held vertices' too, as summed), made when first
    /// asked for ([`shape_diagonal`]): only the inverse diagonals read
    /// them, which a kind preconditioned by its Cholesky factor makes for
    /// its pattern's first matrix only (72 bytes a block row: 43 MB at
    /// homer 1.2M faces).
    diag: OnceLock<Vec<[f64; 9]>>,
    /// Its lower blocks, summed on the host only where something needs them
    /// (the host's fallbacks: no `SHADER_F64`, a binding too small, AMG).
    lower: OnceLock<Vec<[f64; 9]>>,
    /// What the host keeps of its [`IsoRingSym3::laplacian_square`] term.
    square: Option<Arc<SquareParts>>,
}

impl ShapeForm {
    /// Its diagonal blocks, made at the first call.
    fn diagonal(&self) -> &[[f64; 9]] {
        self.diag
            .get_or_init(|| shape_diagonal(&self.a, &self.slots, self.square.as_deref()))
    }
}

/// What the host keeps of a constant term `S Mt^-1 S (x) I3`
/// ([`IsoRingSym3::laplacian_square`]) whose values the GPU holds
/// ([`laplacian_square_values`], added by `sum_shape_blocks.wgsl`): its
/// diagonal and its absolute row sums, one value a vertex each.
pub(crate) struct SquareParts {
    /// The model whose term this is.
    pub model: Arc<ShapeOperatorModel>,
    /// The term's value at each vertex's diagonal slot.
    diag: Vec<f64>,
    /// The term's absolute row sums (for [`shape_norm_bound`]).
    row_abs: Vec<f64>,
}

impl SquareParts {
    /// The parts of `values` ([`laplacian_square_values`] of `model`) on
    /// the lower pattern of `a`.
    pub fn new(model: Arc<ShapeOperatorModel>, a: &IsoRingSym3, values: &[f64]) -> SquareParts {
        let n = a.n();
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let diag = (0..n).map(|v| values[a.diagonal_slot(v)]).collect();
        let mut row_abs = vec![0f64; n];
        add_abs_row_sums(col_ptr, row_idx, values, &mut row_abs);
        SquareParts {
            model,
            diag,
            row_abs,
        }
    }

    /// Whether these are the parts of `model` (by identity).
    pub fn of(&self, model: &Arc<ShapeOperatorModel>) -> bool {
        Arc::ptr_eq(&self.model, model)
    }
}

/// The values on `a`'s lower pattern of its [`IsoRingSym3::laplacian_square`]
/// term `S Mt^-1 S`, as [`IsoRingSym3::laplacian_square_values`] sums them
/// (to the bit), through `slots` where `S` has the rings' rows' columns
/// (E_m's cotangent and E_l's mean-value Laplacian of one mesh) instead of
/// a search per pair.
pub(crate) fn laplacian_square_values(
    a: &IsoRingSym3,
    slots: &RingSlots,
) -> Result<Option<Vec<f64>>, SolverError> {
    let Some(model) = &a.laplacian_square else {
        return Ok(None);
    };
    if !square_through_slots(model, a, slots) {
        return a.laplacian_square_values();
    }
    Ok(Some(square_values_through_slots(
        model,
        slots,
        a.iso.row_idx.len(),
    )))
}

/// Whether `model`'s Laplacian `S` has the rows of `a`'s rings, whose pairs'
/// slots `slots` holds: then [`square_values_through_slots`] sums its
/// square.
pub(crate) fn square_through_slots(
    model: &ShapeOperatorModel,
    a: &IsoRingSym3,
    slots: &RingSlots,
) -> bool {
    let s = &*model.laplacian;
    slots.of(&a.rings) && s.start == a.rings.start && s.idx == a.rings.idx
}

/// [`laplacian_square_values`] of `model` on a lower pattern of `entries`
/// entries, where [`square_through_slots`] holds: its rows' pairs go
/// through `slots` (one serial pass, in the rows' order).
pub(crate) fn square_values_through_slots(
    model: &ShapeOperatorModel,
    slots: &RingSlots,
    entries: usize,
) -> Vec<f64> {
    let s = &*model.laplacian;
    let mut values = vec![0f64; entries];
    let mut row = Vec::new();
    for i in 0..s.len() {
        let m = model.square_weight(i);
        if m == 0.0 {
            continue;
        }
        // The pairs of `SparseRows::pairs`, in its order, from the row read
        // once; one slot per pair (the same columns as the rings').
        row.clear();
        row.extend(s.row(i));
        let mut k = slots.slot[slots.start[i] as usize..slots.start[i + 1] as usize].iter();
        for &(p, wp) in &row {
            for &(q, wq) in &row {
                if p >= q {
                    values[*k.next().unwrap() as usize] += m * (wp * wq);
                }
            }
        }
    }
    values
}

impl HostMatrix {
    /// The prepared matrix with each `bs x bs` block expanded into scalar entries
    /// (CSR, `bs` rows per block row), and its inverted diagonal.
    pub fn scalar_expansion(&self) -> (Vec<u32>, Vec<u32>, Vec<f64>, Vec<f64>) {
        let h = self;
        let bs = h.bs;
        let mut row_ptr = Vec::with_capacity(h.rows * bs + 1);
        let entries = h.nnz_blocks() * bs * bs;
        let mut col_idx = Vec::with_capacity(entries);
        let mut vals = Vec::with_capacity(entries);
        let mut dinv = Vec::with_capacity(h.rows * bs);
        h.make_diagonal();
        row_ptr.push(0u32);
        for i in 0..h.rows {
            let blocks = h.row_ptr[i] as usize..h.row_ptr[i + 1] as usize;
            let d = h.diag_block(i);
            for q in 0..bs {
                for k in blocks.clone() {
                    let j = h.col_idx[k] as usize;
                    let m = h.block_values(k);
                    for t in 0..bs {
                        col_idx.push((j * bs + t) as u32);
                        vals.push(m[q * bs + t]);
                    }
                }
                dinv.push(1.0 / d[q * bs + q]);
                row_ptr.push(col_idx.len() as u32);
            }
        }
        (row_ptr, col_idx, vals, dinv)
    }

    /// Pattern from a lower-triangle CSC (row >= col, sorted, diagonal present).
    pub fn pattern(
        n: usize,
        bs: usize,
        col_ptr: &[usize],
        row_idx: &[usize],
    ) -> Result<HostMatrix, SolverError> {
        if col_ptr.len() != n + 1 || col_ptr[n] != row_idx.len() {
            return Err(SolverError::DimensionMismatch(format!(
                "column pointers ({}) do not describe {} columns and {} entries",
                col_ptr.len(),
                n,
                row_idx.len()
            )));
        }
        let nnz_full = 2 * row_idx.len() - n;
        if nnz_full as u64 * (bs * bs) as u64 >= u32::MAX as u64
            || n * bs * crate::CMAX >= u32::MAX as usize
        {
            return Err(SolverError::Backend(format!(
                "matrix too large for 32-bit GPU indices ({n} rows, {nnz_full} blocks)"
            )));
        }
        let mut count = vec![0u32; n + 1];
        for j in 0..n {
            let (s, e) = (col_ptr[j], col_ptr[j + 1]);
            if s >= e || row_idx[s] != j {
                return Err(SolverError::NotPositiveDefinite);
            }
            for &i in &row_idx[s..e] {
                if i < j || i >= n {
                    return Err(SolverError::DimensionMismatch(format!(
                        "entry ({i}, {j}) is not in the lower triangle of a {n} x {n} matrix"
                    )));
                }
                count[i + 1] += 1;
                if i != j {
                    count[j + 1] += 1;
                }
            }
        }
        for i in 0..n {
            count[i + 1] += count[i];
        }
        let row_ptr = count.clone();
        let mut next = count;
        // Row r gets (r, j) for the columns j < r in ascending order, then
        // (r, r) and (r, i) for the rows i > r of column r in their
        // (ascending) order: every row sorted.
        let mut col_idx = vec![0u32; nnz_full];
        let mut diag = vec![0u32; n];
        for j in 0..n {
            for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
                let lo = next[i];
                next[i] += 1;
                col_idx[lo as usize] = j as u32;
                if i == j {
                    diag[i] = lo;
                } else {
                    let up = next[j];
                    next[j] += 1;
                    col_idx[up as usize] = i as u32;
                }
            }
        }
        Ok(HostMatrix {
            bs,
            rows: n,
            row_ptr,
            col_idx,
            vals: if bs == 1 {
                vec![0.0; nnz_full]
            } else {
                Vec::new()
            },
            lower: Vec::new(),
            shape: None,
            shape_rows: OnceLock::new(),
            map: OnceLock::new(),
            map_fixed: Vec::new(),
            diag,
            key: solver_cpu::PatternKey::of(col_ptr, row_idx),
            lower_col_ptr: col_ptr.iter().map(|&c| c as u32).collect(),
            norm: OnceLock::new(),
        })
    }

    pub fn same_pattern(&self, bs: usize, col_ptr: &[usize], row_idx: &[usize]) -> bool {
        self.bs == bs && self.key == solver_cpu::PatternKey::of(col_ptr, row_idx)
    }

    /// Length of one column.
    pub fn n(&self) -> usize {
        self.rows * self.bs
    }

    pub fn nnz_blocks(&self) -> usize {
        self.col_idx.len()
    }

    /// Values of a block matrix; rows/columns of fixed vertices become identity
    /// (as `BlockSym3::fill_scalar`).
    pub fn fill_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) {
        let mut lower = std::mem::take(&mut self.lower);
        lower.clear();
        lower.extend_from_slice(&a.blocks);
        self.set_lower(lower, fixed);
    }

    /// Values of a shape matrix in isotropic-plus-ring form, `K (x) I3 + sum_i
    /// R_i^T C_i R_i`, without its explicit [`BlockSym3`]: the lower blocks are
    /// summed in place (no allocation after the first fill of a pattern) with
    /// the ring pairs' slots from `slots`, in the order and with the
    /// arithmetic of [`IsoRingSym3::to_blocks`] (the same values to the bit).
    pub fn fill_shape(
        &mut self,
        a: &IsoRingSym3,
        slots: &RingSlots,
        fixed: &[bool],
    ) -> Result<(), SolverError> {
        let mut scratch = std::mem::take(&mut self.lower);
        let square = laplacian_square_values(a, slots)?;
        sum_lower(a, slots, square.as_deref(), &mut scratch);
        self.set_lower(scratch, fixed);
        Ok(())
    }

    /// A shape matrix kept in its isotropic-plus-ring form, for the GPU to
    /// sum its blocks (`sum_shape_blocks.wgsl`): the host keeps `a` (for the
    /// residuals, [`Self::residual`]) and its diagonal blocks, no lower
    /// blocks. Hand `a` back with [`Self::take_shape`]. A term `a` names
    /// ([`IsoRingSym3::laplacian_square`]) comes with its `square` parts.
    pub fn set_shape(
        &mut self,
        a: IsoRingSym3,
        slots: Arc<RingSlots>,
        fixed: &[bool],
        square: Option<Arc<SquareParts>>,
    ) {
        debug_assert_eq!(self.bs, 3);
        debug_assert_eq!(
            a.laplacian_square.as_ref().map(Arc::as_ptr),
            square.as_ref().map(|q| Arc::as_ptr(&q.model))
        );
        self.norm = OnceLock::new();
        self.lower = Vec::new();
        self.shape = Some(ShapeForm {
            a,
            slots,
            diag: OnceLock::new(),
            lower: OnceLock::new(),
            square,
        });
        self.set_fixed(fixed);
    }

    /// Makes what [`Self::diag_block`] reads where it is made only when
    /// first asked for: a shape form's diagonal blocks, or the block map.
    /// Call it before diagonal blocks are read on rayon's threads: made at a
    /// row's first read inside such a loop, their making's own parallel
    /// tasks could let a thread of the loop take up another row's read,
    /// which would wait on the making it is part of.
    pub fn make_diagonal(&self) {
        match &self.shape {
            Some(f) => {
                f.diagonal();
            }
            None => self.make_block_parts(),
        }
    }

    /// Makes what [`Self::block_values`] reads where it is made only when
    /// first asked for (the block map, a shape form's lower blocks), before
    /// block values are read on rayon's threads (as [`Self::make_diagonal`]).
    pub fn make_block_parts(&self) {
        if self.bs == 3 {
            self.map();
            self.lower_blocks();
        }
    }

    /// Drops a shape form's diagonal blocks (made again when asked for).
    pub fn release_diagonal(&mut self) {
        if let Some(f) = &mut self.shape {
            f.diag = OnceLock::new();
        }
    }

    /// The shape matrix kept by [`Self::set_shape`].
    pub fn shape_form(&self) -> Option<&IsoRingSym3> {
        self.shape.as_ref().map(|f| &f.a)
    }

    /// Takes back the shape matrix kept by [`Self::set_shape`]: the matrix
    /// has no values until the next fill ([`Self::is_filled`]).
    pub fn take_shape(&mut self) -> Option<IsoRingSym3> {
        self.shape.take().map(|f| f.a)
    }

    /// Whether the matrix has values (a shape matrix taken back has none).
    pub fn is_filled(&self) -> bool {
        self.bs == 1 || self.shape.is_some() || self.lower.len() == self.lower_len()
    }

    /// New lower blocks (the input pattern's, in its order) with the rows and
    /// columns of the held vertices `fixed` the identity: the map is made
    /// again only when the held vertices change.
    fn set_lower(&mut self, lower: Vec<[f64; 9]>, fixed: &[bool]) {
        debug_assert_eq!(self.bs, 3);
        debug_assert_eq!(lower.len(), self.lower_len());
        self.norm = OnceLock::new();
        self.lower = lower;
        self.shape = None;
        self.set_fixed(fixed);
    }

    /// The held vertices `fixed`: the map made for others is dropped (made
    /// again when asked for).
    pub(crate) fn set_fixed(&mut self, fixed: &[bool]) {
        if self.map_fixed != fixed {
            self.map = OnceLock::new();
            self.map_fixed.clear();
            self.map_fixed.extend_from_slice(fixed);
        }
    }

    /// For each block of the full pattern, where its values come from in the
    /// lower-CSC input: the lower block's index (with [`TRANSPOSE`] for the
    /// upper triangle), [`ZERO`] or [`IDENTITY`] in the rows and columns of
    /// held vertices (`fixed`). Every lower index fits below [`IDENTITY`]
    /// without the transpose bit ([`Self::pattern`] bounds the blocks).
    fn block_map(&self, fixed: &[bool]) -> Vec<u32> {
        let mut map = vec![ZERO; self.nnz_blocks()];
        self.for_each_row_mut(&mut map, |r, p, c, out| {
            let (k, transposed) = self.lower_source(r, p);
            *out = match (fixed[r] || fixed[c], c == r) {
                (true, true) => IDENTITY,
                (true, false) => ZERO,
                (false, _) if transposed => k as u32 | TRANSPOSE,
                (false, _) => k as u32,
            };
        });
        map
    }

    /// For the block at full position `p` in row `r`, its lower-CSC input
    /// entry and whether the block is that entry's transpose (the upper
    /// triangle): at and right of the diagonal, row `r` lists lower column
    /// `r`'s rows in order; left of it, `(r, c)` is found in row `c`'s.
    fn lower_source(&self, r: usize, p: usize) -> (usize, bool) {
        let c = self.col_idx[p] as usize;
        if c >= r {
            let t = p - self.diag[r] as usize;
            return (self.lower_col_ptr[r] as usize + t, c > r);
        }
        let from = self.diag[c] as usize;
        let row_c = &self.col_idx[from..self.row_ptr[c + 1] as usize];
        // (r, c) is in lower column c, so r is in row c right of its diagonal.
        let t = row_c.partition_point(|&q| (q as usize) < r);
        debug_assert_eq!(row_c[t] as usize, r);
        (self.lower_col_ptr[c] as usize + t, false)
    }

    /// `f(r, p, c, &mut out[p])` for every full position `p` of every row
    /// `r` (column `c`), the rows on rayon's threads.
    fn for_each_row_mut<T: Send>(
        &self,
        out: &mut [T],
        f: impl Fn(usize, usize, usize, &mut T) + Sync,
    ) {
        let row_ptr = &self.row_ptr;
        let groups = solver_cpu::row_groups_mut(out, self.rows, |r| row_ptr[r] as usize, 1024);
        groups.into_par_iter().for_each(|(rows, group)| {
            let base = row_ptr[rows.start] as usize;
            for r in rows {
                for p in row_ptr[r] as usize..row_ptr[r + 1] as usize {
                    f(r, p, self.col_idx[p] as usize, &mut group[p - base]);
                }
            }
        });
    }

    /// Per block of the full pattern, where its values come from (for
    /// `expand_blocks.wgsl`): see [`Self::block_map`].
    pub fn map(&self) -> &[u32] {
        self.map.get_or_init(|| self.block_map(&self.map_fixed))
    }

    /// Drops the host's copy of [`Self::map`] (4 bytes a full block: 46 MB
    /// at homer 1.2M faces, 165 MB at 4.3M), for a matrix whose expansion
    /// on the GPU holds it: nothing on the host reads it then. A host path
    /// that asks for it (block values, the fallbacks' uploads) makes it
    /// again.
    pub fn release_map(&mut self) {
        self.map = OnceLock::new();
    }

    /// Whether the host holds [`Self::map`] now.
    #[cfg(test)]
    pub fn map_held(&self) -> bool {
        self.map.get().is_some()
    }

    /// Whether a shape form's diagonal blocks are made.
    #[cfg(test)]
    pub fn diagonal_held(&self) -> bool {
        self.shape.as_ref().is_some_and(|f| f.diag.get().is_some())
    }

    /// The lower-triangle blocks of a block matrix, in input order (a shape
    /// matrix's summed on the host when first asked for).
    pub fn lower_blocks(&self) -> &[[f64; 9]] {
        match &self.shape {
            Some(f) => f.lower.get_or_init(|| {
                log::debug!("shape matrix: lower blocks summed on the host for a fallback");
                let mut out = Vec::new();
                // The host keeps the term's parts, not its values: found
                // again (they were found for these slots when the parts
                // were made, so this can not fail).
                let square = laplacian_square_values(&f.a, &f.slots).ok().flatten();
                sum_lower(&f.a, &f.slots, square.as_deref(), &mut out);
                out
            }),
            None => &self.lower,
        }
    }

    /// Whether a shape matrix's lower blocks were summed on the host.
    #[cfg(test)]
    pub fn lower_summed_on_host(&self) -> bool {
        self.shape.as_ref().is_some_and(|f| f.lower.get().is_some())
    }

    /// Bytes of host memory this matrix holds beyond the shape matrix's own
    /// form (which the caller, or the CPU backend, holds as well): its
    /// pattern, values, maps and indices, by their vectors' capacities.
    pub fn host_bytes(&self) -> usize {
        #[allow(clippy::ptr_arg)]
        fn b<T>(v: &Vec<T>) -> usize {
            v.capacity() * std::mem::size_of::<T>()
        }
        let mut n = b(&self.row_ptr)
            + b(&self.col_idx)
            + b(&self.vals)
            + b(&self.lower)
            + self.map.get().map_or(0, b)
            + b(&self.map_fixed)
            + b(&self.diag)
            + b(&self.lower_col_ptr);
        if let Some(f) = &self.shape {
            n += f.diag.get().map_or(0, b) + f.lower.get().map_or(0, b);
        }
        if let Some(r) = self.shape_rows.get() {
            n += b(&r.row_ptr) + b(&r.entries);
        }
        n
    }

    /// Lower-triangle blocks of the pattern.
    pub fn lower_len(&self) -> usize {
        self.lower_col_ptr.last().map_or(0, |&l| l as usize)
    }

    /// The diagonal block of block row `row` (the identity for a held
    /// vertex).
    pub fn diag_block(&self, row: usize) -> [f64; 9] {
        match &self.shape {
            Some(_) if self.map_fixed[row] => [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            Some(f) => f.diagonal()[row],
            None => self.block_values(self.diag[row] as usize),
        }
    }

    /// The values of stored block `k` (row-major; the first `bs * bs` count).
    #[inline]
    pub fn block_values(&self, k: usize) -> [f64; 9] {
        if self.bs == 1 {
            let mut v = [0.0; 9];
            v[0] = self.vals[k];
            return v;
        }
        match self.map()[k] {
            ZERO => [0.0; 9],
            IDENTITY => [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            m if m & TRANSPOSE != 0 => {
                let b = &self.lower_blocks()[(m & !TRANSPOSE) as usize];
                [b[0], b[3], b[6], b[1], b[4], b[7], b[2], b[5], b[8]]
            }
            m => self.lower_blocks()[m as usize],
        }
    }

    /// Every stored value, `bs * bs` per block in block-CSR order (for the
    /// AMG set-up, which keeps its own copy, and for tests).
    pub fn full_values(&self) -> Vec<f64> {
        if self.bs == 1 {
            return self.vals.clone();
        }
        let mut out = Vec::new();
        self.values_into(0..self.nnz_blocks(), |v| v, &mut out);
        out
    }

    /// The values of blocks `blocks`, each through `part`, appended to `out`
    /// (in parallel).
    pub fn values_into<T: Send>(
        &self,
        blocks: std::ops::Range<usize>,
        part: fn(f64) -> T,
        out: &mut Vec<T>,
    ) {
        let bb = self.bs * self.bs;
        if self.bs == 1 {
            out.par_extend(self.vals[blocks].par_iter().map(|&v| part(v)));
            return;
        }
        self.make_block_parts();
        out.par_extend(
            blocks
                .into_par_iter()
                .flat_map_iter(move |k| self.block_values(k).into_iter().take(bb).map(part)),
        );
    }

    /// Values of a scalar matrix.
    pub fn fill_scalar(&mut self, a: &SymCsc) {
        debug_assert_eq!(self.bs, 1);
        self.norm = OnceLock::new();
        let mut vals = std::mem::take(&mut self.vals);
        self.for_each_row_mut(&mut vals, |r, p, _, out| {
            *out = a.values[self.lower_source(r, p).0];
        });
        self.vals = vals;
    }

    /// `||A||_inf`, the largest absolute row sum (an upper bound of `||A||_2`
    /// for a symmetric matrix): one pass over the values after each fill,
    /// kept for every solve of those values.
    pub fn norm_inf(&self) -> f64 {
        *self.norm.get_or_init(|| self.row_sums_max())
    }

    /// Whether [`Self::norm_inf`] was found for the current values.
    #[cfg(test)]
    pub fn norm_found(&self) -> bool {
        self.norm.get().is_some()
    }

    fn row_sums_max(&self) -> f64 {
        if let Some(f) = &self.shape {
            let square = f.square.as_ref().map(|q| q.row_abs.as_slice());
            let ring_abs = rings_abs_parts(&f.a, &f.slots);
            return shape_norm_bound(&f.a, square, &ring_abs, &self.map_fixed);
        }
        let bs = self.bs;
        self.make_block_parts();
        (0..self.rows)
            .into_par_iter()
            .map(|row| {
                let mut acc = [0f64; 3];
                for k in self.row_ptr[row] as usize..self.row_ptr[row + 1] as usize {
                    let m = self.block_values(k);
                    for q in 0..bs {
                        acc[q] += m[q * bs..(q + 1) * bs].iter().map(|v| v.abs()).sum::<f64>();
                    }
                }
                acc.into_iter().fold(0.0, f64::max)
            })
            .reduce(|| 0.0, f64::max)
    }

    /// `r = b - A x` in f64 for `ncols` columns (column-major, length `n` each).
    pub fn residual(&self, b: &[f64], x: &[f64], r: &mut [f64], ncols: usize) {
        let n = self.n();
        let bs = self.bs;
        if let Some(f) = &self.shape {
            // In the isotropic-plus-ring form, as the CPU backend's product:
            // held columns dropped, held rows the identity.
            let rows = self.shape_rows.get_or_init(|| f.a.row_index());
            let fixed = &self.map_fixed;
            let mut xm = vec![0.0; n];
            for c in 0..ncols {
                let (bc, xc) = (&b[c * n..(c + 1) * n], &x[c * n..(c + 1) * n]);
                let rc = &mut r[c * n..(c + 1) * n];
                xm.par_chunks_mut(3).enumerate().for_each(|(v, o)| {
                    if !fixed[v] {
                        o.copy_from_slice(&xc[3 * v..3 * v + 3]);
                    } else {
                        o.fill(0.0);
                    }
                });
                f.a.mul_vec_rows(rows, &xm, rc);
                rc.par_chunks_mut(3).enumerate().for_each(|(v, o)| {
                    for q in 0..3 {
                        let ax = if fixed[v] { xc[3 * v + q] } else { o[q] };
                        o[q] = bc[3 * v + q] - ax;
                    }
                });
            }
            return;
        }
        self.make_block_parts();
        for c in 0..ncols {
            let (bc, xc) = (&b[c * n..(c + 1) * n], &x[c * n..(c + 1) * n]);
            r[c * n..(c + 1) * n]
                .par_chunks_mut(bs)
                .enumerate()
                .for_each(|(row, out)| {
                    let mut acc = [0f64; 3];
                    for k in self.row_ptr[row] as usize..self.row_ptr[row + 1] as usize {
                        let j = self.col_idx[k] as usize;
                        let m = self.block_values(k);
                        for q in 0..bs {
                            let mut s = 0.0;
                            for t in 0..bs {
                                s += m[q * bs + t] * xc[j * bs + t];
                            }
                            acc[q] += s;
                        }
                    }
                    for q in 0..bs {
                        out[q] = bc[row * bs + q] - acc[q];
                    }
                });
        }
    }
}

/// The lower blocks of `a` (input order) summed into `out`, with the ring
/// pairs' slots `slots`, in the order and with the arithmetic of
/// [`IsoRingSym3::to_blocks`] (the same values to the bit), and of
/// `sum_shape_blocks.wgsl`: `K`'s value plus, where `a` names a Laplacian
/// square, its value in `square` ([`laplacian_square_values`]), then the rings.
fn sum_lower(a: &IsoRingSym3, slots: &RingSlots, square: Option<&[f64]>, out: &mut Vec<[f64; 9]>) {
    out.clear();
    match square {
        Some(sq) => out.par_extend(
            a.iso
                .values
                .par_iter()
                .zip(sq)
                .map(|(&v, &q)| v + q)
                .map(|v| [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]),
        ),
        None => out.par_extend(
            a.iso
                .values
                .par_iter()
                .map(|&v| [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]),
        ),
    }
    let rings = &a.rings;
    for (i, c) in a.ring_c.iter().enumerate() {
        let pairs = &slots.slot[slots.start[i] as usize..slots.start[i + 1] as usize];
        if *c == [0.0; 6] {
            continue;
        }
        let m = sym3_block(c);
        // One slot per ring pair, in the same order (`RingSlots::new`).
        for (&s, (_, _, f)) in pairs.iter().zip(rings.pairs(i)) {
            for (o, me) in out[s as usize].iter_mut().zip(&m) {
                *o += f * me;
            }
        }
    }
}

/// `f(i, w)` for each row `i` of the rings that holds column `p` with
/// weight `w` (its own row's diagonal weight for `i == p`), rows whose
/// `C_i` is zero left out, in ascending `i`: for symmetric rings
/// (`RingSlots::symmetric`: `p`'s neighbours are the rows that hold it),
/// in the order in which `sum_lower` sums the rings' terms into `p`'s
/// diagonal slot.
fn rings_holding(a: &IsoRingSym3, p: usize, mut f: impl FnMut(usize, f64)) {
    let rings = &*a.rings;
    let nb = &rings.idx[rings.start[p]..rings.start[p + 1]];
    let below = nb.partition_point(|&i| (i as usize) < p);
    let rows = nb[..below]
        .iter()
        .map(|&i| i as usize)
        .chain(std::iter::once(p))
        .chain(nb[below..].iter().map(|&i| i as usize));
    for i in rows {
        if a.ring_c[i] == [0.0; 6] {
            continue;
        }
        let w = if i == p {
            rings.diag[p]
        } else {
            let row = &rings.idx[rings.start[i]..rings.start[i + 1]];
            match row.binary_search(&(p as u32)) {
                Ok(k) => -rings.w[rings.start[i] + k],
                Err(_) => continue,
            }
        };
        f(i, w);
    }
}

/// The diagonal blocks of the shape matrix `a` (held vertices' too): `K`'s
/// value, plus the constant term's (`square`) as the GPU adds it, plus the
/// rings' `w^2 C_i`, in the order `sum_lower` sums the diagonal slots (the
/// same bits).
fn shape_diagonal(
    a: &IsoRingSym3,
    slots: &RingSlots,
    square: Option<&SquareParts>,
) -> Vec<[f64; 9]> {
    let mut diag: Vec<[f64; 9]> = (0..a.n())
        .into_par_iter()
        .map(|v| {
            let mut k = a.iso.values[a.diagonal_slot(v)];
            if let Some(q) = square {
                k += q.diag[v];
            }
            [k, 0.0, 0.0, 0.0, k, 0.0, 0.0, 0.0, k]
        })
        .collect();
    let add = |d: &mut [f64; 9], c: &[f64; 6], w: f64| {
        let m = sym3_block(c);
        let f = w * w;
        for (o, me) in d.iter_mut().zip(&m) {
            *o += f * me;
        }
    };
    if slots.symmetric {
        diag.par_iter_mut()
            .enumerate()
            .for_each(|(p, d)| rings_holding(a, p, |i, w| add(d, &a.ring_c[i], w)));
    } else {
        for (i, c) in a.ring_c.iter().enumerate() {
            if *c == [0.0; 6] {
                continue;
            }
            for (p, w) in a.rings.row(i) {
                add(&mut diag[p], c, w);
            }
        }
    }
    diag
}

/// Per row `p` of the shape matrix `a`, the rings' part of
/// [`shape_norm_bound`]: the sum over the rings `i` holding `p` of
/// `|R_ip| ||C_i||_inf sum_q |R_iq|` (`slots`: `a`'s ring slots).
fn rings_abs_parts(a: &IsoRingSym3, slots: &RingSlots) -> Vec<f64> {
    let mut ring_abs = vec![0.0; a.n()];
    if slots.symmetric {
        ring_abs.par_iter_mut().enumerate().for_each(|(p, abs)| {
            rings_holding(a, p, |i, w| {
                *abs += w.abs() * (sym3_norm_inf(&a.ring_c[i]) * slots.abs_sum[i]);
            });
        });
    } else {
        for (i, c) in a.ring_c.iter().enumerate() {
            if *c == [0.0; 6] {
                continue;
            }
            let cs = sym3_norm_inf(c) * slots.abs_sum[i];
            for (p, w) in a.rings.row(i) {
                ring_abs[p] += w.abs() * cs;
            }
        }
    }
    ring_abs
}

/// An upper bound of `||A||_inf` for a shape matrix `a` with the held
/// vertices `fixed` (rows of the identity), without its blocks: per row `p`,
/// `sum_j |K_pj|`, plus the rings' part `ring_abs[p]` ([`rings_abs_parts`]),
/// plus the absolute row sums `square` of a Laplacian square term it names
/// (the triangle inequality on every block's sum). Used for the rounding
/// floor of the residual target only, where the GPU does not find the
/// exact norm itself (`refine.wgsl`'s `rounding_floor`: the host's
/// fallbacks).
fn shape_norm_bound(
    a: &IsoRingSym3,
    square: Option<&[f64]>,
    ring_abs: &[f64],
    fixed: &[bool],
) -> f64 {
    let n = a.n();
    let mut row = match square {
        Some(r) => r.to_vec(),
        None => vec![0f64; n],
    };
    add_abs_row_sums(&a.iso.col_ptr, &a.iso.row_idx, &a.iso.values, &mut row);
    let held = fixed.iter().any(|&f| f);
    (0..n)
        .filter(|&p| !fixed[p])
        .map(|p| row[p] + ring_abs[p])
        .fold(if held { 1.0 } else { 0.0 }, f64::max)
}

/// `row[p] += sum_j |A_pj|` for the symmetric matrix `A` of lower-CSC
/// `(col_ptr, row_idx, values)`.
fn add_abs_row_sums(col_ptr: &[usize], row_idx: &[usize], values: &[f64], row: &mut [f64]) {
    for j in 0..col_ptr.len().saturating_sub(1) {
        for s in col_ptr[j]..col_ptr[j + 1] {
            let i = row_idx[s];
            row[i] += values[s].abs();
            if i != j {
                row[j] += values[s].abs();
            }
        }
    }
}

/// `||C||_inf` of a symmetric 3x3 `C` stored as (xx, yy, zz, xy, xz, yz).
fn sym3_norm_inf(c: &[f64; 6]) -> f64 {
    [
        c[0].abs() + c[3].abs() + c[4].abs(),
        c[3].abs() + c[1].abs() + c[5].abs(),
        c[4].abs() + c[5].abs() + c[2].abs(),
    ]
    .into_iter()
    .fold(0.0, f64::max)
}

/// Rows of the rings per task of [`RingSlots::new`]: homer 1.2M's 600k
/// rows make 147 tasks.
const RINGS_PER_TASK: usize = 4096;

/// Where [`HostMatrix::fill_shape`] adds each ring pair: for every row `i` of
/// the rings, the lower-CSC slot of each pair `(p, q)` of its entries with
/// `p >= q`, in the order of [`SparseRows::row`] twice nested. Found once per
/// pattern and rings (binary searches), then reused by every matrix of the
/// pattern: the rings are the input's Laplacian, fixed for a run.
pub(crate) struct RingSlots {
    /// The rings the slots were found for (kept to recognise them).
    rings: Arc<SparseRows>,
    /// Per row `i`, its pairs' slots are `slot[start[i]..start[i + 1]]`.
    start: Vec<u32>,
    slot: Arc<[u32]>,
    /// Per row `i`, `sum_q |R_iq|` (for [`shape_norm_bound`]'s rings' part).
    abs_sum: Vec<f64>,
    /// The pairs per part of the lower blocks, for the parts' size it was
    /// counted for ([`Self::pairs_per_part`]).
    part_pairs: std::sync::OnceLock<(usize, Vec<usize>)>,
    /// Whether `p` is in row `i` exactly when `i` is in row `p`: then the
    /// rings' diagonal blocks are gathered per block row
    /// ([`HostMatrix::set_shape`]).
    symmetric: bool,
}

impl RingSlots {
    /// The slots of `rings`' pairs in the lower pattern `(col_ptr, row_idx)`;
    /// an error names the first pair outside it. Each pair's slot is a
    /// binary search of its column: rows in groups of [`RINGS_PER_TASK`] on
    /// rayon's threads, each group into its own part of the slots
    /// ([`solver_cpu::row_groups_mut`]). On one thread, about 0.5 s at homer
    /// 1.2M and 1.5 s at 4.3M before the first shape solve on an H200's
    /// host (inferred from the log's gap around it, not timed apart there);
    /// 0.20 s at 1.2M on the development machine, 0.11 s on its 2 threads.
    /// The same slots on any number of threads.
    ///
    /// Where `given` holds slots in that order (the matrix's own,
    /// [`IsoRingSym3::ring_slots`]), they are checked instead, a pass of
    /// two reads a pair (its column holds the slot, the slot holds its row),
    /// and shared where every one holds: the shape model's, so the host
    /// keeps one copy (67 MB at homer 1.2M). Slots that fail the check are
    /// searched for as above.
    pub fn new(
        rings: &Arc<SparseRows>,
        col_ptr: &[usize],
        row_idx: &[usize],
        given: Option<&Arc<[u32]>>,
    ) -> Result<RingSlots, SolverError> {
        let n = col_ptr.len().saturating_sub(1);
        // A row of d entries (its own included) has d (d + 1) / 2 pairs.
        let mut start = Vec::with_capacity(rings.len() + 1);
        start.push(0usize);
        for i in 0..rings.len() {
            let d = rings.start[i + 1] - rings.start[i] + 1;
            start.push(start[i] + d * (d + 1) / 2);
        }
        let total = start[rings.len()];
        if total > u32::MAX as usize {
            return Err(SolverError::DimensionMismatch(format!(
                "{total} ring pairs: more than 32-bit offsets hold"
            )));
        }
        let start_u32: Vec<u32> = start.iter().map(|&v| v as u32).collect();
        let abs_sum = || {
            (0..rings.len())
                .into_par_iter()
                .map(|i| rings.row(i).map(|(_, w)| w.abs()).sum())
                .collect()
        };
        if let Some(given) = given.filter(|g| g.len() == total) {
            let holds = |i: usize| {
                let mine = &given[start[i]..start[i + 1]];
                rings.pairs(i).zip(mine).all(|((p, q, _), &k)| {
                    let k = k as usize;
                    q < n && (col_ptr[q]..col_ptr[q + 1]).contains(&k) && row_idx[k] == p
                })
            };
            if (0..rings.len()).into_par_iter().all(holds) {
                return Ok(RingSlots {
                    rings: rings.clone(),
                    start: start_u32,
                    slot: given.clone(),
                    abs_sum: abs_sum(),
                    part_pairs: Default::default(),
                    symmetric: rings.pattern_is_symmetric(),
                });
            }
            log::warn!("the matrix's ring pair slots do not hold in its pattern: searched for");
        }
        let mut slot = vec![0u32; total];
        let groups =
            solver_cpu::row_groups_mut(&mut slot, rings.len(), |i| start[i], RINGS_PER_TASK);
        // Each group's first pair outside the pattern: the first group's
        // with one is the first of all.
        let fill = |(r, part): (std::ops::Range<usize>, &mut [u32])| -> Result<(), SolverError> {
            let mut at = 0usize;
            let first = r.start;
            for i in r {
                for (p, q, _) in rings.pairs(i) {
                    let found = (q < n)
                        .then(|| {
                            let (s, e) = (col_ptr[q], col_ptr[q + 1]);
                            row_idx[s..e].binary_search(&p).ok().map(|k| s + k)
                        })
                        .flatten();
                    let Some(k) = found else {
                        return Err(SolverError::DimensionMismatch(format!(
                            "ring pair ({p}, {q}) of row {i} is outside the matrix pattern"
                        )));
                    };
                    let Some(to) = part.get_mut(at) else {
                        return Err(SolverError::DimensionMismatch(format!(
                            "ring row {i} repeats a column"
                        )));
                    };
                    *to = k as u32;
                    at += 1;
                }
                if at != start[i + 1] - start[first] {
                    return Err(SolverError::DimensionMismatch(format!(
                        "ring row {i} repeats a column"
                    )));
                }
            }
            Ok(())
        };
        let filled: Vec<Result<(), SolverError>> = groups.into_par_iter().map(fill).collect();
        filled.into_iter().collect::<Result<(), SolverError>>()?;
        Ok(RingSlots {
            rings: rings.clone(),
            start: start_u32,
            slot: slot.into(),
            abs_sum: abs_sum(),
            part_pairs: Default::default(),
            symmetric: rings.pattern_is_symmetric(),
        })
    }

    /// Whether these slots are `given`'s (shared, not copied).
    pub fn shares(&self, given: &Arc<[u32]>) -> bool {
        Arc::ptr_eq(&self.slot, given)
    }

    /// Whether these are the slots of `rings` (the same rows, by identity).
    pub fn of(&self, rings: &Arc<SparseRows>) -> bool {
        Arc::ptr_eq(&self.rings, rings)
    }

    /// Ring pairs in all.
    #[cfg(test)]
    pub fn pairs(&self) -> usize {
        self.slot.len()
    }

    /// The pairs whose lower block is in each part of `part_blocks` lower
    /// blocks (`parts` of them, the last part all the blocks past the
    /// others): counted once for a part size.
    pub fn pairs_per_part(&self, part_blocks: usize, parts: usize) -> Vec<usize> {
        let count = || {
            let mut n = vec![0; parts];
            for &s in self.slot.iter() {
                n[(s as usize / part_blocks.max(1)).min(parts - 1)] += 1;
            }
            n
        };
        match self.part_pairs.get() {
            Some((b, n)) if *b == part_blocks && n.len() == parts => n.clone(),
            Some(_) => count(),
            None => self
                .part_pairs
                .get_or_init(|| (part_blocks, count()))
                .1
                .clone(),
        }
    }

    /// The pairs gathered by lower block (`slots` of them), for
    /// `sum_shape_blocks.wgsl`: block `s`'s pairs are `start[s]..start[s +
    /// 1]`, each with its ring and weight `R_ip R_iq`, in ring order (the
    /// order [`HostMatrix::fill_shape`] adds them in).
    pub fn by_block(&self, rings: &SparseRows, slots: usize) -> (Vec<u32>, Vec<u32>, Vec<f64>) {
        let mut ring = vec![0u32; self.slot.len()];
        let mut f = vec![0f64; self.slot.len()];
        let start = self.scatter_by_block(
            slots,
            rings.len(),
            |i| rings.pairs(i).map(move |(_, _, w)| (i as u32, w)),
            |at, (i, w)| {
                ring[at] = i;
                f[at] = w;
            },
        );
        (start, ring, f)
    }

    /// [`Self::by_block`] with each pair packed in one `u32` and no weight:
    /// `(i << 2 bits) | (a << bits) | b`, its ring `i` and the positions
    /// `a`, `b` of `p` and `q` in row `i` (the diagonal first), whose
    /// weights `R_ip R_iq` the GPU reads from [`ring_weights`]. `bits` from
    /// [`pack_bits`]: 4 bytes a pair against 12 (16.8M pairs at homer 1.2M).
    pub fn by_block_packed(
        &self,
        rings: &SparseRows,
        slots: usize,
        bits: u32,
    ) -> (Vec<u32>, Vec<u32>) {
        let mut packed = vec![0u32; self.slot.len()];
        let start = self.scatter_by_block(
            slots,
            rings.len(),
            |i| {
                rings
                    .pair_positions(i)
                    .map(move |(a, b)| ((i as u32) << (2 * bits)) | ((a as u32) << bits) | b as u32)
            },
            |at, v| packed[at] = v,
        );
        (start, packed)
    }

    /// The one pass both forms gather by: `put(at, item)` for each ring
    /// `i`'s items `pairs(i)` (one per ring pair, in the slots' order) at its
    /// place `at` among its lower block's pairs (`slots` blocks, their pairs
    /// in ring order); returns per block where its pairs start, and their
    /// end.
    fn scatter_by_block<I: Iterator>(
        &self,
        slots: usize,
        rings: usize,
        pairs: impl Fn(usize) -> I,
        mut put: impl FnMut(usize, I::Item),
    ) -> Vec<u32> {
        let mut start = vec![0u32; slots + 1];
        for &s in self.slot.iter() {
            start[s as usize + 1] += 1;
        }
        for s in 0..slots {
            start[s + 1] += start[s];
        }
        let mut next = start.clone();
        for i in 0..rings {
            let slots = &self.slot[self.start[i] as usize..self.start[i + 1] as usize];
            for (&s, item) in slots.iter().zip(pairs(i)) {
                let at = next[s as usize] as usize;
                next[s as usize] += 1;
                put(at, item);
            }
        }
        start
    }
}

/// The bits a ring pair's two positions in its row take each when packed
/// with its ring in one `u32` ([`RingSlots::by_block_packed`]): enough for
/// the longest row; `None` where the rings' count does not fit the bits
/// left (the pairs then go with their rings and weights apart).
pub(crate) fn pack_bits(rings: &SparseRows) -> Option<u32> {
    // A row's entries: its diagonal and its others (asked at every matrix,
    // so from the starts, not by walking the rows).
    let longest = rings.start.windows(2).map(|w| w[1] - w[0] + 1).max()?;
    let bits = (usize::BITS - (longest - 1).leading_zeros()).max(1);
    let ring_bits = 32u32.checked_sub(2 * bits).filter(|&b| b >= 1)?;
    (rings.len() as u64 <= 1u64 << ring_bits).then_some(bits)
}

/// Each row of `rings` as its weights, the diagonal first (the
/// coefficients [`SparseRows::row`] gives): row `i` is
/// `weights[start[i]..start[i + 1]]`. What packed ring pairs
/// ([`RingSlots::by_block_packed`]) are weighed from.
pub(crate) fn ring_weights(rings: &SparseRows) -> (Vec<u32>, Vec<f64>) {
    let mut start = Vec::with_capacity(rings.len() + 1);
    let mut weights = Vec::with_capacity(rings.len() + rings.w.len());
    start.push(0);
    for i in 0..rings.len() {
        weights.extend(rings.row(i).map(|(_, w)| w));
        start.push(weights.len() as u32);
    }
    (start, weights)
}

/// An SPD shape matrix on a strip of `n` vertices (a closed ring): rings of
/// each vertex and its two neighbours, `K` diagonally dominant on their
/// 2-ring pattern, `C_i` positive definite on most rings and zero on the
/// others; values depending on `seed`.
#[cfg(test)]
pub(crate) fn shape_strip(n: usize, seed: f64) -> IsoRingSym3 {
    let mut a = strip_pattern(n);
    for j in 0..n {
        for s in a.iso.col_ptr[j]..a.iso.col_ptr[j + 1] {
            let v = ((s as f64 + seed) * 0.37).sin();
            a.iso.values[s] = if a.iso.row_idx[s] == j {
                2.0 + seed + 0.3 * v
            } else {
                -0.1 * (1.0 + 0.3 * v)
            };
        }
    }
    for (i, c) in a.ring_c.iter_mut().enumerate() {
        if i % 5 != 3 {
            let s = (i as f64 + seed).cos();
            *c = [0.3 + 0.1 * s, 0.2, 0.4 - 0.1 * s, 0.05 * s, -0.02, 0.04];
        }
    }
    a
}

/// The zero shape matrix on a strip of `n` vertices (a closed ring): rings
/// of each vertex and its two neighbours, `K`'s pattern their 2-ring.
#[cfg(test)]
fn strip_pattern(n: usize) -> IsoRingSym3 {
    let mut t = Vec::new();
    for i in 0..n {
        for (j, w) in [(i + 1, 1.0 + 0.1 * i as f64), (i + n - 1, 0.7)] {
            t.push((i as u32, (j % n) as u32, w));
        }
    }
    let rings = Arc::new(SparseRows::from_triplets(n, t, true));
    let pairs = (0..n).flat_map(|i| [(i, (i + 1) % n), (i, (i + 2) % n)]);
    let pat = SymCsc::from_pattern(n, pairs);
    IsoRingSym3::new(n, pat.col_ptr, pat.row_idx, rings)
}

/// A Laplacian square model for `a`: rows with the columns of `a`'s rings
/// (as E_m's cotangent rows have E_l's mean-value rows' columns) and other
/// weights, `Mt` 0 at vertex 2 (a vertex outside every face).
#[cfg(test)]
pub(crate) fn square_model(a: &IsoRingSym3) -> Arc<ShapeOperatorModel> {
    let r = &a.rings;
    let w: Vec<f64> = (0..r.w.len())
        .map(|k| r.w[k] * (1.3 + 0.2 * (k as f64).sin()))
        .collect();
    let diag = (0..r.len())
        .map(|i| w[r.start[i]..r.start[i + 1]].iter().sum())
        .collect();
    let laplacian = Arc::new(SparseRows {
        start: r.start.clone(),
        idx: r.idx.clone(),
        w,
        diag,
    });
    let mt = (0..r.len())
        .map(|i| if i == 2 { 0.0 } else { 0.5 + 0.1 * i as f64 })
        .collect();
    Arc::new(ShapeOperatorModel {
        laplacian,
        mt,
        c: 0.0,
    })
}

#[cfg(test)]
mod shape_fill_tests {
    use super::*;

    /// A shape matrix on a strip of `n` vertices ([`strip_pattern`]), `C_i`
    /// nonzero on most rows (not positive definite).
    fn strip(n: usize) -> IsoRingSym3 {
        let mut a = strip_pattern(n);
        for (k, v) in a.iso.values.iter_mut().enumerate() {
            *v = 1.0 + (k as f64 * 0.37).sin();
        }
        for (i, c) in a.ring_c.iter_mut().enumerate() {
            if i % 5 != 3 {
                let s = (i as f64).cos();
                *c = [0.3 * s, -0.1, -0.2 - 0.3 * s, 0.05 * s, -0.02, 0.04];
            }
        }
        a
    }

    #[test]
    fn shape_fill_equals_the_explicit_blocks_to_the_bit() {
        let a = strip(11);
        let mut fixed = vec![false; 11];
        fixed[4] = true;
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let mut want = HostMatrix::pattern(11, 3, col_ptr, row_idx).unwrap();
        want.fill_blocks(&a.to_blocks(), &fixed);
        let slots = RingSlots::new(&a.rings, col_ptr, row_idx, None).unwrap();
        assert!(slots.of(&a.rings));
        let mut got = HostMatrix::pattern(11, 3, col_ptr, row_idx).unwrap();
        got.fill_shape(&a, &slots, &fixed).unwrap();
        assert_eq!(got.full_values(), want.full_values());
        // New values, the same slots: still equal (the first fill's lower
        // blocks, summed in place, are not added to).
        let mut b = a.clone();
        b.ring_c[2] = [1.0, 0.0, -1.0, 0.5, 0.0, 0.0];
        b.iso.values[0] += 2.0;
        want.fill_blocks(&b.to_blocks(), &fixed);
        got.fill_shape(&b, &slots, &fixed).unwrap();
        assert_eq!(got.full_values(), want.full_values());
        // Different rings (equal values, another allocation) are not these.
        let other = RingSlots::new(&Arc::new((*a.rings).clone()), col_ptr, row_idx, None).unwrap();
        assert!(!slots.of(&other.rings));
        // A Laplacian square term the matrix names: summed as `to_blocks`
        // sums it, and its values are the same through the ring slots and
        // by search (slots of other rings).
        b.laplacian_square = Some(square_model(&b));
        want.fill_blocks(&b.to_blocks(), &fixed);
        got.fill_shape(&b, &slots, &fixed).unwrap();
        assert_eq!(got.full_values(), want.full_values());
        let fast = laplacian_square_values(&b, &slots).unwrap().unwrap();
        let searched = laplacian_square_values(&b, &other).unwrap().unwrap();
        assert_eq!(fast, searched);
        assert!(fast.iter().filter(|v| **v != 0.0).count() > 11);
        // Without the term's values the sum differs.
        b.laplacian_square = None;
        want.fill_blocks(&b.to_blocks(), &fixed);
        assert_ne!(got.full_values(), want.full_values());
    }

    /// Every full block is the lower block, its transpose above the
    /// diagonal, or the identity / zero in a held vertex's row or column,
    /// found here by row and column; a second fill with other held vertices
    /// follows them.
    #[test]
    fn fill_writes_each_block_from_its_source_for_the_held_vertices_given() {
        let a = strip(11);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        // Off-diagonal blocks made unsymmetric, so that a block copied
        // where its transpose belongs shows.
        let mut blocks = a.to_blocks();
        for j in 0..11 {
            for k in col_ptr[j] + 1..col_ptr[j + 1] {
                blocks.blocks[k][1] += 0.25 + k as f64;
            }
        }
        let lower = |i: usize, j: usize| -> [f64; 9] {
            let k = (col_ptr[j]..col_ptr[j + 1])
                .find(|&k| row_idx[k] == i)
                .expect("(i, j) in the lower pattern");
            blocks.blocks[k]
        };
        let mut h = HostMatrix::pattern(11, 3, col_ptr, row_idx).unwrap();
        for held in [vec![4usize], vec![0, 7, 10]] {
            let mut fixed = vec![false; 11];
            held.iter().for_each(|&v| fixed[v] = true);
            h.fill_blocks(&blocks, &fixed);
            for i in 0..11 {
                for f in h.row_ptr[i] as usize..h.row_ptr[i + 1] as usize {
                    let j = h.col_idx[f] as usize;
                    let want: [f64; 9] = match (fixed[i] || fixed[j], i >= j) {
                        (true, _) if i == j => [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                        (true, _) => [0.0; 9],
                        (false, true) => lower(i, j),
                        (false, false) => {
                            let b = lower(j, i);
                            std::array::from_fn(|e| b[3 * (e % 3) + e / 3])
                        }
                    };
                    assert_eq!(h.block_values(f), want, "held {held:?}, block ({i}, {j})");
                }
            }
        }
    }

    /// A released map costs the host nothing until asked for, and is then
    /// made again the same, for the held vertices of the last fill: new
    /// held vertices give another.
    #[test]
    fn a_released_map_is_made_again_when_asked_for() {
        let a = strip(11);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let blocks = a.to_blocks();
        let mut h = HostMatrix::pattern(11, 3, col_ptr, row_idx).unwrap();
        let mut fixed = vec![false; 11];
        fixed[3] = true;
        h.fill_blocks(&blocks, &fixed);
        let map = h.map().to_vec();
        let values: Vec<[f64; 9]> = (0..h.nnz_blocks()).map(|k| h.block_values(k)).collect();
        let held = h.host_bytes();
        h.release_map();
        assert!(!h.map_held());
        assert_eq!(held - h.host_bytes(), 4 * map.len());
        assert_eq!(h.map(), &map[..]);
        h.release_map();
        let again: Vec<[f64; 9]> = (0..h.nnz_blocks()).map(|k| h.block_values(k)).collect();
        assert_eq!(again, values);
        // Read on rayon's threads right after a release: made first, once.
        let (full, norm) = (h.full_values(), h.norm_inf());
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap();
        for _ in 0..3 {
            h.release_map();
            h.norm = OnceLock::new();
            let read = pool.install(|| (h.full_values(), h.norm_inf()));
            assert_eq!(read, (full.clone(), norm));
        }
        fixed[3] = false;
        fixed[8] = true;
        h.fill_blocks(&blocks, &fixed);
        assert_ne!(h.map(), &map[..], "the map of other held vertices");
    }

    /// A scalar matrix's every stored value, on both triangles, is its lower
    /// entry's, found here by row and column.
    #[test]
    fn scalar_fill_writes_each_value_from_its_lower_entry() {
        let a = strip(11);
        let mut k = a.iso.clone();
        for (e, v) in k.values.iter_mut().enumerate() {
            *v = 1.0 + e as f64;
        }
        let (col_ptr, row_idx) = (&k.col_ptr, &k.row_idx);
        let mut h = HostMatrix::pattern(11, 1, col_ptr, row_idx).unwrap();
        h.fill_scalar(&k);
        assert_eq!(h.lower_len(), row_idx.len());
        for i in 0..11 {
            for f in h.row_ptr[i] as usize..h.row_ptr[i + 1] as usize {
                let j = h.col_idx[f] as usize;
                let (r, c) = (i.max(j), i.min(j));
                let e = (col_ptr[c]..col_ptr[c + 1])
                    .find(|&e| row_idx[e] == r)
                    .expect("(r, c) in the lower pattern");
                assert_eq!(h.block_values(f)[0], k.values[e], "({i}, {j})");
            }
        }
    }

    /// The mixed-precision matrix's scalar inverse diagonal, written
    /// straight into the queue's staging memory for each new set of values,
    /// is `1 / a_ii` of those values, in row order, to the bit.
    #[test]
    fn split_inverse_diagonal_follows_each_set_of_values() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let a = strip(11);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let mut h = HostMatrix::pattern(11, 3, col_ptr, row_idx).unwrap();
        let fixed = vec![false; 11];
        let mut blocks = a.to_blocks();
        // Diagonally dominant blocks: each diagonal entry its own value.
        for (j, &first) in col_ptr[..11].iter().enumerate() {
            // The diagonal block comes first in its column.
            let d = &mut blocks.blocks[first];
            for (q, e) in [0, 4, 8].into_iter().enumerate() {
                d[e] = 50.0 + (j * 3 + q) as f64;
            }
        }
        h.fill_blocks(&blocks, &fixed);
        let mut minv = Vec::new();
        crate::block_jacobi::inverse_diagonal(&h, &mut minv).unwrap();
        let f32_matrix = GpuMatrix::upload(ctx, &h, Some(&minv), true).unwrap();
        let split = GpuMatrix::upload_split_f64(ctx, &h, &f32_matrix, true, true).unwrap();
        let read = |m: &GpuMatrix| ctx.read::<f64>(&m.minv, 33, &mut None, None).unwrap();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&read(&split)), bits(&split_inverse_diagonal(&h)));
        blocks.blocks.iter_mut().flatten().for_each(|v| *v *= 3.0);
        h.fill_blocks(&blocks, &fixed);
        split.write_diagonal(ctx, &h, &[]);
        let now = read(&split);
        assert_eq!(bits(&now), bits(&split_inverse_diagonal(&h)));
        assert_eq!(now[4], 1.0 / (3.0 * 54.0));
    }

    /// `norm_inf` is kept between solves of one set of values and follows
    /// every new fill (scaled values, then other held vertices).
    #[test]
    fn norm_follows_each_fill() {
        let a = strip(11);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let mut h = HostMatrix::pattern(11, 3, col_ptr, row_idx).unwrap();
        let fixed = vec![false; 11];
        let mut blocks = a.to_blocks();
        h.fill_blocks(&blocks, &fixed);
        let n1 = h.norm_inf();
        assert!(n1 > 1.0, "{n1}");
        assert_eq!(h.norm_inf(), n1);
        blocks.blocks.iter_mut().flatten().for_each(|v| *v *= 3.0);
        h.fill_blocks(&blocks, &fixed);
        assert!(
            (h.norm_inf() - 3.0 * n1).abs() <= 1e-12 * n1,
            "{} against {}",
            h.norm_inf(),
            3.0 * n1
        );
        // Every vertex held: the identity.
        h.fill_blocks(&blocks, &[true; 11]);
        assert_eq!(h.norm_inf(), 1.0);
    }

    /// A shape matrix kept in its form answers as its summed blocks do:
    /// the same diagonal blocks (to the bit), the same residuals (to
    /// rounding), the lower blocks summed when asked for, and a norm bound
    /// at least the norm (and within the triangle inequality's slack).
    #[test]
    fn shape_form_answers_as_its_blocks() {
        let n = 23;
        let plain = shape_strip(n, 0.3);
        let mut named = plain.clone();
        named.laplacian_square = Some(square_model(&plain));
        let (col_ptr, row_idx) = (&plain.iso.col_ptr, &plain.iso.row_idx);
        let slots = Arc::new(RingSlots::new(&plain.rings, col_ptr, row_idx, None).unwrap());
        let cases = [vec![], vec![4usize, 11]]
            .into_iter()
            .flat_map(|held| [(held.clone(), &plain), (held, &named)]);
        // One matrix through every case, its form taken back between them
        // (the solver's way: the next set-up refills the last one's
        // vectors), against a fresh one each time.
        let mut reused = HostMatrix::pattern(n, 3, col_ptr, row_idx).unwrap();
        for (held, a) in cases {
            let mut fixed = vec![false; n];
            held.iter().for_each(|&v| fixed[v] = true);
            let mut blocks = HostMatrix::pattern(n, 3, col_ptr, row_idx).unwrap();
            blocks.fill_shape(a, &slots, &fixed).unwrap();
            let mut form = HostMatrix::pattern(n, 3, col_ptr, row_idx).unwrap();
            let square = laplacian_square_values(a, &slots).unwrap().map(|v| {
                let model = a.laplacian_square.clone().unwrap();
                Arc::new(SquareParts::new(model, a, &v))
            });
            reused.take_shape();
            reused.set_shape(a.clone(), slots.clone(), &fixed, square.clone());
            form.set_shape(a.clone(), slots.clone(), &fixed, square);
            assert!(form.is_filled() && form.shape_form().is_some());
            assert_eq!(reused.norm_inf().to_bits(), form.norm_inf().to_bits());
            for v in 0..n {
                assert_eq!(reused.diag_block(v), form.diag_block(v));
            }
            // The form holds diagonal blocks, not the lower ones.
            let lower = blocks.lower_len();
            assert!(
                blocks.host_bytes() >= form.host_bytes() + 72 * (lower - n),
                "{} against {}",
                blocks.host_bytes(),
                form.host_bytes()
            );
            for v in 0..n {
                assert_eq!(
                    form.diag_block(v),
                    blocks.diag_block(v),
                    "held {held:?}, vertex {v}"
                );
            }
            let x: Vec<f64> = (0..6 * n).map(|i| (i as f64 * 0.71).sin()).collect();
            let b: Vec<f64> = (0..6 * n).map(|i| (i as f64 * 0.13).cos()).collect();
            let (mut r1, mut r2) = (vec![0.0; 6 * n], vec![0.0; 6 * n]);
            blocks.residual(&b, &x, &mut r1, 2);
            form.residual(&b, &x, &mut r2, 2);
            for (u, v) in r1.iter().zip(&r2) {
                assert!((u - v).abs() <= 1e-13 * (1.0 + u.abs()), "{u} vs {v}");
            }
            let (exact, bound) = (blocks.norm_inf(), form.norm_inf());
            assert!(bound >= exact && bound <= 4.0 * exact, "{bound} vs {exact}");
            assert_eq!(form.full_values(), blocks.full_values());
        }
        let mut form = HostMatrix::pattern(n, 3, col_ptr, row_idx).unwrap();
        form.set_shape(plain.clone(), slots, &[false; 23], None);
        assert_eq!(form.take_shape().unwrap().iso.values, plain.iso.values);
        assert!(!form.is_filled());
    }

    /// The pairs gathered by lower block carry every ring pair once, with
    /// its ring and weight, in ring order within each block.
    #[test]
    fn pairs_by_block_are_the_slots_inverted() {
        let n = 17;
        let a = shape_strip(n, 0.0);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let slots = RingSlots::new(&a.rings, col_ptr, row_idx, None).unwrap();
        let nnz = row_idx.len();
        let (start, ring, f) = slots.by_block(&a.rings, nnz);
        assert_eq!(start.len(), nnz + 1);
        assert_eq!(start[nnz] as usize, slots.pairs());
        let mut want: Vec<Vec<(u32, f64)>> = vec![Vec::new(); nnz];
        for i in 0..n {
            let mut t = slots.slot[slots.start[i] as usize..slots.start[i + 1] as usize].iter();
            for (p, wp) in a.rings.row(i) {
                for (q, wq) in a.rings.row(i) {
                    if p >= q {
                        let s = *t.next().unwrap() as usize;
                        // The slot is block (p, q) of the lower pattern.
                        assert_eq!(row_idx[s], p);
                        assert!((col_ptr[q]..col_ptr[q + 1]).contains(&s));
                        want[s].push((i as u32, wp * wq));
                    }
                }
            }
        }
        for s in 0..nnz {
            let got: Vec<(u32, f64)> = (start[s]..start[s + 1])
                .map(|t| (ring[t as usize], f[t as usize]))
                .collect();
            assert_eq!(got, want[s], "block {s}");
        }
    }

    /// Packed by block, each pair names the ring and, by its positions in
    /// the ring's row, the weights whose product is the pair's weight as
    /// gathered unpacked, the same bits, in the same order.
    #[test]
    fn packed_pairs_by_block_are_the_weighed_ones() {
        let n = 17;
        let a = shape_strip(n, 0.0);
        let slots = RingSlots::new(&a.rings, &a.iso.col_ptr, &a.iso.row_idx, None).unwrap();
        let nnz = a.iso.row_idx.len();
        let bits = pack_bits(&a.rings).unwrap();
        // Rows of 3 (the diagonal and two neighbours): 2 bits a position.
        assert_eq!(bits, 2);
        let (start, ring, f) = slots.by_block(&a.rings, nnz);
        let (start_p, packed) = slots.by_block_packed(&a.rings, nnz, bits);
        assert_eq!(start, start_p);
        let (row_start, weights) = ring_weights(&a.rings);
        assert_eq!(row_start.len(), n + 1);
        for (t, &v) in packed.iter().enumerate() {
            let i = (v >> (2 * bits)) as usize;
            let (p, q) = ((v >> bits) & 3, v & 3);
            let r = row_start[i] as usize;
            assert_eq!(i as u32, ring[t], "pair {t}");
            assert!(p < 3 && q < 3 && r + 3 == row_start[i + 1] as usize);
            assert_eq!(
                (weights[r + p as usize] * weights[r + q as usize]).to_bits(),
                f[t].to_bits()
            );
        }
    }

    /// Positions take the bits of the longest row; rings too many for the
    /// bits left are not packed.
    #[test]
    fn pair_packing_fits_the_longest_row_and_the_rings() {
        // `rows` rings, the first of `len` entries (the diagonal and
        // `len - 1` others), the rest of 2.
        let rings = |rows: u32, len: u32| {
            let mut t: Vec<_> = (1..len).map(|j| (0, j, 1.0)).collect();
            t.extend((1..rows).map(|i| (i, 0, 1.0)));
            SparseRows::from_triplets(rows as usize, t, true)
        };
        assert_eq!(pack_bits(&rings(5, 2)), Some(1));
        assert_eq!(pack_bits(&rings(5, 4)), Some(2));
        assert_eq!(pack_bits(&rings(5, 5)), Some(3));
        assert_eq!(pack_bits(&rings(5, 16)), Some(4));
        assert_eq!(pack_bits(&rings(5, 17)), Some(5));
        // 2^15 entries: 15 bits each, 2 left for the ring (4 rings).
        assert_eq!(pack_bits(&rings(4, 1 << 15)), Some(15));
        assert_eq!(pack_bits(&rings(5, 1 << 15)), None);
        assert_eq!(pack_bits(&rings(4, (1 << 15) + 1)), None);
        assert_eq!(
            pack_bits(&SparseRows::from_triplets(0, Vec::new(), true)),
            None
        );
    }

    /// Each ring pair's slot is the pattern entry `(p, q)`, row after row in
    /// the pairs' order, the same on any number of threads, over rows in
    /// several tasks.
    #[test]
    fn ring_slots_are_the_pairs_entries_on_any_number_of_threads() {
        let n = 2 * RINGS_PER_TASK + 77;
        let a = strip_pattern(n);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let mut want = Vec::new();
        for i in 0..n {
            for (p, q, _) in a.rings.pairs(i) {
                let s = (col_ptr[q]..col_ptr[q + 1])
                    .find(|&k| row_idx[k] == p)
                    .unwrap();
                want.push(s as u32);
            }
        }
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let slots = pool.install(|| RingSlots::new(&a.rings, col_ptr, row_idx, None).unwrap());
            assert_eq!(&*slots.slot, &want[..], "{threads} threads");
            assert_eq!(slots.start.len(), n + 1);
            for i in 0..n {
                let pairs = a.rings.pairs(i).count() as u32;
                assert_eq!(slots.start[i + 1] - slots.start[i], pairs, "row {i}");
            }
        }
    }

    /// Slots the matrix brings are shared where each holds, and searched for
    /// where one does not or their count is wrong.
    #[test]
    fn given_ring_slots_are_taken_where_they_hold() {
        let n = 2 * RINGS_PER_TASK + 17;
        let a = strip_pattern(n);
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let searched = RingSlots::new(&a.rings, col_ptr, row_idx, None).unwrap();
        let given: Arc<[u32]> = searched.slot.to_vec().into();
        let taken = RingSlots::new(&a.rings, col_ptr, row_idx, Some(&given)).unwrap();
        assert!(taken.shares(&given));
        assert_eq!(taken.start, searched.start);
        assert_eq!(taken.abs_sum, searched.abs_sum);
        // One slot moved to its column's next entry (still inside the
        // pattern, the wrong row), in a late task: searched for.
        let mut wrong = searched.slot.to_vec();
        let k = searched.start[n - 3] as usize + 1;
        wrong[k] += 1;
        let wrong: Arc<[u32]> = wrong.into();
        let fixed = RingSlots::new(&a.rings, col_ptr, row_idx, Some(&wrong)).unwrap();
        assert!(!fixed.shares(&wrong));
        assert_eq!(&*fixed.slot, &*searched.slot);
        let short: Arc<[u32]> = searched.slot[1..].to_vec().into();
        let fixed = RingSlots::new(&a.rings, col_ptr, row_idx, Some(&short)).unwrap();
        assert!(!fixed.shares(&short));
        assert_eq!(&*fixed.slot, &*searched.slot);
    }

    /// Of several rows with pairs outside the pattern, in different tasks,
    /// the error names the first.
    #[test]
    fn the_first_ring_pair_outside_the_pattern_is_named() {
        let n = 3 * RINGS_PER_TASK;
        let a = strip_pattern(n);
        // Without the pair (i, i+2) of rows i + 1 = 5000 and 10000: the
        // second off-diagonal entry of columns 4999 and 9999.
        let drop = [4999, 9999];
        let pairs = (0..n).flat_map(|i| [(i, (i + 1) % n), (i, (i + 2) % n)]);
        let kept = pairs.filter(|&(i, j)| !(drop.contains(&i) && j == (i + 2) % n));
        let pat = SymCsc::from_pattern(n, kept);
        let e = RingSlots::new(&a.rings, &pat.col_ptr, &pat.row_idx, None).err();
        let Some(SolverError::DimensionMismatch(m)) = e else {
            panic!("{e:?}");
        };
        assert!(m.contains("of row 5000 "), "{m}");
    }

    #[test]
    fn ring_pairs_outside_the_pattern_are_an_error() {
        let a = strip(9);
        // The pattern of K without its second off-diagonals: (i, i+2) pairs
        // of the rings fall outside.
        let pat = SymCsc::from_pattern(9, (0..9).map(|i| (i, (i + 1) % 9)));
        let e = RingSlots::new(&a.rings, &pat.col_ptr, &pat.row_idx, None).err();
        assert!(
            matches!(&e, Some(SolverError::DimensionMismatch(m)) if m.contains("outside the matrix pattern")),
            "{e:?}"
        );
    }
}

/// The f32 copy on the GPU.
pub(crate) struct GpuMatrix {
    pub row_ptr: wgpu::Buffer,
    pub storage: MatrixStorage,
    pub minv: wgpu::Buffer,
    /// Bytes one product reads of the matrix as stored (row pointers
    /// included), and in its least storage at its precision
    /// ([`crate::KernelWork`]).
    pub stored: (u64, u64),
}

/// [`GpuMatrix::stored`] for `entries` stored entries (blocks of `bs x bs`)
/// of `value_bytes` each and `rows` (block) rows: every layout stores one
/// value per entry and one u32 column per block, so the bytes as stored are
/// the least bytes.
fn stored_bytes(rows: usize, entries: usize, bs: u64, value_bytes: u64) -> (u64, u64) {
    let (rows, entries) = (rows as u64, entries as u64);
    let least = entries * (bs * bs * value_bytes + 4) + 4 * (rows + 1);
    (least, least)
}

/// Where the stored entries live.
pub(crate) enum MatrixStorage {
    /// Scalar matrices (`bs` = 1): column indices and values in two buffers.
    Csr {
        col_idx: wgpu::Buffer,
        vals: wgpu::Buffer,
    },
    /// 3x3 blocks in storage buffers, split by block rows into [`Chunk`]s
    /// that each fit one storage binding: per block its 9 f32 values
    /// (row-major, 36 bytes) and its u32 block column (4 bytes). One
    /// [`ChunkParams`] uniform per chunk.
    Blocks {
        chunks: Vec<Chunk>,
        uniforms: Vec<wgpu::Buffer>,
    },
    /// 3x3 blocks in f64 as two f32 parts, `hi = f32(v)` (the f32 matrix's
    /// own value buffers, shared, with its columns and uniforms) and
    /// `lo = f32(v - hi)` in buffers of the same chunks: the f64 product of
    /// the mixed-precision solve (`bsr_spmv_f64.wgsl`).
    SplitBlocks {
        hi: Vec<Chunk>,
        lo: Vec<wgpu::Buffer>,
        uniforms: Vec<wgpu::Buffer>,
    },
}

/// A range of block rows of a block-CSR matrix with its blocks in storage
/// buffers: `cols` (one u32 per block) and `vals` (`per_block` f32 per block,
/// row-major), block `k` of the matrix at `k - blocks.start`. The row
/// pointers stay global (one buffer for the matrix).
#[derive(Clone)]
pub(crate) struct Chunk {
    pub rows: std::ops::Range<usize>,
    pub blocks: std::ops::Range<usize>,
    pub cols: wgpu::Buffer,
    pub vals: wgpu::Buffer,
}

/// The uniform of one chunk's product (`C` in `bsr_spmv.wgsl`): its block
/// rows `row0..row1`, the partial-sum slot of its first workgroup, and its
/// first block (subtracted from the global row pointers).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ChunkParams {
    pub row0: u32,
    pub row1: u32,
    pub group0: u32,
    pub block0: u32,
}

/// The largest storage binding a chunk may take: the binding limit and the
/// buffer limit, rounded down to 4 bytes.
pub(crate) fn binding_limit(ctx: &Context) -> u64 {
    let l = &ctx.limits;
    l.max_storage_buffer_binding_size.min(l.max_buffer_size) / 4 * 4
}

/// A chunk's block rows and its blocks.
pub(crate) type RowsAndBlocks = (std::ops::Range<usize>, std::ops::Range<usize>);

/// Split the block rows of `row_ptr` into ranges `(rows, blocks)` whose
/// values (`block_bytes` per block) fit `limit` bytes: greedy, as many whole
/// rows per chunk as fit. One chunk when the whole matrix fits. A single
/// block row over the limit is a [`GpuError::LimitExceeded`] naming
/// `max_storage_buffer_binding_size`.
pub(crate) fn split_rows(
    what: &str,
    row_ptr: &[u32],
    block_bytes: u64,
    limit: u64,
) -> Result<Vec<RowsAndBlocks>, GpuError> {
    let rows = row_ptr.len() - 1;
    let max_blocks = (limit / block_bytes.max(1)) as usize;
    let mut out = Vec::new();
    let mut r0 = 0;
    while r0 < rows || out.is_empty() {
        let k0 = row_ptr[r0] as usize;
        // The last row end r1 with row_ptr[r1] - k0 <= max_blocks.
        let end = row_ptr[r0..].partition_point(|&p| p as usize - k0 <= max_blocks) + r0 - 1;
        let r1 = end.min(rows);
        if r1 == r0 && r0 < rows {
            let blocks = (row_ptr[r0 + 1] - row_ptr[r0]) as u64;
            return Err(GpuError::LimitExceeded {
                what: format!("{what}: block row {r0} of {blocks} blocks of {block_bytes} bytes"),
                limit_name: "max_storage_buffer_binding_size",
                needed: blocks * block_bytes,
                limit,
            });
        }
        out.push((r0..r1, k0..row_ptr[r1] as usize));
        r0 = r1;
    }
    Ok(out)
}

/// Where the values of an upload are read: a flat array (`per_block` f64
/// values per block), or a prepared host matrix, whose blocks come from its
/// lower triangle as they are written.
#[derive(Clone, Copy)]
pub(crate) enum Values<'a> {
    Flat(&'a [f64]),
    Host(&'a HostMatrix),
    /// None now: the GPU's expansion writes them.
    Later,
}

impl Values<'_> {
    /// `part` of the values of blocks `blocks` (`per_block` each), appended
    /// to `out`.
    fn band(
        self,
        per_block: usize,
        blocks: std::ops::Range<usize>,
        part: fn(f64) -> f32,
        out: &mut Vec<f32>,
    ) {
        match self {
            Values::Flat(v) => out.par_extend(
                v[per_block * blocks.start..per_block * blocks.end]
                    .par_iter()
                    .map(|&x| part(x)),
            ),
            Values::Host(h) => h.values_into(blocks, part, out),
            Values::Later => {}
        }
    }
}

/// Upload a block-CSR matrix (`per_block` values per block in `vals`) as
/// chunks that each fit one storage binding, the values as `f32` through
/// `part` (`hi`: `v as f32`).
pub(crate) fn upload_chunks(
    ctx: &Context,
    what: &str,
    row_ptr: &[u32],
    col_idx: &[u32],
    per_block: usize,
    vals: Values<'_>,
) -> Result<Vec<Chunk>, GpuError> {
    let ranges = split_rows(what, row_ptr, 4 * per_block as u64, binding_limit(ctx))?;
    let mut chunks = Vec::with_capacity(ranges.len());
    for (i, (rows, blocks)) in ranges.into_iter().enumerate() {
        let part = |p: &str| format!("{what} {p}, chunk {i} (block rows {rows:?})");
        let vals_buf = ctx.storage(&part("values"), (4 * per_block * blocks.len()) as u64)?;
        let cols = ctx.storage_init(&part("block columns"), &col_idx[blocks.clone()])?;
        chunks.push(Chunk {
            rows,
            blocks,
            cols,
            vals: vals_buf,
        });
    }
    write_chunk_values(ctx, &chunks, per_block, vals, high_part);
    Ok(chunks)
}

/// `f32(v)`, the high part of an f64 value.
pub(crate) fn high_part(v: f64) -> f32 {
    v as f32
}

/// `f32(v - f64(f32(v)))`, the low part: with [`high_part`], `hi + lo`
/// equals `v` to a relative 2^-48.
pub(crate) fn low_part(v: f64) -> f32 {
    (v - (v as f32) as f64) as f32
}

/// Write `part(v)` of the values into `bufs` (one per chunk, the chunks'
/// value buffers or the low parts), a band of at most 4M values at a time so
/// the host holds no full f32 copy of the matrix.
pub(crate) fn write_chunk_parts(
    ctx: &Context,
    chunks: &[Chunk],
    bufs: &[&wgpu::Buffer],
    per_block: usize,
    vals: Values<'_>,
    part: fn(f64) -> f32,
) {
    if let Values::Later = vals {
        return;
    }
    let band = ((1 << 22) / per_block.max(1)).max(1);
    let mut out: Vec<f32> = Vec::new();
    for (c, buf) in chunks.iter().zip(bufs) {
        for start in c.blocks.clone().step_by(band) {
            let end = (start + band).min(c.blocks.end);
            out.clear();
            vals.band(per_block, start..end, part, &mut out);
            let at = 4 * per_block * (start - c.blocks.start);
            ctx.write_buffer(buf, at as u64, bytemuck::cast_slice(&out));
        }
    }
}

/// [`write_chunk_parts`] into the chunks' own value buffers.
pub(crate) fn write_chunk_values(
    ctx: &Context,
    chunks: &[Chunk],
    per_block: usize,
    vals: Values<'_>,
    part: fn(f64) -> f32,
) {
    let bufs: Vec<&wgpu::Buffer> = chunks.iter().map(|c| &c.vals).collect();
    write_chunk_parts(ctx, chunks, &bufs, per_block, vals, part);
}

/// Workgroups of 128 block rows each chunk's product runs, and their total:
/// the partial-sum slots a chunked product writes (chunk `i`'s first slot is
/// the sum of the counts before it).
pub(crate) fn chunk_groups(chunks: &[Chunk]) -> Vec<u32> {
    let wg = crate::device::ROW_WG as usize;
    chunks
        .iter()
        .map(|c| c.rows.len().div_ceil(wg).max(1) as u32)
        .collect()
}

/// One [`ChunkParams`] uniform per chunk.
fn chunk_uniforms(ctx: &Context, chunks: &[Chunk]) -> Result<Vec<wgpu::Buffer>, GpuError> {
    let mut group0 = 0;
    chunks
        .iter()
        .zip(chunk_groups(chunks))
        .map(|(c, g)| {
            let p = ChunkParams {
                row0: c.rows.start as u32,
                row1: c.rows.end as u32,
                group0,
                block0: c.blocks.start as u32,
            };
            group0 += g;
            ctx.uniform_of("block matrix chunk params", &p)
        })
        .collect()
}

/// The scalar inverse diagonal `1 / a_ii` of a 3x3 block matrix.
fn split_inverse_diagonal(h: &HostMatrix) -> Vec<f64> {
    split_inverse_values(h).collect()
}

/// The values of [`split_inverse_diagonal`], in order.
fn split_inverse_values(h: &HostMatrix) -> impl Iterator<Item = f64> + '_ {
    h.make_diagonal();
    (0..3 * h.rows).map(|r| 1.0 / h.diag_block(r / 3)[4 * (r % 3)])
}

/// [`split_inverse_diagonal`] into `buffer` (from 0), written straight into
/// the queue's staging memory: the matrix's every new set of values writes
/// it (24 bytes a block row, 14 MB at 1.2M faces), and a vector of it would
/// be faulted in page by page each time.
fn write_split_inverse_diagonal(ctx: &Context, buffer: &wgpu::Buffer, h: &HostMatrix) {
    ctx.write_buffer_with(buffer, 24 * h.rows as u64, |view| {
        view.into_chunks::<8>()
            .0
            .write_iter(split_inverse_values(h).map(f64::to_ne_bytes));
    });
}

impl GpuMatrix {
    /// The matrix `h` with the inverse diagonal `minv` (`None`: zeros, for
    /// a kind whose preconditioner reads none until it is written); a
    /// block matrix's values are written from `h` when `write`, else left
    /// for the GPU's expansion.
    pub fn upload(
        ctx: &Context,
        h: &HostMatrix,
        minv: Option<&[f32]>,
        write: bool,
    ) -> Result<GpuMatrix, GpuError> {
        let storage = if h.bs == 3 {
            let chunks = upload_chunks(
                ctx,
                "block matrix",
                &h.row_ptr,
                &h.col_idx,
                9,
                if write {
                    Values::Host(h)
                } else {
                    Values::Later
                },
            )?;
            MatrixStorage::Blocks {
                uniforms: chunk_uniforms(ctx, &chunks)?,
                chunks,
            }
        } else {
            // Check every size first so the error names the first buffer over a limit.
            ctx.check_storage(
                &format!("scalar matrix values ({} entries of f32)", h.nnz_blocks()),
                (h.nnz_blocks() * 4) as u64,
            )?;
            ctx.check_storage("scalar matrix column indices", (h.col_idx.len() * 4) as u64)?;
            let vals32: Vec<f32> = h.vals.iter().map(|&v| v as f32).collect();
            MatrixStorage::Csr {
                col_idx: ctx.storage_init("matrix column indices", &h.col_idx)?,
                vals: ctx.storage_init("matrix values", &vals32)?,
            }
        };
        let minv = match minv {
            Some(minv) => ctx.storage_init("inverted diagonal blocks", minv)?,
            None => ctx.storage(
                "inverted diagonal blocks (not yet written)",
                4 * (h.rows * h.bs * h.bs).max(1) as u64,
            )?,
        };
        Ok(GpuMatrix {
            row_ptr: ctx.storage_init("matrix row pointers", &h.row_ptr)?,
            storage,
            minv,
            stored: stored_bytes(h.rows, h.nnz_blocks(), h.bs as u64, 4),
        })
    }

    /// Partial-sum slots (workgroups) the product writes per column: one per
    /// 128 rows, per chunk for a block matrix.
    pub fn partial_slots(&self, rows: usize) -> u64 {
        match &self.storage {
            MatrixStorage::Csr { .. } => (rows as u64).div_ceil(crate::device::ROW_WG as u64),
            MatrixStorage::Blocks { chunks, .. }
            | MatrixStorage::SplitBlocks { hi: chunks, .. } => {
                chunk_groups(chunks).iter().map(|&g| g as u64).sum()
            }
        }
        .max(1)
    }

    /// The host matrix as scalar CSR (every `bs x bs` block as `bs^2` entries)
    /// with its inverted diagonal, in `precision`: the f64 SpMV of the
    /// mixed-precision solve and the precision comparison.
    pub fn upload_scalar(
        ctx: &Context,
        h: &HostMatrix,
        precision: Precision,
    ) -> Result<GpuMatrix, GpuError> {
        let (row_ptr, col_idx, vals, dinv) = h.scalar_expansion();
        let fp = precision.bytes();
        ctx.check_storage(
            &format!(
                "scalar matrix values ({} entries of {precision:?})",
                vals.len()
            ),
            vals.len() as u64 * fp,
        )?;
        ctx.check_storage("scalar matrix column indices", col_idx.len() as u64 * 4)?;
        Ok(GpuMatrix {
            row_ptr: ctx.storage_init("scalar expansion row pointers", &row_ptr)?,
            storage: MatrixStorage::Csr {
                col_idx: ctx.storage_init("scalar expansion column indices", &col_idx)?,
                vals: ctx.storage_init("scalar expansion values", &precision.encode(&vals))?,
            },
            minv: ctx.storage_init(
                "scalar expansion inverse diagonal",
                &precision.encode(&dinv),
            )?,
            stored: stored_bytes(row_ptr.len() - 1, col_idx.len(), 1, fp),
        })
    }

    /// The f64 block matrix of the mixed-precision solve: the f32 matrix
    /// `f32_matrix`'s value buffers as the high parts (with its columns, row
    /// pointers and chunk uniforms), new buffers of the low parts
    /// (`v - f64(f32(v))` rounded to f32, so `hi + lo` carries 48 bits) in
    /// the same chunks, and the scalar inverse diagonal in f64 (from `h`
    /// where `diagonal`, else zeros until written). The low parts are
    /// written from `h` when `write`, else left for the GPU's expansion.
    pub fn upload_split_f64(
        ctx: &Context,
        h: &HostMatrix,
        f32_matrix: &GpuMatrix,
        write: bool,
        diagonal: bool,
    ) -> Result<GpuMatrix, GpuError> {
        let MatrixStorage::Blocks { chunks, uniforms } = &f32_matrix.storage else {
            return Err(GpuError::Backend(
                "the f64 block product needs the f32 block matrix".into(),
            ));
        };
        assert_eq!(h.bs, 3);
        let lo = chunks
            .iter()
            .enumerate()
            .map(|(i, c)| {
                ctx.storage(
                    &format!(
                        "f64 block matrix, low parts, chunk {i} ({} blocks)",
                        c.blocks.len()
                    ),
                    (36 * c.blocks.len()) as u64,
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        if write {
            write_chunk_parts(
                ctx,
                chunks,
                &lo.iter().collect::<Vec<_>>(),
                9,
                Values::Host(h),
                low_part,
            );
        }
        let (rows, blocks) = (h.rows as u64, h.nnz_blocks() as u64);
        let minv = match diagonal {
            true => ctx.storage_init(
                "scalar inverse diagonal (f64)",
                &Precision::F64.encode(&split_inverse_diagonal(h)),
            )?,
            false => ctx.storage(
                "scalar inverse diagonal (f64, not yet written)",
                (24 * rows).max(8),
            )?,
        };
        // hi and lo, 36 bytes each, are the 72 bytes of the f64 values: the
        // least storage at f64.
        let stored = blocks * (36 + 36 + 4) + 4 * (rows + 1);
        Ok(GpuMatrix {
            row_ptr: f32_matrix.row_ptr.clone(),
            storage: MatrixStorage::SplitBlocks {
                hi: chunks.clone(),
                lo,
                uniforms: uniforms.clone(),
            },
            stored: (stored, stored_bytes(h.rows, h.nnz_blocks(), 3, 8).1),
            minv,
        })
    }

    /// The chunks' uniforms ([`ChunkParams`]) of a block matrix (none for a
    /// scalar one).
    pub fn chunk_uniforms(&self) -> &[wgpu::Buffer] {
        match &self.storage {
            MatrixStorage::Csr { .. } => &[],
            MatrixStorage::Blocks { uniforms, .. } => uniforms,
            MatrixStorage::SplitBlocks { uniforms, .. } => uniforms,
        }
    }

    /// The value storage of a block matrix: its chunks (the f32 values, or the
    /// high parts) and, for the f64 split matrix, the low parts' buffers.
    pub fn block_parts(&self) -> Option<(&[Chunk], Option<&[wgpu::Buffer]>)> {
        match &self.storage {
            MatrixStorage::Csr { .. } => None,
            MatrixStorage::Blocks { chunks, .. } => Some((chunks, None)),
            MatrixStorage::SplitBlocks { hi, lo, .. } => Some((hi, Some(lo))),
        }
    }

    /// Rewrite the inverse diagonal only (`minv` for an f32 matrix; the f64
    /// scalar inverse diagonal of `h` for the split matrix): with the values
    /// expanded on the GPU ([`crate::expand_blocks`]), what [`Self::write_values`]
    /// leaves to the host.
    pub fn write_diagonal(&self, ctx: &Context, h: &HostMatrix, minv: &[f32]) {
        match &self.storage {
            MatrixStorage::SplitBlocks { .. } => write_split_inverse_diagonal(ctx, &self.minv, h),
            _ => ctx.write_buffer(&self.minv, 0, bytemuck::cast_slice(minv)),
        }
    }

    /// New values, same pattern, with the inverse diagonal `minv` (none:
    /// left as it is).
    pub fn write_values(&self, ctx: &Context, h: &HostMatrix, minv: Option<&[f32]>) {
        match &self.storage {
            MatrixStorage::Csr { vals, .. } => {
                let vals32: Vec<f32> = h.vals.iter().map(|&v| v as f32).collect();
                ctx.write_buffer(vals, 0, bytemuck::cast_slice(&vals32));
            }
            MatrixStorage::Blocks { chunks, .. } => {
                write_chunk_values(ctx, chunks, 9, Values::Host(h), high_part);
            }
            // The high parts are the f32 matrix's buffers (rewritten there);
            // the inverse diagonal is f64 here, computed from `h`.
            MatrixStorage::SplitBlocks { hi, lo, .. } => {
                write_chunk_parts(
                    ctx,
                    hi,
                    &lo.iter().collect::<Vec<_>>(),
                    9,
                    Values::Host(h),
                    low_part,
                );
                if minv.is_some() {
                    write_split_inverse_diagonal(ctx, &self.minv, h);
                }
                return;
            }
        }
        if let Some(minv) = minv {
            ctx.write_buffer(&self.minv, 0, bytemuck::cast_slice(minv));
        }
    }
}

#[cfg(test)]
mod layout_tests {
    use super::*;

    #[test]
    fn rows_split_into_chunks_that_fit_the_limit() {
        // Rows of 2, 3, 1, 4, 2 blocks of 36 bytes.
        let row_ptr = [0u32, 2, 5, 6, 10, 12];
        // Everything fits: one chunk.
        let one = split_rows("m", &row_ptr, 36, 12 * 36).unwrap();
        assert_eq!(one, vec![(0..5, 0..12)]);
        // At most 5 blocks a chunk: whole rows, greedily.
        let five = split_rows("m", &row_ptr, 36, 5 * 36 + 35).unwrap();
        assert_eq!(five, vec![(0..2, 0..5), (2..4, 5..10), (4..5, 10..12)]);
        // Every block is in exactly one chunk, the chunks in row order.
        for limit in [4, 5, 6, 7, 12] {
            let c = split_rows("m", &row_ptr, 36, limit * 36).unwrap();
            assert_eq!(c.first().unwrap().0.start, 0);
            assert_eq!(c.last().unwrap().0.end, 5);
            for w in c.windows(2) {
                assert_eq!(w[0].0.end, w[1].0.start);
                assert_eq!(w[0].1.end, w[1].1.start);
            }
            for (rows, blocks) in &c {
                assert!(blocks.len() as u64 <= limit);
                assert_eq!(blocks.start, row_ptr[rows.start] as usize);
                assert_eq!(blocks.end, row_ptr[rows.end] as usize);
            }
        }
        // A row of 4 blocks cannot fit 3: a typed error naming the limit.
        let e = split_rows("block matrix", &row_ptr, 36, 3 * 36).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("max_storage_buffer_binding_size") && msg.contains("block row 3"),
            "{msg}"
        );
        // An empty matrix is one empty chunk.
        assert_eq!(split_rows("m", &[0], 36, 36).unwrap(), vec![(0..0, 0..0)]);
    }

    #[test]
    fn high_and_low_parts_carry_48_bits() {
        // Values whose f32 rounding alone is off by ~1e-8 relative.
        let vals: Vec<f64> = (0..9)
            .map(|i| {
                (1.0 + i as f64).sqrt() * 10f64.powi(i - 4) * if i % 2 == 0 { 1.0 } else { -1.0 }
            })
            .collect();
        let mut worst_f32 = 0f64;
        for &v in &vals {
            let (hi, lo) = (high_part(v), low_part(v));
            let f32_err = ((hi as f64 - v) / v).abs();
            let split_err = ((hi as f64 + lo as f64 - v) / v).abs();
            worst_f32 = worst_f32.max(f32_err);
            assert!(
                split_err <= 2f64.powi(-48),
                "value {v}: hi + lo {split_err:e}"
            );
        }
        // The low parts matter: f32 alone is off by ~2^-25 somewhere.
        assert!(worst_f32 > 1e-8, "f32 alone {worst_f32:e}");
    }
}
