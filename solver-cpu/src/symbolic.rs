//! Symbolic analysis of a sparse Cholesky factorization `P A P^T = L L^T`,
//! made once per pattern:
//!
//! - the upper triangle of `P A P^T`'s pattern;
//! - its elimination tree, `parent(j) = min { i > j : L_ij != 0 }` (Liu's
//!   algorithm: each entry `A_kj`, `j < k`, climbs from `j` by compressed
//!   paths to the root of its subtree so far, which becomes a child of `k`);
//! - a postorder of the tree and the column counts `c_j = |L_{*j}|`, diagonal
//!   included (Gilbert, Ng and Peyton: `c_j` is the number of row subtrees
//!   `j` belongs to, found from the leaves of each row subtree and the least
//!   common ancestors of consecutive leaves, in near `O(nnz(A))` steps);
//! - faer's supernodes (or simplicial structure) from the tree and counts.
//!
//! faer's `factorize_symbolic_cholesky` finds the same tree and counts by
//! walking every row subtree, a step per entry of `L` (123M for homer 1.2M's
//! shape `K`), and the GPU path's first factor waits for the analysis. The
//! numeric factorization and the solves on this analysis are faer's, run as
//! its `SymbolicCholesky` runs them: the permutation is applied here.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{
    simplicial, supernodal, CholeskySymbolicParams, SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::{FaerError, SparseColMatRef, SymbolicSparseColMatRef};
use faer::traits::RealField;
use faer::{Conj, MatMut, Par, Side};

const NONE: u32 = u32::MAX;

/// faer's `CHOLESKY_SUPERNODAL_RATIO_FACTOR` (private there): a factor is
/// supernodal where its flops per stored value exceed this times
/// [`CholeskySymbolicParams::supernodal_flop_ratio_threshold`].
const SUPERNODAL_RATIO_FACTOR: f64 = 40.0;

/// A symbolic Cholesky factor: faer's supernodal or simplicial structure and
/// the fill-reducing permutation it is of.
#[derive(Debug)]
pub(crate) struct SymbolicFactor {
    raw: SymbolicCholeskyRaw<u32>,
    /// `forward[new] = old`.
    forward: Vec<u32>,
    /// `inverse[old] = new`.
    inverse: Vec<u32>,
}

impl SymbolicFactor {
    /// faer's structure of `L`.
    pub(crate) fn raw(&self) -> &SymbolicCholeskyRaw<u32> {
        &self.raw
    }

