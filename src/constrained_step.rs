//! One sequential-linearly-constrained Newton step (paper Sec. 4, Eqs. 15-18).
//!
//! For a quadratic energy with Hessian `H` (prefactored) and constraints `F(x) = 0`
//! with Jacobian `L`, the step `(dx, lambda)` solves
//! `[H L^T; L 0] [dx; lambda] = [-grad E; -F]`. With `y = H^-1 (-grad E)` and
//! `Y = H^-1 L^T` (k+1 right-hand sides through the same factor, Eq. 16-18):
//! `(L Y) lambda = L y + F`, solved by SVD (pseudo-inverse, robust to redundant
//! or contradictory demands), then `dx = y - Y lambda`.

use crate::Result;
use faer::Mat;
use rayon::prelude::*;

/// Entries per task of the step's vector updates.
const CHUNK: usize = 1 << 16;
use solver_cpu::SpdSolver;

/// How constraints share Lagrange multipliers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Multipliers {
    /// One multiplier per constraint (default; converges in a few steps).
    #[default]
    PerConstraint,
    /// One multiplier per metric kind on the squared sum of its constraints (the
    /// paper's grouping, Eqs. 9-14; its gradient vanishes at the solution).
    PerKind,
}

/// The constraints as the Newton step sees them: values and dense Jacobian rows.
pub struct Linearized {
    pub values: Vec<f64>,
    pub rows: Vec<Vec<f64>>,
}

/// How many groups `groups` (compacted ids, `groups[j]` the group of
/// constraint j) names: one multiplier each where they are grouped per kind.
pub fn group_count(groups: &[usize]) -> usize {
    groups.iter().copied().max().map_or(0, |g| g + 1)
}

impl Linearized {
    /// Group per kind (`groups[j]` = group of constraint j): `F_g = sum C_j^2`,
    /// `grad F_g = sum 2 C_j grad C_j`.
    pub fn grouped(self, groups: &[usize]) -> Linearized {
        let ng = group_count(groups);
        let n = self.rows.first().map_or(0, |r| r.len());
        let mut values = vec![0.0; ng];
        let mut rows = vec![vec![0.0; n]; ng];
        for (j, &g) in groups.iter().enumerate() {
            add_to_group(self.values[j], &self.rows[j], &mut values[g], &mut rows[g]);
        }
        Linearized { values, rows }
    }
}

/// Adds constraint `C_j` (value `c`, gradient `grad`) to its group's
/// `F_g = sum C_j^2` (`value`) and `grad F_g = sum 2 C_j grad C_j` (`row`).
pub fn add_to_group(c: f64, grad: &[f64], value: &mut f64, row: &mut [f64]) {
    *value += c * c;
    for (o, &v) in row.iter_mut().zip(grad) {
        *o += 2.0 * c * v;
    }
}

/// Result of one step.
pub struct Step {
    pub dx: Vec<f64>,
    pub lambda: Vec<f64>,
}

/// Solve Eqs. 16-18 with the prepared solver; `neg_grad` is `-grad E` at the
/// current point. The k+1 solutions `[y | Y]` of the previous step in
/// `warm` as the initial guess of an iterative solver (unused when its size does
/// not match); `warm` receives this step's solutions. The gradient and the
/// Jacobian rows are moved into the right-hand side (one copy of each at a time:
/// at a million vertices every column is tens of MiB).
pub fn constrained_step_warm(
    solver: &mut dyn SpdSolver,
    neg_grad: Vec<f64>,
    lin: Linearized,
    warm: &mut Vec<f64>,
) -> Result<Step> {
    let n = neg_grad.len();
    let rhs = stacked(
        std::iter::once(neg_grad).chain(lin.rows),
        n,
        lin.values.len() + 1,
    );
    constrained_step_stacked(solver, None, &lin.values, rhs, warm)
}

/// The `ncols` columns `cols` (each of length `n`) moved one at a time into
/// one right-hand side.
fn stacked(cols: impl IntoIterator<Item = Vec<f64>>, n: usize, ncols: usize) -> Vec<f64> {
    let mut rhs = Vec::with_capacity(n * ncols);
    for c in cols {
        rhs.extend_from_slice(&c);
    }
    rhs
}

