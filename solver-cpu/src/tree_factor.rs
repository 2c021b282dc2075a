//! Supernodal numeric Cholesky `P A P^T = L L^T`, the independent subtrees of
//! the supernodal elimination tree factored at once on rayon's threads.
//!
//! faer's `factorize_supernodal_numeric_llt` is left-looking: supernode `s`
//! gathers `A`'s columns, subtracts `L_d L_d^T` restricted to its rows for every
//! descendant `d` whose row pattern meets its columns, then factors its
//! diagonal block and solves the rows below (`L_s = A_s - sum_d L_d L_dm^T`,
//! `L_top = chol(.)`, `L_bot = L_bot L_top^-T`). It visits the supernodes one
//! after the other and parallelises only inside one supernode's dense
//! kernels, so on a mesh's matrix, whose supernodes are small below the top
//! separators, it keeps about one core busy whatever the thread count.
//!
//! Every descendant of `s` lies in its subtree, so `s` can start as soon as
//! its children are done. Here the tree is cut where a subtree's estimated
//! work falls under `1 / (8 threads)` of the whole: each subtree below the cut
//! is one task, run one supernode after the other; each supernode above it is
//! a task of its own, started when the last of its children's tasks ends, and
//! may use every thread in its dense kernels. A supernode's arithmetic (its
//! descendants in ascending order, the same kernels) does not depend on the
//! schedule, so the factor is the same on every run and for every thread
//! count.

use crate::symbolic::SymbolicFactor;
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::{cholesky_in_place, cholesky_in_place_scratch, LltError};
use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;
use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::traits::RealField;
use faer::{Accum, MatMut, MatRef, Par, Side};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Mutex;

const NONE: u32 = u32::MAX;

/// Products below this many multiply-adds run as a plain loop (faer's kernels
/// cost more than the arithmetic there).
const SMALL_PRODUCT: usize = 4096;

/// Columns per panel of an update's lower triangle.
const PANEL: usize = 64;

/// The supernodal elimination tree, its update lists and its cut into tasks.
#[derive(Debug)]
pub(crate) struct TreeSchedule {
    /// The supernodes `d` whose rows meet supernode `s`'s columns, ascending:
    /// `updates[update_ptr[s]..update_ptr[s + 1]]`.
    update_ptr: Vec<usize>,
    updates: Vec<u32>,
    /// Each task's supernodes, ascending: `task_nodes[task_ptr[t]..task_ptr[t + 1]]`.
    task_ptr: Vec<usize>,
    task_nodes: Vec<u32>,
    /// The task whose start waits for task `t` (`NONE` for a root's).
    task_parent: Vec<u32>,
    /// How many tasks task `t` waits for.
    task_children: Vec<u32>,
    /// A task above the cut: its dense kernels may use every thread.
    task_wide: Vec<bool>,
    /// The most columns of any supernode (the dense factor's scratch).
    max_cols: usize,
    /// The estimated work over its heaviest chain of supernodes: how many
    /// threads the tree alone can keep busy (dense kernels above the cut add more).
    parallelism: f64,
}