    /// The permutation `P` (`forward[new] = old`).
    pub(crate) fn perm(&self) -> PermRef<'_, u32> {
        PermRef::new_checked(&self.forward, &self.inverse, self.forward.len())
    }

    /// `forward[new] = old`.
    pub(crate) fn forward(&self) -> &[u32] {
        &self.forward
    }

    /// Unknowns.
    pub(crate) fn nrows(&self) -> usize {
        self.forward.len()
    }

    /// Stored values of `L`.
    pub(crate) fn len_val(&self) -> usize {
        match &self.raw {
            SymbolicCholeskyRaw::Simplicial(s) => s.len_val(),
            SymbolicCholeskyRaw::Supernodal(s) => s.len_val(),
        }
    }

    /// `P A P^T`'s triangle on `side` (its rows unsorted within a column)
    /// from `a`, a triangle (lower) of `A`: `(col_ptr, row_idx, values)`.
    pub(crate) fn permute<T: RealField + Copy>(
        &self,
        a: SparseColMatRef<'_, u32, T>,
        side: Side,
    ) -> (Vec<u32>, Vec<u32>, Vec<T>) {
        let n = self.nrows();
        let nnz = a.val().len();
        let mut col_ptr = vec![0u32; n + 1];
        let mut row_idx = vec![0u32; nnz];
        let mut values = vec![T::zero_impl(); nnz];
        let mut buf = MemBuffer::new(faer::sparse::utils::permute_self_adjoint_scratch::<u32>(n));
        faer::sparse::utils::permute_self_adjoint_to_unsorted(
            &mut values,
            &mut col_ptr,
            &mut row_idx,
            a,
            self.perm(),
            Side::Lower,
            side,
            MemStack::new(&mut buf),
        );
        (col_ptr, row_idx, values)
    }

    /// faer's numeric `L L^T` of `a` (its lower triangle, unpermuted) into
    /// `out`, one supernode or column after the other: `Some(false)` where
    /// `a` is not positive definite in precision `T`, `None` where its
    /// scratch could not be allocated.
    pub(crate) fn factorize_numeric_llt<T: RealField + Copy>(
        &self,
        out: &mut [T],
        a: SparseColMatRef<'_, u32, T>,
        par: Par,
    ) -> Option<bool> {
        let n = self.nrows();
        let side = match &self.raw {
            SymbolicCholeskyRaw::Simplicial(_) => Side::Upper,
            SymbolicCholeskyRaw::Supernodal(_) => Side::Lower,
        };
        let (col_ptr, row_idx, values) = self.permute(a, side);
        let permuted = SparseColMatRef::new(
            SymbolicSparseColMatRef::new_unsorted_checked(n, n, &col_ptr, None, &row_idx),
            &values,
        );
        let factored = match &self.raw {
            SymbolicCholeskyRaw::Simplicial(s) => {
                let req = simplicial::factorize_simplicial_numeric_llt_scratch::<u32, T>(n);
                let mut buf = MemBuffer::try_new(req).ok()?;
                simplicial::factorize_simplicial_numeric_llt(
                    out,
                    permuted,
                    Default::default(),
                    s,
                    MemStack::new(&mut buf),
                )
                .is_ok()
            }
            SymbolicCholeskyRaw::Supernodal(s) => {
                let req = supernodal::factorize_supernodal_numeric_llt_scratch::<u32, T>(
                    s,
                    par,
                    Default::default(),
                );
                let mut buf = MemBuffer::try_new(req).ok()?;
                supernodal::factorize_supernodal_numeric_llt(
                    out,
                    permuted,
                    Default::default(),
                    s,
                    par,
                    MemStack::new(&mut buf),
                    Default::default(),
                )
                .is_ok()
            }
        };
        Some(factored)
    }

    /// Solves `A X = B` in place for the `n`-row columns of `rhs` (column
    /// major) with the factor `values`: `P^T L^-T L^-1 P`, the triangular
    /// solves faer's. False where scratch memory was not available.
    pub(crate) fn solve_in_place<T: RealField + Copy>(
        &self,
        values: &[T],
        rhs: &mut [T],
        par: Par,
    ) -> bool {
        let n = self.nrows();
        if n == 0 {
            return true;
        }
        let k = rhs.len() / n;
        let req = match &self.raw {
            SymbolicCholeskyRaw::Simplicial(s) => s.solve_in_place_scratch::<T>(k),
            SymbolicCholeskyRaw::Supernodal(s) => s.solve_in_place_scratch::<T>(k, par),
        };
        let Ok(mut buf) = MemBuffer::try_new(req) else {
            return false;
        };
        let mut x = Vec::new();
        if x.try_reserve_exact(n * k).is_err() {
            return false;
        }
        for col in rhs.chunks_exact(n) {
            x.extend(self.forward.iter().map(|&old| col[old as usize]));
        }
        let m = MatMut::from_column_major_slice_mut(&mut x, n, k);
        let stack = MemStack::new(&mut buf);
        match &self.raw {
            SymbolicCholeskyRaw::Simplicial(s) => simplicial::SimplicialLltRef::new(s, values)
                .solve_in_place_with_conj(Conj::No, m, par, stack),
            SymbolicCholeskyRaw::Supernodal(s) => supernodal::SupernodalLltRef::new(s, values)
                .solve_in_place_with_conj(Conj::No, m, par, stack),
        }
        for (col, solved) in rhs.chunks_exact_mut(n).zip(x.chunks_exact(n)) {
            for (o, &new) in col.iter_mut().zip(&self.inverse) {
                *o = solved[new as usize];
            }
        }
        true
    }
}