/// As [`constrained_step_warm`] with `y = H^-1 (-grad E)` known: only the
/// k columns of `Y = H^-1 L^T` are solved (`warm`: their initial guess and
/// solutions).
pub fn constrained_step_given(
    solver: &mut dyn SpdSolver,
    y: Vec<f64>,
    lin: Linearized,
    warm: &mut Vec<f64>,
) -> Result<Step> {
    let n = y.len();
    let k = lin.values.len();
    let rhs = stacked(lin.rows, n, k);
    constrained_step_stacked(solver, Some(y), &lin.values, rhs, warm)
}

/// Eqs. 16-18 on right-hand sides made in place, each column `n` long:
/// `[-grad E | L^T]` where `y` is to be solved (`None`), else `L^T` alone
/// (a caller that writes the Jacobian's rows straight into them copies
/// none: at homer 4.3M, stacking four columns of 6.5M values took 0.25 s).
/// `warm`: the solutions' initial guess (unused when its size does not
/// match), then the solutions.
pub fn constrained_step_stacked(
    solver: &mut dyn SpdSolver,
    y: Option<Vec<f64>>,
    values: &[f64],
    rhs: Vec<f64>,
    warm: &mut Vec<f64>,
) -> Result<Step> {
    let k = values.len();
    let ncols = k + usize::from(y.is_none());
    let y = match (y, k) {
        (Some(y), 0) => return step_from_solutions(y, values, &[], &[]),
        (y, _) => y,
    };
    let n = rhs.len() / ncols;
    if warm.len() != rhs.len() {
        warm.clear();
        warm.resize(rhs.len(), 0.0);
    }
    let t = std::time::Instant::now();
    solver.solve_with_guess(&rhs, warm, ncols)?;
    log::debug!(
        "constrained step: {ncols} right-hand sides solved in {:.3} s",
        t.elapsed().as_secs_f64()
    );
    match y {
        None => {
            let rows: Vec<&[f64]> = rhs[n..].chunks(n.max(1)).collect();
            let (y, ycols) = warm.split_at(n);
            step_from_solutions(y.to_vec(), values, &rows, ycols)
        }
        Some(y) => {
            let rows: Vec<&[f64]> = rhs.chunks(n.max(1)).collect();
            step_from_solutions(y, values, &rows, warm)
        }
    }
}

/// Eqs. 17-18 from the solutions of Eq. 16: `y = H^-1 (-grad E)` and the
/// columns of `Y = H^-1 L^T` (column j, for the Jacobian row `rows[j]`, at
/// `ycols[j n..(j + 1) n]`); `values` are the constraints' values `F`.
pub fn step_from_solutions(
    y: Vec<f64>,
    values: &[f64],
    rows: &[&[f64]],
    ycols: &[f64],
) -> Result<Step> {
    let n = y.len();
    let k = values.len();
    if k == 0 {
        return Ok(Step {
            dx: y,
            lambda: vec![],
        });
    }
    let t = std::time::Instant::now();
    // S = L Y (k x k), r = L y + F: the k (k + 1) products at once, each
    // on one thread (at homer 4.3M, 12 products of 6.5M entries).
    let col = |j: usize| &ycols[j * n..(j + 1) * n];
    let products: Vec<f64> = (0..k * (k + 1))
        .into_par_iter()
        .map(|p| {
            let (i, j) = (p / (k + 1), p % (k + 1));
            match j {
                0 => dot(rows[i], &y),
                j => dot(rows[i], col(j - 1)),
            }
        })
        .collect();
    let mut s = Mat::<f64>::zeros(k, k);
    let mut r = vec![0.0; k];
    for i in 0..k {
        r[i] = products[i * (k + 1)] + values[i];
        for j in 0..k {
            s[(i, j)] = products[i * (k + 1) + 1 + j];
        }
    }
    let lambda = pinv_solve(&s, &r)?;
    // dx = y - Y lambda, each entry's columns subtracted in column order.
    let mut dx = y;
    let used: Vec<(f64, &[f64])> = (0..k)
        .filter(|&j| lambda[j] != 0.0)
        .map(|j| (lambda[j], col(j)))
        .collect();
    dx.par_chunks_mut(CHUNK).enumerate().for_each(|(c, d)| {
        let entries = c * CHUNK..c * CHUNK + d.len();
        for (l, col) in &used {
            d.iter_mut()
                .zip(&col[entries.clone()])
                .for_each(|(d, c)| *d -= l * c);
        }
    });
    log::debug!(
        "constrained step: multipliers and the step from {k} + 1 solutions in {:.3} s",
        t.elapsed().as_secs_f64()
    );
    Ok(Step { dx, lambda })
}