impl TreeSchedule {
    /// The schedule of `sym`'s factorization on `threads` threads.
    pub(crate) fn new(sym: &SymbolicSupernodalCholesky<u32>, threads: usize) -> Self {
        let ns = sym.n_supernodes();
        let n = sym.nrows();
        let begin = sym.supernode_begin();
        let end = sym.supernode_end();
        let mut snode_of = vec![0u32; n];
        let mut max_cols = 0;
        for s in 0..ns {
            let (b, e) = (begin[s] as usize, end[s] as usize);
            snode_of[b..e].fill(s as u32);
            max_cols = max_cols.max(e - b);
        }
        // Parents (the supernode of the first row below the diagonal block)
        // and the update lists, counted then filled.
        let mut parent = vec![NONE; ns];
        let mut update_ptr = vec![0usize; ns + 1];
        let mut work = vec![0f64; ns];
        for (d, w) in work.iter_mut().enumerate() {
            let pattern = sym.supernode(d).pattern();
            if let Some(&r) = pattern.first() {
                parent[d] = snode_of[r as usize];
            }
            let mut last = NONE;
            for &r in pattern {
                let s = snode_of[r as usize];
                if s != last {
                    update_ptr[s as usize + 1] += 1;
                    last = s;
                }
            }
            // Its dense factor and solve, and the updates it sends up.
            let q = (end[d] - begin[d]) as f64;
            let m = pattern.len() as f64;
            *w = q * q * q / 3.0 + m * q * q + m * m * q;
        }
        for s in 0..ns {
            update_ptr[s + 1] += update_ptr[s];
        }
        let mut updates = vec![0u32; update_ptr[ns]];
        let mut at = update_ptr.clone();
        for d in 0..ns {
            let mut last = NONE;
            for &r in sym.supernode(d).pattern() {
                let s = snode_of[r as usize];
                if s != last {
                    updates[at[s as usize]] = d as u32;
                    at[s as usize] += 1;
                    last = s;
                }
            }
        }
        drop(snode_of);
        // The heaviest chain of supernodes' own work from a leaf to the root:
        // the tree lets the factorization run at most `total / chain` at once.
        let mut chain = work.clone();
        for s in 0..ns {
            if parent[s] != NONE {
                let p = parent[s] as usize;
                chain[p] = chain[p].max(chain[s] + work[p]);
            }
        }
        // Subtree work: a parent comes after its children.
        let mut subtree = work;
        for s in 0..ns {
            if parent[s] != NONE {
                let w = subtree[s];
                subtree[parent[s] as usize] += w;
            }
        }
        let total: f64 = (0..ns)
            .filter(|&s| parent[s] == NONE)
            .map(|s| subtree[s])
            .sum();
        let heaviest_chain = (0..ns)
            .filter(|&s| parent[s] == NONE)
            .map(|s| chain[s])
            .fold(0.0, f64::max);
        let cut = if threads <= 1 {
            f64::INFINITY
        } else {
            total / (8 * threads) as f64
        };
        // Each supernode's task: its own above the cut, else its subtree
        // root's below it (parents first, so descending).
        let big: Vec<bool> = subtree.iter().map(|&w| w > cut).collect();
        let mut owner = vec![0u32; ns];
        for s in (0..ns).rev() {
            let p = parent[s];
            owner[s] = if big[s] || p == NONE || big[p as usize] {
                s as u32
            } else {
                owner[p as usize]
            };
        }
        let mut task_of = vec![NONE; ns];
        let mut roots = Vec::new();
        for s in 0..ns {
            if owner[s] == s as u32 {
                task_of[s] = roots.len() as u32;
                roots.push(s);
            }
        }
        let tasks = roots.len();
        let mut task_ptr = vec![0usize; tasks + 1];
        for s in 0..ns {
            task_ptr[task_of[owner[s] as usize] as usize + 1] += 1;
        }
        for t in 0..tasks {
            task_ptr[t + 1] += task_ptr[t];
        }
        let mut task_nodes = vec![0u32; ns];
        let mut at = task_ptr.clone();
        for s in 0..ns {
            let t = task_of[owner[s] as usize] as usize;
            task_nodes[at[t]] = s as u32;
            at[t] += 1;
        }
        let mut task_parent = vec![NONE; tasks];
        let mut task_children = vec![0u32; tasks];
        let mut task_wide = vec![false; tasks];
        for (t, &r) in roots.iter().enumerate() {
            task_wide[t] = big[r];
            let p = parent[r];
            if p != NONE {
                let pt = task_of[owner[p as usize] as usize];
                task_parent[t] = pt;
                task_children[pt as usize] += 1;
            }
        }
        TreeSchedule {
            update_ptr,
            updates,
            task_ptr,
            task_nodes,
            task_parent,
            task_children,
            task_wide,
            max_cols,
            parallelism: if heaviest_chain > 0.0 {
                total / heaviest_chain
            } else {
                1.0
            },
        }
    }

