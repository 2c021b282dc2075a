//! Symmetric matrices of 3x3 blocks: one block row/column per vertex, the natural
//! layout for x/y/z-coupled unknowns (dof `3 v + r`).

use crate::SymCsc;

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