/// Seconds of an analysis's parts, for the log.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct AnalysisSeconds {
    /// The permuted pattern, its elimination tree and column counts.
    pub(crate) tree_and_counts: f64,
    /// faer's supernodes (or simplicial structure).
    pub(crate) structure: f64,
}

/// The symbolic factor of the pattern `a` (a triangle of `A`; lower in this
/// crate) in `ordering`, with `params`' choice between supernodal and
/// simplicial: the factor faer's `factorize_symbolic_cholesky` makes.
pub(crate) fn analyse_pattern(
    a: SymbolicSparseColMatRef<'_, u32>,
    ordering: SymmetricOrdering<'_, u32>,
    params: CholeskySymbolicParams<'_>,
) -> Result<(SymbolicFactor, AnalysisSeconds), FaerError> {
    let n = a.nrows();
    let mut forward = try_zeroed(n)?;
    let mut inverse = try_zeroed(n)?;
    let ordering_flops = match ordering {
        SymmetricOrdering::Amd => {
            let req = amd::order_maybe_unsorted_scratch::<u32>(n, a.compute_nnz());
            let mut buf = MemBuffer::try_new(req).map_err(|_| FaerError::OutOfMemory)?;
            let flops = amd::order_maybe_unsorted(
                &mut forward,
                &mut inverse,
                a,
                params.amd_params,
                MemStack::new(&mut buf),
            )?;
            Some(flops.n_div + flops.n_mult_subs_ldl)
        }
        SymmetricOrdering::Identity => {
            for (i, (f, v)) in forward.iter_mut().zip(&mut inverse).enumerate() {
                (*f, *v) = (i as u32, i as u32);
            }
            None
        }
        SymmetricOrdering::Custom(perm) => {
            let (f, v) = perm.arrays();
            forward.copy_from_slice(f);
            inverse.copy_from_slice(v);
            None
        }
    };
    let t = std::time::Instant::now();
    // The lower triangle (for the counts) on a thread of its own while this
    // one makes the upper triangle and its tree; both only read `a`.
    let ((upper_ptr, upper_rows), parent, (lower_ptr, lower_rows)) = std::thread::scope(|s| {
        let lower = std::thread::Builder::new()
            .name("permuted lower".into())
            .spawn_scoped(s, || permuted_triangle(a, &inverse, Side::Lower));
        let upper = permuted_triangle(a, &inverse, Side::Upper);
        let parent = elimination_tree(&upper.0, &upper.1);
        let lower = match lower.map(|h| h.join()) {
            Ok(Ok(lower)) => lower,
            Ok(Err(panic)) => std::panic::resume_unwind(panic),
            // No thread to be had: here.
            Err(_) => permuted_triangle(a, &inverse, Side::Lower),
        };
        (upper, parent, lower)
    });
    let order = postorder(&parent);
    let counts = column_counts(&parent, &order, &lower_ptr, &lower_rows);
    drop((lower_ptr, lower_rows, order));
    // faer's limit for u32 indices: the factor's values indexable by i32.
    let l_nnz: u64 = counts.iter().map(|&c| c as u64).sum();
    if l_nnz > i32::MAX as u64 {
        return Err(FaerError::IndexOverflow);
    }
    let tree_and_counts = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    // faer's flop estimate: AMD's where it ordered, else from the counts.
    let flops = ordering_flops.unwrap_or_else(|| {
        let (mut div, mut mult) = (0u128, 0u128);
        for &c in &counts {
            let c = c as u128;
            div += c;
            mult += c * (c + 1) / 2;
        }
        div as f64 + mult as f64
    });
    let upper = SymbolicSparseColMatRef::new_unsorted_checked(n, n, &upper_ptr, None, &upper_rows);
    let etree: Vec<i32> = parent
        .iter()
        .map(|&p| if p == NONE { -1 } else { p as i32 })
        .collect();
    drop(parent);
    // SAFETY: `etree` is the elimination tree of `upper` in faer's encoding
    // (the parent's index, -1 at a root), the array faer's
    // `prefactorize_symbolic_cholesky` fills for it, and `counts` its column
    // counts (the tests compare both, and the structures made from them,
    // with faer's).
    let tree = unsafe { simplicial::EliminationTreeRef::<u32>::from_inner(&etree) };
    let raw = if flops / l_nnz as f64
        > params.supernodal_flop_ratio_threshold.0 * SUPERNODAL_RATIO_FACTOR
    {
        let req = supernodal::factorize_supernodal_symbolic_cholesky_scratch::<u32>(n);
        let mut buf = MemBuffer::try_new(req).map_err(|_| FaerError::OutOfMemory)?;
        SymbolicCholeskyRaw::Supernodal(supernodal::factorize_supernodal_symbolic_cholesky(
            upper,
            tree,
            &counts,
            MemStack::new(&mut buf),
            params.supernodal_params,
        )?)
    } else {
        let req = simplicial::factorize_simplicial_symbolic_cholesky_scratch::<u32>(n);
        let mut buf = MemBuffer::try_new(req).map_err(|_| FaerError::OutOfMemory)?;
        SymbolicCholeskyRaw::Simplicial(simplicial::factorize_simplicial_symbolic_cholesky(
            upper,
            tree,
            &counts,
            MemStack::new(&mut buf),
        )?)
    };
    Ok((
        SymbolicFactor {
            raw,
            forward,
            inverse,
        },
        AnalysisSeconds {
            tree_and_counts,
            structure: t.elapsed().as_secs_f64(),
        },
    ))
}