    /// How many tasks the factorization runs.
    pub(crate) fn tasks(&self) -> usize {
        self.task_parent.len()
    }
}

/// The factor's values, written by one task per supernode and read by the
/// supernode's ancestors after it is done (the tasks' order sees to both).
struct SharedValues<T> {
    ptr: *mut T,
    len: usize,
}

unsafe impl<T: Send> Send for SharedValues<T> {}
unsafe impl<T: Send> Sync for SharedValues<T> {}

impl<T> SharedValues<T> {
    /// # Safety
    /// No other live slice may overlap `a..b` while the result is used mutably.
    #[allow(clippy::mut_from_ref)]
    unsafe fn slice_mut(&self, a: usize, b: usize) -> &mut [T] {
        assert!(a <= b && b <= self.len);
        std::slice::from_raw_parts_mut(self.ptr.add(a), b - a)
    }

    /// # Safety
    /// No live mutable slice may overlap `a..b` while the result is used.
    unsafe fn slice(&self, a: usize, b: usize) -> &[T] {
        assert!(a <= b && b <= self.len);
        std::slice::from_raw_parts(self.ptr.add(a), b - a)
    }
}

/// A task's working memory: row positions inside the current supernode
/// (`NONE` outside its pattern) and an update's product.
struct Scratch<T> {
    global_to_local: Vec<u32>,
    local: Vec<usize>,
    product: Vec<T>,
    dense: MemBuffer,
}

struct Context<'a, T> {
    sym: &'a SymbolicSupernodalCholesky<u32>,
    a: SparseColMatRef<'a, u32, T>,
    schedule: &'a TreeSchedule,
    values: SharedValues<T>,
    par: Par,
    pending: Vec<AtomicU32>,
    failed: AtomicBool,
    error: Mutex<Option<LltError>>,
    spare: Mutex<Vec<Scratch<T>>>,
}

