//! Symmetric matrices of 3x3 blocks: one block row/column per vertex, the natural
//! layout for x/y/z-coupled unknowns (dof `3 v + r`).

use crate::SymCsc;

/// `values`, the entries of `rows` rows stored one row after the other
/// (row `r`'s from `start(r)` to `start(r + 1)`, `start(0)` the first),
/// cut into groups of `group` rows: each group's rows and entries, for
/// rayon's threads to fill apart.
pub fn row_groups_mut<T>(
    values: &mut [T],
    rows: usize,
    start: impl Fn(usize) -> usize,
    group: usize,
) -> Vec<(std::ops::Range<usize>, &mut [T])> {
    let mut groups = Vec::with_capacity(rows.div_ceil(group.max(1)));
    let mut rest = values;
    for first in (0..rows).step_by(group.max(1)) {
        let last = (first + group).min(rows);
        let (entries, tail) = rest.split_at_mut(start(last) - start(first));
        groups.push((first..last, entries));
        rest = tail;
    }
    groups
}

/// The strictly lower blocks of a [`BlockSym3`] listed by block row: for row `i`,
/// `entries[row_ptr[i]..row_ptr[i + 1]]` holds (block slot, block column). With
/// the column-wise storage this gives a gather-only, row-parallel product.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BlockRows {
    pub row_ptr: Vec<usize>,
    pub entries: Vec<(u32, u32)>,
}

impl BlockRows {
    /// Index of the strictly lower entries of the lower pattern `(col_ptr, row_idx)`.
    pub fn of_pattern(n: usize, col_ptr: &[usize], row_idx: &[usize]) -> BlockRows {
        let mut row_ptr = vec![0usize; n + 1];
        for j in 0..n {
            for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
                if i != j {
                    row_ptr[i + 1] += 1;
                }
            }
        }
        for i in 0..n {
            row_ptr[i + 1] += row_ptr[i];
        }
        let mut next = row_ptr.clone();
        let mut entries = vec![(0u32, 0u32); row_ptr[n]];
        for j in 0..n {
            let range = col_ptr[j]..col_ptr[j + 1];
            for (k, &i) in range.clone().zip(&row_idx[range]) {
                if i != j {
                    entries[next[i]] = (k as u32, j as u32);
                    next[i] += 1;
                }
            }
        }
        BlockRows { row_ptr, entries }
    }
}

/// Lower-triangular block pattern (block row >= block column), each block a
/// row-major 3x3 matrix. Diagonal blocks are stored whole (symmetric).
#[derive(Debug, Clone, Default)]
pub struct BlockSym3 {
    pub n: usize,
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    pub blocks: Vec<[f64; 9]>,
}

impl BlockSym3 {
    /// Pattern from vertex pairs (either order); diagonal always present.
    pub fn from_pattern(n: usize, pairs: impl IntoIterator<Item = (usize, usize)>) -> Self {
        let s = SymCsc::from_pattern(n, pairs);
        let nnz = s.row_idx.len();
        BlockSym3 {
            n,
            col_ptr: s.col_ptr,
            row_idx: s.row_idx,
            blocks: vec![[0.0; 9]; nnz],
        }
    }

    /// Block slot of (i, j) in either order, and whether the stored block is the
    /// transpose of the requested one.
    #[inline]
    pub fn slot(&self, i: usize, j: usize) -> Option<(usize, bool)> {
        let (r, c, t) = if i >= j { (i, j, false) } else { (j, i, true) };
        let s = self.col_ptr[c];
        let e = self.col_ptr[c + 1];
        self.row_idx[s..e]
            .binary_search(&r)
            .ok()
            .map(|k| (s + k, t))
    }

    /// Add `v * I3` to block (i, j) (and implicitly (j, i)).
    #[inline]
    pub fn add_scalar(&mut self, i: usize, j: usize, v: f64) {
        if let Some((k, _)) = self.slot(i, j) {
            let b = &mut self.blocks[k];
            b[0] += v;
            b[4] += v;
            b[8] += v;
        }
    }

    /// Add the 3x3 block `m` (row-major) to block (i, j); for i == j, `m` must be symmetric.
    #[inline]
    pub fn add_block(&mut self, i: usize, j: usize, m: &[f64; 9]) {
        if let Some((k, t)) = self.slot(i, j) {
            let b = &mut self.blocks[k];
            if t {
                for r in 0..3 {
                    for c in 0..3 {
                        b[3 * r + c] += m[3 * c + r];
                    }
                }
            } else {
                for q in 0..9 {
                    b[q] += m[q];
                }
            }
        }
    }

    /// Checks that `fixed` has one flag per block row (the `prepare_blocks` contract).
    pub fn check_fixed(&self, fixed: &[bool]) -> Result<(), crate::SolverError> {
        if fixed.len() == self.n {
            return Ok(());
        }
        Err(crate::SolverError::DimensionMismatch(format!(
            "{} fixed flags for {} block rows",
            fixed.len(),
            self.n
        )))
    }