fn try_zeroed(n: usize) -> Result<Vec<u32>, FaerError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| FaerError::OutOfMemory)?;
    v.resize(n, 0);
    Ok(v)
}

/// The triangle on `side` of `P A P^T`'s pattern, `P` given by
/// `inverse[old] = new`, from a triangle `a` of `A` (either: each entry goes
/// to the column of its larger new index for the upper triangle, of its
/// smaller for the lower); rows unsorted within a column.
fn permuted_triangle(
    a: SymbolicSparseColMatRef<'_, u32>,
    inverse: &[u32],
    side: Side,
) -> (Vec<u32>, Vec<u32>) {
    let n = a.ncols();
    let at = |j: usize| {
        a.row_idx_of_col_raw(j).iter().map(move |&i| {
            let (x, y) = (inverse[i as usize], inverse[j]);
            match side {
                Side::Upper => (x.min(y), x.max(y)),
                Side::Lower => (x.max(y), x.min(y)),
            }
        })
    };
    let mut ptr = vec![0u32; n + 1];
    for j in 0..n {
        for (_, col) in at(j) {
            ptr[col as usize + 1] += 1;
        }
    }
    for j in 0..n {
        ptr[j + 1] += ptr[j];
    }
    let mut next = ptr[..n].to_vec();
    let mut rows = vec![0u32; ptr[n] as usize];
    for j in 0..n {
        for (row, col) in at(j) {
            rows[next[col as usize] as usize] = row;
            next[col as usize] += 1;
        }
    }
    (ptr, rows)
}

/// The elimination tree of the upper-triangle pattern `(ptr, rows)`:
/// `parent[j]`, [`NONE`] at a root (Liu's algorithm with path compression:
/// `ancestor[i]` jumps to the highest column that has reached `i` so far).
fn elimination_tree(ptr: &[u32], rows: &[u32]) -> Vec<u32> {
    let n = ptr.len() - 1;
    let mut parent = vec![NONE; n];
    let mut ancestor = vec![NONE; n];
    for k in 0..n {
        for &row in &rows[ptr[k] as usize..ptr[k + 1] as usize] {
            let mut i = row;
            while i != NONE && (i as usize) < k {
                let next = ancestor[i as usize];
                ancestor[i as usize] = k as u32;
                if next == NONE {
                    parent[i as usize] = k as u32;
                }
                i = next;
            }
        }
    }
    parent
}

/// A postorder of a forest: each node after its descendants, children in
/// ascending order.
struct Postorder {
    /// `post[k]`: the `k`-th node.
    post: Vec<u32>,
    /// `first[j]`: the place in `post` of `j`'s first descendant (its own
    /// where `j` is a leaf): `j`'s subtree is `post[first[j]..=place of j]`.
    first: Vec<u32>,
}