impl<T: RealField + Copy + Send + Sync> Context<'_, T> {
    fn scratch(&self) -> Scratch<T> {
        if let Some(s) = self.spare.lock().unwrap().pop() {
            return s;
        }
        let req: StackReq =
            cholesky_in_place_scratch::<T>(self.schedule.max_cols, self.par, Default::default());
        Scratch {
            global_to_local: vec![NONE; self.sym.nrows()],
            local: Vec::new(),
            product: Vec::new(),
            dense: MemBuffer::new(req),
        }
    }

    /// Factors task `t`'s supernodes, one after the other.
    fn run_task(&self, t: usize) -> Result<(), LltError> {
        let par = if self.schedule.task_wide[t] {
            self.par
        } else {
            Par::Seq
        };
        let mut scratch = self.scratch();
        let nodes =
            &self.schedule.task_nodes[self.schedule.task_ptr[t]..self.schedule.task_ptr[t + 1]];
        let mut result = Ok(());
        for &s in nodes {
            if self.failed.load(Ordering::Relaxed) {
                break;
            }
            // Safety: `s`'s values are written by this task alone, and its
            // descendants' were written by tasks that ended before this one
            // started (the pending counts' acquire/release order).
            result = unsafe { self.factor_supernode(s as usize, &mut scratch, par) };
            if result.is_err() {
                break;
            }
        }
        self.spare.lock().unwrap().push(scratch);
        result
    }

    /// The left-looking step of supernode `s` (faer's, restated).
    ///
    /// # Safety
    /// Every descendant of `s` is factored, and no other thread touches `s`'s values.
    unsafe fn factor_supernode(
        &self,
        s: usize,
        scratch: &mut Scratch<T>,
        par: Par,
    ) -> Result<(), LltError> {
        let sym = self.sym;
        let col_ptr_val = sym.col_ptr_for_val();
        let s_start = sym.supernode_begin()[s] as usize;
        let s_end = sym.supernode_end()[s] as usize;
        let s_pattern = sym.supernode(s).pattern();
        let q = s_end - s_start;
        let m = q + s_pattern.len();
        let g2l = &mut scratch.global_to_local;
        for (i, &row) in s_pattern.iter().enumerate() {
            g2l[row as usize] = (i + q) as u32;
        }
        let ls = self
            .values
            .slice_mut(col_ptr_val[s] as usize, col_ptr_val[s + 1] as usize);
        ls.fill(T::zero_impl());
        // A's columns (lower part) into the supernode.
        for j in s_start..s_end {
            let col = &mut ls[(j - s_start) * m..(j - s_start + 1) * m];
            let rows = self.a.row_idx_of_col_raw(j);
            let vals = self.a.val_of_col(j);
            for (&i, &v) in rows.iter().zip(vals) {
                let i = i as usize;
                if i < j {
                    continue;
                }
                let local = if i >= s_end {
                    g2l[i] as usize
                } else {
                    i - s_start
                };
                col[local] += v;
            }
        }
        // Descendants' updates.
        let updates =
            &self.schedule.updates[self.schedule.update_ptr[s]..self.schedule.update_ptr[s + 1]];
        for &d in updates {
            let d = d as usize;
            let d_pattern = sym.supernode(d).pattern();
            let dq = (sym.supernode_end()[d] - sym.supernode_begin()[d]) as usize;
            let dm = dq + d_pattern.len();
            let ld = self
                .values
                .slice(col_ptr_val[d] as usize, col_ptr_val[d + 1] as usize);
            let p0 = d_pattern.partition_point(|&r| (r as usize) < s_start);
            let mid = d_pattern[p0..].partition_point(|&r| (r as usize) < s_end);
            let rows = d_pattern.len() - p0;
            let first = dq + p0;
            // The rows' places in `s`: its columns, then its pattern's rows.
            scratch.local.clear();
            scratch
                .local
                .extend(d_pattern[p0..].iter().enumerate().map(|(i, &r)| {
                    if i < mid {
                        r as usize - s_start
                    } else {
                        g2l[r as usize] as usize
                    }
                }));
            let local = &scratch.local;
            // Subtracts the product's columns `j0..j0 + w` (rows `j0..`,
            // each column `j` from its row `j` on), stored column-major
            // with `rows - j0` rows, from their places in `s`.
            let scatter = |ls: &mut [T], product: &[T], j0: usize, w: usize| {
                let h = rows - j0;
                for jj in 0..w {
                    let j = j0 + jj;
                    let dst = &mut ls[local[j] * m..(local[j] + 1) * m];
                    for (&r, &v) in local[j..].iter().zip(&product[jj * h + jj..(jj + 1) * h]) {
                        dst[r] -= v;
                    }
                }
            };
            // The product's lower part, `L_d[rows] L_d[mid]^T`.
            if rows * mid * dq < SMALL_PRODUCT {
                // Column by column.
                scratch.product.resize(rows * mid, T::zero_impl());
                let product = &mut scratch.product[..rows * mid];
                for j in 0..mid {
                    let col = &mut product[j * rows..(j + 1) * rows];
                    col[j..].fill(T::zero_impl());
                    for k in 0..dq {
                        let ldk = &ld[k * dm + first..k * dm + first + rows];
                        let b = ldk[j];
                        for (c, &a) in col[j..].iter_mut().zip(&ldk[j..]) {
                            *c += a * b;
                        }
                    }
                }
                scatter(ls, product, 0, mid);
            } else {
                // The square's lower triangle in panels of columns, each
                // with the rows below it (faer's triangular product would
                // allocate a temporary square per call), each subtracted
                // before the next is made: the scratch holds one panel,
                // not the whole product (36 MiB at the peak of homer
                // 1.2M's factorization on two threads, more on more).
                let ld = MatRef::from_column_major_slice(ld, dm, dq);
                let bot = ld.subrows(first, rows);
                scratch
                    .product
                    .resize(rows * PANEL.min(mid), T::zero_impl());
                for j0 in (0..mid).step_by(PANEL) {
                    let (w, h) = (PANEL.min(mid - j0), rows - j0);
                    let product = &mut scratch.product[..h * w];
                    faer::linalg::matmul::matmul(
                        MatMut::from_column_major_slice_mut(product, h, w),
                        Accum::Replace,
                        bot.subrows(j0, h),
                        bot.subrows(j0, w).transpose(),
                        T::one_impl(),
                        par,
                    );
                    scatter(ls, product, j0, w);
                }
            }
        }
        for &row in s_pattern {
            g2l[row as usize] = NONE;
        }
        let lmat = MatMut::from_column_major_slice_mut(ls, m, q);
        let (mut top, bot) = lmat.split_at_row_mut(q);
        if let Err(LltError::NonPositivePivot { index }) = cholesky_in_place(
            top.as_mut(),
            Default::default(),
            par,
            MemStack::new(&mut scratch.dense),
            Default::default(),
        ) {
            return Err(LltError::NonPositivePivot {
                index: index + s_start,
            });
        }
        faer::linalg::triangular_solve::solve_lower_triangular_in_place(
            top.as_ref(),
            bot.transpose_mut(),
            par,
        );
        Ok(())
    }
}