    pub fn clear(&mut self) {
        self.blocks.iter_mut().for_each(|b| *b = [0.0; 9]);
    }

    /// Scalar lower-triangular pattern of the 3n x 3n matrix.
    pub fn scalar_pattern(&self) -> SymCsc {
        let n3 = 3 * self.n;
        let mut col_ptr = Vec::with_capacity(n3 + 1);
        let mut row_idx = Vec::with_capacity(self.row_idx.len() * 9);
        col_ptr.push(0);
        for j in 0..self.n {
            for rc in 0..3 {
                for k in self.col_ptr[j]..self.col_ptr[j + 1] {
                    let i = self.row_idx[k];
                    let r0 = if i == j { rc } else { 0 };
                    for rr in r0..3 {
                        row_idx.push(3 * i + rr);
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        let nnz = row_idx.len();
        SymCsc {
            n: n3,
            col_ptr,
            row_idx,
            values: vec![0.0; nnz],
        }
    }

    /// Write the values into `out` (whose pattern is `scalar_pattern()`). Vertices
    /// with `fixed[v]` get an identity diagonal block and no coupling, so their
    /// unknowns are held at zero increment.
    pub fn fill_scalar(&self, out: &mut SymCsc, fixed: &[bool]) {
        let mut pos = 0;
        for j in 0..self.n {
            for rc in 0..3 {
                for k in self.col_ptr[j]..self.col_ptr[j + 1] {
                    let i = self.row_idx[k];
                    let b = &self.blocks[k];
                    let r0 = if i == j { rc } else { 0 };
                    let cut = fixed[i] || fixed[j];
                    for rr in r0..3 {
                        out.values[pos] = if cut {
                            if i == j && rr == rc {
                                1.0
                            } else {
                                0.0
                            }
                        } else {
                            b[3 * rr + rc]
                        };
                        pos += 1;
                    }
                }
            }
        }
        debug_assert_eq!(pos, out.values.len());
    }

    /// Row-wise index of the strictly lower blocks (for [`BlockSym3::mul_vec_rows`]).
    pub fn row_index(&self) -> BlockRows {
        BlockRows::of_pattern(self.n, &self.col_ptr, &self.row_idx)
    }

    /// y = A x, parallel over block rows; `rows` is this pattern's [`BlockSym3::row_index`].
    pub fn mul_vec_rows(&self, rows: &BlockRows, x: &[f64], y: &mut [f64]) {
        use rayon::prelude::*;
        y.par_chunks_mut(3).enumerate().for_each(|(v, out)| {
            let mut acc = [0.0f64; 3];
            // Column v: blocks (i, v), i >= v, contribute B^T x_i.
            for k in self.col_ptr[v]..self.col_ptr[v + 1] {
                let i = self.row_idx[k];
                let b = &self.blocks[k];
                let xi = &x[3 * i..3 * i + 3];
                for c in 0..3 {
                    acc[c] += b[c] * xi[0] + b[3 + c] * xi[1] + b[6 + c] * xi[2];
                }
            }
            // Row v, strictly lower: blocks (v, j), j < v, contribute B x_j.
            for &(k, j) in &rows.entries[rows.row_ptr[v]..rows.row_ptr[v + 1]] {
                let b = &self.blocks[k as usize];
                let j = j as usize;
                let xj = &x[3 * j..3 * j + 3];
                for r in 0..3 {
                    acc[r] += b[3 * r] * xj[0] + b[3 * r + 1] * xj[1] + b[3 * r + 2] * xj[2];
                }
            }
            out.copy_from_slice(&acc);
        });
    }

    /// y = A x for the full symmetric block matrix (x, y of length 3n).
    pub fn mul_vec(&self, x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        for j in 0..self.n {
            for k in self.col_ptr[j]..self.col_ptr[j + 1] {
                let i = self.row_idx[k];
                let b = &self.blocks[k];
                for r in 0..3 {
                    for c in 0..3 {
                        y[3 * i + r] += b[3 * r + c] * x[3 * j + c];
                    }
                }
                if i != j {
                    for r in 0..3 {
                        for c in 0..3 {
                            y[3 * j + c] += b[3 * r + c] * x[3 * i + r];
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::row_groups_mut;

    /// Each group holds exactly its rows' entries, in order, the last one
    /// short; rows of no entries included.
    #[test]
    fn row_groups_cut_the_entries_at_their_rows() {
        let start = [0usize, 2, 2, 5, 6, 9, 9, 10];
        let rows = start.len() - 1;
        let mut values: Vec<usize> = (0..start[rows]).collect();
        let groups = row_groups_mut(&mut values, rows, |r| start[r], 3);
        let seen: Vec<(std::ops::Range<usize>, Vec<usize>)> =
            groups.into_iter().map(|(r, v)| (r, v.to_vec())).collect();
        assert_eq!(
            seen,
            vec![
                (0..3, vec![0, 1, 2, 3, 4]),
                (3..6, vec![5, 6, 7, 8]),
                (6..7, vec![9]),
            ]
        );
    }
}