/// The postorder of the forest `parent`, in which a parent's index is larger
/// than its children's (an elimination tree): the subtrees' sizes summed up
/// in ascending order, then each node's range placed inside its parent's in
/// descending order, the larger children's to the right. Three passes over
/// the nodes in index order, no search.
fn postorder(parent: &[u32]) -> Postorder {
    let n = parent.len();
    let mut size = vec![1u32; n];
    for j in 0..n {
        if parent[j] != NONE {
            size[parent[j] as usize] += size[j];
        }
    }
    // place[j]: j's place, the last of its subtree's range; free[j]: the
    // end of the part of that range no child has taken yet.
    let mut place = vec![0u32; n];
    let mut free = vec![0u32; n];
    let mut roots = 0u32;
    for j in 0..n {
        if parent[j] == NONE {
            roots += size[j];
            place[j] = roots - 1;
        }
    }
    for j in (0..n).rev() {
        let p = parent[j];
        if p != NONE {
            let end = free[p as usize];
            place[j] = end - 1;
            free[p as usize] = end - size[j];
        }
        free[j] = place[j];
    }
    let mut post = vec![0u32; n];
    let mut first = vec![0u32; n];
    for j in 0..n {
        post[place[j] as usize] = j as u32;
        first[j] = place[j] + 1 - size[j];
    }
    Postorder { post, first }
}