/// Solve the small k x k system `S lambda = r` through its SVD, dropping singular
/// values below `1e-12 * sigma_max` (redundant or contradictory constraints).
pub fn pinv_solve(s: &Mat<f64>, r: &[f64]) -> Result<Vec<f64>> {
    let k = r.len();
    let svd = s.svd().map_err(|e| {
        crate::Error::Internal(format!("SVD of the multiplier system failed: {e:?}"))
    })?;
    let (u, sv, v) = (svd.U(), svd.S().column_vector(), svd.V());
    let smax = (0..k).map(|i| sv[i].abs()).fold(0.0, f64::max);
    let mut out = vec![0.0; k];
    for i in 0..k {
        let si = sv[i];
        if si.abs() <= 1e-12 * smax || si == 0.0 {
            continue;
        }
        let mut ur = 0.0;
        for a in 0..k {
            ur += u[(a, i)] * r[a];
        }
        let c = ur / si;
        for a in 0..k {
            out[a] += v[(a, i)] * c;
        }
    }
    Ok(out)
}

/// `a . b` through faer's SIMD inner product (several independent partial
/// sums; a plain `iter().sum()` adds one element at a time in order, which
/// cannot vectorise and bounds a million-face dot by the add's latency).
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    use faer::{linalg::matmul::dot::inner_prod, Conj};
    let n = a.len().min(b.len());
    inner_prod(
        faer::RowRef::from_slice(&a[..n]),
        Conj::No,
        faer::ColRef::from_slice(&b[..n]),
        Conj::No,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The step from 3 + 1 solutions of 200k entries (several chunks of
    /// the update) is the same bits on 1 and 4 of rayon's threads.
    #[test]
    fn the_step_is_the_same_on_any_number_of_threads() {
        let (n, k) = (200_003, 3);
        let entry = |i: usize, j: usize| ((i * (7 + j)) % 101) as f64 / 37.0 - 1.3;
        let rows: Vec<Vec<f64>> = (0..k)
            .map(|j| (0..n).map(|i| entry(i, j)).collect())
            .collect();
        let ycols: Vec<f64> = (0..k * n).map(|i| entry(i, 5) * 1e-2).collect();
        let on = |threads: usize| {
            crate::ordered::on_threads(threads, || {
                let y: Vec<f64> = (0..n).map(|i| entry(i, 9)).collect();
                let refs: Vec<&[f64]> = rows.iter().map(|r| &r[..]).collect();
                let step = step_from_solutions(y, &[0.1, -0.2, 0.05], &refs, &ycols).unwrap();
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
                (bits(&step.dx), bits(&step.lambda))
            })
        };
        let one = on(1);
        assert!(one.1.iter().all(|&l| l != 0), "every column in the step");
        assert!(one == on(4));
    }

    #[test]
    fn dot_is_the_sum_of_products() {
        // Lengths around the SIMD widths, and one of a 100k-face row. The
        // entries are multiples of 1/8 and 1/4, so every partial sum is exact
        // in f64, whatever the order of the additions: the same to the bit.
        for n in [0usize, 1, 3, 4, 7, 8, 9, 15, 16, 17, 1023, 108_000] {
            let a: Vec<f64> = (0..n)
                .map(|i| ((i * 37 % 101) as f64 - 50.0) / 8.0)
                .collect();
            let b: Vec<f64> = (0..n).map(|i| 1.0 + (i % 13) as f64 * 0.25).collect();
            let exact: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            assert_eq!(dot(&a, &b), exact, "n = {n}");
        }
        // Slices of different lengths: the common prefix.
        assert_eq!(dot(&[1.0, 2.0, 3.0], &[4.0, 5.0]), 14.0);
    }
}