fn spawn_task<'s, T: RealField + Copy + Send + Sync>(
    scope: &rayon::Scope<'s>,
    ctx: &'s Context<'s, T>,
    t: usize,
) {
    scope.spawn(move |scope| {
        if ctx.failed.load(Ordering::Relaxed) {
            return;
        }
        if let Err(e) = ctx.run_task(t) {
            ctx.failed.store(true, Ordering::Relaxed);
            ctx.error.lock().unwrap().get_or_insert(e);
            return;
        }
        let p = ctx.schedule.task_parent[t];
        if p != NONE && ctx.pending[p as usize].fetch_sub(1, Ordering::AcqRel) == 1 {
            spawn_task(scope, ctx, p as usize);
        }
    });
}

/// Numeric supernodal `L L^T` of `a_lower` (already permuted, lower part)
/// into `l_values`, on `schedule`'s tasks; `par` is the thread count
/// (`Par::Seq`: every supernode on this thread, in order).
pub(crate) fn factorize_supernodal_numeric_llt_tree<T: RealField + Copy + Send + Sync>(
    l_values: &mut [T],
    a_lower: SparseColMatRef<'_, u32, T>,
    sym: &SymbolicSupernodalCholesky<u32>,
    schedule: &TreeSchedule,
    par: Par,
) -> Result<(), LltError> {
    assert_eq!(l_values.len(), sym.len_val());
    let ctx = Context {
        sym,
        a: a_lower,
        schedule,
        values: SharedValues {
            ptr: l_values.as_mut_ptr(),
            len: l_values.len(),
        },
        par,
        pending: schedule
            .task_children
            .iter()
            .map(|&c| AtomicU32::new(c))
            .collect(),
        failed: AtomicBool::new(false),
        error: Mutex::new(None),
        spare: Mutex::new(Vec::new()),
    };
    if schedule.tasks() == 1 || par.degree() <= 1 {
        // Tasks in the order of their last supernode: children first.
        let mut order: Vec<usize> = (0..schedule.tasks()).collect();
        order.sort_unstable_by_key(|&t| schedule.task_nodes[schedule.task_ptr[t + 1] - 1]);
        for t in order {
            ctx.run_task(t)?;
        }
        return Ok(());
    }
    rayon::scope(|scope| {
        for t in 0..schedule.tasks() {
            if schedule.task_children[t] == 0 {
                spawn_task(scope, &ctx, t);
            }
        }
    });
    match ctx.error.into_inner().unwrap() {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// A lower triangle permuted to a symbolic factor's ordering (its rows
/// unsorted within a column), owned: the input it was made from may go.
pub(crate) struct PermutedLower<T> {
    col_ptr: Vec<u32>,
    row_idx: Vec<u32>,
    values: Vec<T>,
}

/// `P A P^T`'s lower triangle for `sym`'s permutation `P`, from the lower
/// triangle `(pattern, values)` of `A`.
pub(crate) fn permute_lower<T: RealField + Copy>(
    sym: &SymbolicFactor,
    pattern: SymbolicSparseColMatRef<'_, u32>,
    values: &[T],
) -> PermutedLower<T> {
    let (col_ptr, row_idx, values) =
        sym.permute(SparseColMatRef::new(pattern, values), Side::Lower);
    PermutedLower {
        col_ptr,
        row_idx,
        values,
    }
}

/// `sym`'s numeric factor of `a` (made by [`permute_lower`]) into `out`, its
/// supernodes on rayon's threads as above: `None` where `sym` is simplicial
/// (the caller factors it with faer), else whether the matrix is positive
/// definite in precision `T`.
pub(crate) fn factor_permuted<T: RealField + Copy + Send + Sync>(
    sym: &SymbolicFactor,
    out: &mut [T],
    a: &PermutedLower<T>,
    par: Par,
) -> Option<bool> {
    let SymbolicCholeskyRaw::Supernodal(snodal) = sym.raw() else {
        return None;
    };
    let threads = par.degree().max(1);
    let t = std::time::Instant::now();
    let schedule = TreeSchedule::new(snodal, threads);
    let schedule_seconds = t.elapsed().as_secs_f64();
    let n = a.col_ptr.len() - 1;
    let pattern = SymbolicSparseColMatRef::new_unsorted_checked(n, n, &a.col_ptr, None, &a.row_idx);
    let factored = factorize_supernodal_numeric_llt_tree(
        out,
        SparseColMatRef::new(pattern, &a.values),
        snodal,
        &schedule,
        par,
    );
    log::debug!(
        "Cholesky numeric factor: {} supernodes in {} tasks on {threads} threads (the tree's \
         parallelism {:.1}), schedule {schedule_seconds:.3} s, {:.3} s in all",
        snodal.n_supernodes(),
        schedule.tasks(),
        schedule.parallelism,
        t.elapsed().as_secs_f64()
    );
    Some(factored.is_ok())
}

/// [`permute_lower`], then [`factor_permuted`].
pub(crate) fn factor_numeric_tree<T: RealField + Copy + Send + Sync>(
    sym: &SymbolicFactor,
    out: &mut [T],
    pattern: SymbolicSparseColMatRef<'_, u32>,
    values: &[T],
    par: Par,
) -> Option<bool> {
    if !matches!(sym.raw(), SymbolicCholeskyRaw::Supernodal(_)) {
        return None;
    }
    factor_permuted(sym, out, &permute_lower(sym, pattern, values), par)
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::sparse::linalg::cholesky::{
        factorize_symbolic_cholesky, CholeskySymbolicParams, SymmetricOrdering,
    };
    use faer::sparse::linalg::SupernodalThreshold;

    /// The lower triangle of a `w x h` grid's 9-point Laplacian plus `shift`
    /// on the diagonal (a mesh-like pattern), as `(col_ptr, row_idx, values)`.
    fn grid(w: usize, h: usize, shift: f64) -> (Vec<u32>, Vec<u32>, Vec<f64>) {
        let n = w * h;
        let (mut col_ptr, mut row_idx, mut values) = (vec![0u32], Vec::new(), Vec::new());
        for j in 0..n {
            let (x, y) = (j % w, j / w);
            let mut entries = vec![(j, 8.8 + shift + (j % 7) as f64 * 0.1)];
            for (dx, dy) in [(1i64, 0i64), (-1, 1), (0, 1), (1, 1)] {
                let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                if nx >= 0 && (nx as usize) < w && (ny as usize) < h {
                    let i = ny as usize * w + nx as usize;
                    entries.push((i, -1.0 - (i % 3) as f64 * 0.05));
                }
            }
            entries.sort_by_key(|e| e.0);
            for (i, v) in entries {
                row_idx.push(i as u32);
                values.push(v);
            }
            col_ptr.push(row_idx.len() as u32);
        }
        (col_ptr, row_idx, values)
    }

    fn params() -> CholeskySymbolicParams<'static> {
        CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
            ..Default::default()
        }
    }

    fn symbolic(n: usize, col_ptr: &[u32], row_idx: &[u32]) -> SymbolicFactor {
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, col_ptr, None, row_idx);
        crate::symbolic::analyse_pattern(pattern, SymmetricOrdering::Amd, params())
            .unwrap()
            .0
    }

    /// faer's factor, on faer's own symbolic analysis.
    fn faer_factor(pattern: SymbolicSparseColMatRef<'_, u32>, values: &[f64]) -> Vec<f64> {
        let sym =
            factorize_symbolic_cholesky(pattern, Side::Lower, SymmetricOrdering::Amd, params())
                .unwrap();
        let mut out = vec![0.0; sym.len_val()];
        let par = Par::Seq;
        let mut buf =
            MemBuffer::new(sym.factorize_numeric_llt_scratch::<f64>(par, Default::default()));
        sym.factorize_numeric_llt::<f64>(
            &mut out,
            SparseColMatRef::new(pattern, values),
            Side::Lower,
            Default::default(),
            par,
            MemStack::new(&mut buf),
            Default::default(),
        )
        .unwrap();
        out
    }

    fn tree_factor_on(
        threads: usize,
        sym: &SymbolicFactor,
        pattern: SymbolicSparseColMatRef<'_, u32>,
        values: &[f64],
    ) -> Option<Vec<f64>> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut out = vec![0.0; sym.len_val()];
            let par = if threads == 1 {
                Par::Seq
            } else {
                Par::rayon(threads)
            };
            factor_numeric_tree(sym, &mut out, pattern, values, par)
                .unwrap()
                .then_some(out)
        })
    }

    #[test]
    fn tree_factor_is_faers_factor_and_the_same_on_any_thread_count() {
        // Top separators of over 2 PANELs of columns: updates in several
        // panels.
        let (w, h) = (200, 150);
        let n = w * h;
        let (col_ptr, row_idx, values) = grid(w, h, 0.01);
        let sym = symbolic(n, &col_ptr, &row_idx);
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        let SymbolicCholeskyRaw::Supernodal(snodal) = sym.raw() else {
            panic!("forced supernodal");
        };
        assert!(
            TreeSchedule::new(snodal, 4).tasks() > 8,
            "the cut makes tasks to share"
        );
        let reference = faer_factor(pattern, &values);
        let largest = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let one = tree_factor_on(1, &sym, pattern, &values).unwrap();
        let worst = one
            .iter()
            .zip(&reference)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            worst <= 1e-12 * largest,
            "differs from faer's by {worst} of {largest}"
        );
        for threads in [2, 3, 4] {
            let many = tree_factor_on(threads, &sym, pattern, &values).unwrap();
            assert!(
                many.iter()
                    .zip(&one)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{threads} threads changed the factor"
            );
        }
    }

    #[test]
    fn tree_factor_reports_a_matrix_that_is_not_positive_definite() {
        let (w, h) = (40, 30);
        let n = w * h;
        // The 9-point Laplacian shifted down by more than its smallest
        // eigenvalue: indefinite.
        let (col_ptr, row_idx, values) = grid(w, h, -2.0);
        let sym = symbolic(n, &col_ptr, &row_idx);
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        for threads in [1, 3] {
            assert!(tree_factor_on(threads, &sym, pattern, &values).is_none());
        }
        let (_, _, fine) = grid(w, h, 0.5);
        assert!(tree_factor_on(3, &sym, pattern, &fine).is_some());
    }
}