/// The column counts of `L` (diagonal included) from the elimination tree
/// `parent`, its postorder `post` and the lower-triangle pattern `(ptr,
/// rows)` (Gilbert, Ng and Peyton). Row `i`'s subtree is the set of `j`
/// with `L_ij != 0`; its leaves are among `{ j : A_ij != 0 }`. Visiting the
/// nodes in postorder, `delta[j]` gains 1 where `j` is a leaf of a row
/// subtree and loses 1 at the least common ancestor of that leaf and the row
/// subtree's previous leaf (which the subtree already counts), and each
/// child's count is taken off its parent; the counts are then the sums of
/// `delta` over each subtree.
fn column_counts(parent: &[u32], order: &Postorder, ptr: &[u32], rows: &[u32]) -> Vec<u32> {
    let n = parent.len();
    let Postorder { post, first } = order;
    // A leaf of the tree starts with its own column's diagonal.
    let mut delta = vec![0i32; n];
    for (k, &j) in post.iter().enumerate() {
        delta[j as usize] = i32::from(first[j as usize] == k as u32);
    }
    let mut ancestor: Vec<u32> = (0..n as u32).collect();
    let mut max_first = vec![NONE; n];
    let mut prev_leaf = vec![NONE; n];
    for &j in post.iter() {
        let j = j as usize;
        if parent[j] != NONE {
            delta[parent[j] as usize] -= 1;
        }
        for &i in &rows[ptr[j] as usize..ptr[j + 1] as usize] {
            let i = i as usize;
            // Is j a leaf of row i's subtree: no entry of row i seen so far
            // lies in j's subtree?
            if i <= j || (max_first[i] != NONE && first[j] <= max_first[i]) {
                continue;
            }
            max_first[i] = first[j];
            let prev = prev_leaf[i];
            prev_leaf[i] = j as u32;
            delta[j] += 1;
            if prev == NONE {
                continue;
            }
            // The least common ancestor of the previous leaf and j: the
            // root of prev's set, its path compressed.
            let mut q = prev;
            while q != ancestor[q as usize] {
                q = ancestor[q as usize];
            }
            let mut s = prev;
            while s != q {
                let up = ancestor[s as usize];
                ancestor[s as usize] = q;
                s = up;
            }
            delta[q as usize] -= 1;
        }
        if parent[j] != NONE {
            ancestor[j] = parent[j];
        }
    }
    // A parent's index is larger than its children's.
    for j in 0..n {
        if parent[j] != NONE {
            delta[parent[j] as usize] += delta[j];
        }
    }
    delta.into_iter().map(|c| c as u32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::sparse::linalg::cholesky::factorize_symbolic_cholesky;
    use faer::sparse::linalg::SupernodalThreshold;

    /// Lower-triangle patterns: a 9-point grid, a random one, two
    /// components, a diagonal, one unknown and none.
    fn patterns() -> Vec<(usize, Vec<u32>, Vec<u32>)> {
        let mut out = Vec::new();
        let lower = |n: usize, entries: &mut Vec<(usize, usize)>| {
            for j in 0..n {
                entries.push((j, j));
            }
            let entries: Vec<(usize, usize)> =
                entries.iter().map(|&(a, b)| (a.max(b), a.min(b))).collect();
            let mut cols = vec![Vec::new(); n];
            for (r, c) in entries {
                cols[c].push(r as u32);
            }
            let (mut ptr, mut rows) = (vec![0u32], Vec::new());
            for mut c in cols {
                c.sort_unstable();
                c.dedup();
                rows.extend(c);
                ptr.push(rows.len() as u32);
            }
            (n, ptr, rows)
        };
        let (w, h) = (37, 23);
        let mut grid = Vec::new();
        for y in 0..h {
            for x in 0..w {
                for (dx, dy) in [(1, 0), (0, 1), (1, 1)] {
                    if x + dx < w && y + dy < h {
                        grid.push((y * w + x, (y + dy) * w + x + dx));
                    }
                }
                if x > 0 && y + 1 < h {
                    grid.push((y * w + x, (y + 1) * w + x - 1));
                }
            }
        }
        out.push(lower(w * h, &mut grid));
        // A random pattern (a fixed linear congruential sequence).
        let mut seed = 12345u64;
        let mut next = |m: usize| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as usize % m
        };
        let n = 600;
        let mut random: Vec<(usize, usize)> = (0..1800).map(|_| (next(n), next(n))).collect();
        out.push(lower(n, &mut random));
        let mut two = vec![(0, 3), (3, 5), (1, 2), (2, 4), (4, 6), (1, 6)];
        out.push(lower(7, &mut two));
        out.push(lower(5, &mut Vec::new()));
        out.push(lower(1, &mut Vec::new()));
        out.push(lower(0, &mut Vec::new()));
        out
    }

    fn reversed(n: usize) -> (Vec<u32>, Vec<u32>) {
        let fwd: Vec<u32> = (0..n as u32).rev().collect();
        (fwd.clone(), fwd)
    }

    #[test]
    fn tree_and_counts_are_faers_in_any_ordering() {
        for (n, ptr, rows) in patterns() {
            let a = SymbolicSparseColMatRef::new_checked(n, n, &ptr, None, &rows);
            for inverse in [(0..n as u32).collect::<Vec<u32>>(), reversed(n).1] {
                let (up, ur) = permuted_triangle(a, &inverse, Side::Upper);
                let (lp, lr) = permuted_triangle(a, &inverse, Side::Lower);
                let parent = elimination_tree(&up, &ur);
                let counts = column_counts(&parent, &postorder(&parent), &lp, &lr);
                let mut etree = vec![0i32; n];
                let mut faer_counts = vec![0u32; n];
                let mut buf = MemBuffer::new(simplicial::prefactorize_symbolic_cholesky_scratch::<
                    u32,
                >(n, ur.len()));
                let upper = SymbolicSparseColMatRef::new_unsorted_checked(n, n, &up, None, &ur);
                simplicial::prefactorize_symbolic_cholesky::<u32>(
                    &mut etree,
                    &mut faer_counts,
                    upper,
                    MemStack::new(&mut buf),
                );
                let ours: Vec<i32> = parent
                    .iter()
                    .map(|&p| if p == NONE { -1 } else { p as i32 })
                    .collect();
                assert_eq!(ours, etree, "elimination tree of an {n}-unknown pattern");
                assert_eq!(
                    counts, faer_counts,
                    "column counts of an {n}-unknown pattern"
                );
            }
        }
    }

    #[test]
    fn postorder_puts_every_node_after_its_descendants() {
        for (n, ptr, rows) in patterns() {
            let a = SymbolicSparseColMatRef::new_checked(n, n, &ptr, None, &rows);
            let (up, ur) = permuted_triangle(a, &reversed(n).1, Side::Upper);
            let parent = elimination_tree(&up, &ur);
            let Postorder { post, first } = postorder(&parent);
            let mut at = vec![usize::MAX; n];
            for (k, &j) in post.iter().enumerate() {
                assert_eq!(at[j as usize], usize::MAX, "node {j} twice");
                at[j as usize] = k;
            }
            let is_under = |mut i: u32, j: u32| loop {
                if i == j {
                    break true;
                }
                if i == NONE {
                    break false;
                }
                i = parent[i as usize];
            };
            for j in 0..n {
                if parent[j] != NONE {
                    assert!(at[j] < at[parent[j] as usize]);
                }
                // j's subtree is the range ending at j, from first[j].
                let subtree = (0..n as u32).filter(|&i| is_under(i, j as u32)).count();
                assert_eq!(at[j] + 1 - first[j] as usize, subtree, "subtree of {j}");
                for &i in &post[first[j] as usize..=at[j]] {
                    assert!(is_under(i, j as u32), "{i} in the range of {j}");
                }
            }
            // Children in ascending order.
            for w in post.windows(2) {
                let (a, b) = (w[0] as usize, w[1] as usize);
                if parent[a] != NONE && parent[a] == parent[b] {
                    assert!(a < b);
                }
            }
        }
    }

    #[test]
    fn analysis_is_faers_symbolic_factor() {
        for (n, ptr, rows) in patterns() {
            let a = SymbolicSparseColMatRef::new_checked(n, n, &ptr, None, &rows);
            let (fwd, inv) = reversed(n);
            for threshold in [
                SupernodalThreshold::FORCE_SUPERNODAL,
                SupernodalThreshold::FORCE_SIMPLICIAL,
                SupernodalThreshold::AUTO,
            ] {
                let params = || CholeskySymbolicParams {
                    supernodal_flop_ratio_threshold: threshold,
                    ..Default::default()
                };
                // The identity against faer's as a given permutation: faer's
                // `Identity` analyses the upper triangle it is handed, the
                // diagonal alone of a lower one.
                let identity: Vec<u32> = (0..n as u32).collect();
                let orderings = |ours: bool| {
                    [
                        SymmetricOrdering::Amd,
                        SymmetricOrdering::Custom(PermRef::new_checked(&fwd, &inv, n)),
                        match ours {
                            true => SymmetricOrdering::Identity,
                            false => SymmetricOrdering::Custom(PermRef::new_checked(
                                &identity, &identity, n,
                            )),
                        },
                    ]
                };
                for (ours, theirs) in orderings(true).into_iter().zip(orderings(false)) {
                    let (ours, _) = analyse_pattern(a, ours, params()).unwrap();
                    let theirs =
                        factorize_symbolic_cholesky(a, Side::Lower, theirs, params()).unwrap();
                    let (f, i) = theirs.perm().unwrap().arrays();
                    assert_eq!((ours.forward.as_slice(), ours.inverse.as_slice()), (f, i));
                    assert_eq!(ours.len_val(), theirs.len_val());
                    match (ours.raw(), theirs.raw()) {
                        (
                            SymbolicCholeskyRaw::Supernodal(o),
                            SymbolicCholeskyRaw::Supernodal(t),
                        ) => {
                            assert_eq!(o.supernode_begin(), t.supernode_begin());
                            assert_eq!(o.supernode_end(), t.supernode_end());
                            assert_eq!(o.col_ptr_for_row_idx(), t.col_ptr_for_row_idx());
                            assert_eq!(o.col_ptr_for_val(), t.col_ptr_for_val());
                            assert_eq!(o.row_idx(), t.row_idx());
                        }
                        (
                            SymbolicCholeskyRaw::Simplicial(o),
                            SymbolicCholeskyRaw::Simplicial(t),
                        ) => {
                            assert_eq!(o.col_ptr(), t.col_ptr());
                            assert_eq!(o.row_idx(), t.row_idx());
                        }
                        _ => panic!(
                            "supernodal in one analysis, simplicial in the other ({n} unknowns)"
                        ),
                    }
                }
            }
        }
    }
}
