//! Scale-factor estimation (paper Sec. 2.2, Eq. 3).
//!
//! `min_s  k_d sum_{(i,j) in Q} (s_i - s_j)^2 + k_r sum_i rho_i (s_i - 1)^2`
//! `s.t.   C_j(s) = sum_f c_jf s_f^p_j / T_j - 1 = 0`  (Eqs. 9, 11, 13: p = 1, 2, 3)
//!
//! `Q` is the set of adjacent face pairs, `rho_i = A_i / mean(A)` with input face
//! areas (pitfall (a): an unweighted regulariser makes `s` non-uniform and
//! resolution-dependent; `Regulariser::Uniform` keeps the paper's literal form).
//! The Hessian `H` is constant for the whole run: it is factored once. Of a
//! Newton step's solves (Eq. 16), `y = H^-1 (-grad E) = 1 - s` needs none
//! (`grad E = H (s - 1)`), and a column of `Y = H^-1 L^T` is solved only when
//! its Jacobian row changed: a degree-1 constraint's row is the same at every
//! Newton step of one estimation.

use crate::constrained_step::{add_to_group, group_count, step_from_solutions, Multipliers};
use crate::Result;
use solver_cpu::{NewtonRules, PowerSum, SpdSolver, SymCsc};

/// The estimation is done when every constraint's `|C_j(s)|` is below this,
const RESIDUAL: f64 = 1e-12;
/// or once a step moves no scale factor by this much.
const MOVED: f64 = 1e-13;
/// No scale factor is stepped below this (less a tenth of the way there):
/// a face cannot be scaled through zero.
const FLOOR: f64 = 0.05;

/// Weighting of the regulariser `k_r (s_i - 1)^2`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Regulariser {
    /// Weighted by input face area over the mean face area (default).
    #[default]
    Area,
    /// Unweighted, as printed in the paper.
    Uniform,
}

/// One constraint in scale-factor form: `sum_f coeffs_f s_f^degree / target - 1`.
pub struct ScaleConstraint {
    pub coeffs: Vec<(u32, f64)>,
    pub degree: i32,
    pub target: f64,
    pub group: usize,
}

impl ScaleConstraint {
    /// `C(s)`.
    pub fn value(&self, s: &[f64]) -> f64 {
        let sum: f64 = self
            .coeffs
            .iter()
            .map(|&(f, c)| c * power(s[f as usize], self.degree))
            .sum();
        sum / self.target - 1.0
    }
    /// Adds `dC/ds` into `out`.
    pub fn gradient(&self, s: &[f64], out: &mut [f64]) {
        let p = self.degree as f64;
        for &(f, c) in &self.coeffs {
            out[f as usize] += p * c * power(s[f as usize], self.degree - 1) / self.target;
        }
    }
}

/// `s^p` for a metric's degree: its products for `p` up to 3 (what `powi`
/// computes, without the call `powi` makes for an exponent not known at
/// compile time: a volume's row evaluates it on every face, every Newton step).
#[inline]
fn power(s: f64, p: i32) -> f64 {
    match p {
        0 => 1.0,
        1 => s,
        2 => s * s,
        3 => s * s * s,
        _ => s.powi(p),
    }
}

/// The per-kind grouping of `constraints` at `s` ([`add_to_group`], as
/// `Linearized::grouped` sums it): returns the groups' values and leaves
/// their rows in `rows`, group g at `g n..(g + 1) n`.
fn grouped_rows(
    constraints: &[ScaleConstraint],
    s: &[f64],
    values: Vec<f64>,
    groups: &[usize],
    rows: &mut Vec<f64>,
) -> Vec<f64> {
    let n = s.len();
    let ng = group_count(groups);
    let mut grouped = vec![0.0; ng];
    rows.clear();
    rows.resize(n * ng, 0.0);
    let mut row = vec![0.0; n];
    for ((c, &g), &v) in constraints.iter().zip(groups).zip(&values) {
        row.iter_mut().for_each(|r| *r = 0.0);
        c.gradient(s, &mut row);
        add_to_group(v, &row, &mut grouped[g], &mut rows[g * n..(g + 1) * n]);
    }
    grouped
}

/// Outcome of one estimation.
#[derive(Debug, Clone, Default)]
pub struct ScaleInfo {
    pub newton_iterations: usize,
    pub max_residual: f64,
}

/// The prefactored scale-factor system of one mesh.
pub struct ScaleFactorSystem {
    n: usize,
    solver: Box<dyn SpdSolver>,
    /// The Jacobian rows `Y`'s columns were last solved for, row j at
    /// `j n..(j + 1) n`.
    rows: Vec<f64>,
    /// `Y = H^-1 L^T` of those rows, column j at `j n..(j + 1) n` (also the
    /// initial guess of an iterative solver when a row changes).
    ycols: Vec<f64>,
    /// The buffers a Newton step builds its rows and its `y` in, kept from
    /// one estimation to the next: at a million faces they are tens of MB,
    /// which a fresh allocation would fault in page by page every time.
    spare_rows: Vec<f64>,
    spare_y: Vec<f64>,
}

impl ScaleFactorSystem {
    /// Work of its solver so far.
    pub fn counters(&self) -> solver_cpu::WorkCounters {
        self.solver.counters()
    }

    /// Assemble and factor `2 k_d L_Q + 2 k_r diag(rho)` (Hessian of Eq. 3)
    /// with `solver`.
    pub fn with_solver(
        face_pairs: &[[u32; 2]],
        areas: &[f64],
        k_d: f64,
        k_r: f64,
        reg: Regulariser,
        solver: Box<dyn SpdSolver>,
    ) -> Result<Self> {
        Self::with_hessian(Self::hessian(face_pairs, areas, k_d, k_r, reg), solver)
    }

    /// The system of [`Self::hessian`]'s `h`, factored (or uploaded) by
    /// `solver`.
    pub fn with_hessian(h: SymCsc, mut solver: Box<dyn SpdSolver>) -> Result<Self> {
        solver.prepare(&h)?;
        Ok(ScaleFactorSystem {
            n: h.n,
            solver,
            rows: Vec::new(),
            ycols: Vec::new(),
            spare_rows: Vec::new(),
            spare_y: Vec::new(),
        })
    }

    /// `2 k_d L_Q + 2 k_r diag(rho)`, the constant Hessian of Eq. 3 on the
    /// faces' adjacency `face_pairs`.
    pub fn hessian(
        face_pairs: &[[u32; 2]],
        areas: &[f64],
        k_d: f64,
        k_r: f64,
        reg: Regulariser,
    ) -> SymCsc {
        let n = areas.len();
        let mut h =
            SymCsc::from_pattern(n, face_pairs.iter().map(|p| (p[0] as usize, p[1] as usize)));
        let mean = areas.iter().sum::<f64>() / n.max(1) as f64;
        let k_r = if k_r > 0.0 { k_r } else { 1e-8 };
        for i in 0..n {
            let rho = match reg {
                Regulariser::Area => (areas[i] / mean).max(1e-6),
                Regulariser::Uniform => 1.0,
            };
            let sl = h.slot(i, i).unwrap();
            h.values[sl] += 2.0 * k_r * rho;
        }
        for p in face_pairs {
            let (a, b) = (p[0] as usize, p[1] as usize);
            let d = 2.0 * k_d;
            let sa = h.slot(a, a).unwrap();
            h.values[sa] += d;
            let sb = h.slot(b, b).unwrap();
            h.values[sb] += d;
            let sab = h.slot(a, b).unwrap();
            h.values[sab] -= d;
        }
        h
    }

    /// Make `ycols` the solutions `H^-1 r` of the Jacobian rows `next` (row j
    /// at `j n..(j + 1) n`): the columns whose row changed since they were
    /// solved are solved together (their previous solutions the initial
    /// guess), the others kept. `next` receives the previous rows, so that the
    /// caller builds the following step's rows in memory already touched, and
    /// an all-changed or one-changed solve reads them and writes `ycols` in
    /// place (no copies; the time saved was within the development machine's
    /// drift, 2026-11-25).
    fn jacobian_solutions(&mut self, next: &mut Vec<f64>, k: usize) -> Result<()> {
        let n = self.n;
        if self.rows.len() != n * k || self.ycols.len() != n * k {
            // Every column counts as changed.
            self.rows.clear();
            self.ycols = vec![0.0; n * k];
        }
        let changed: Vec<usize> = (0..k)
            .filter(|&j| self.rows.get(j * n..(j + 1) * n) != Some(&next[j * n..(j + 1) * n]))
            .collect();
        let solved = match changed[..] {
            [] => Ok(()),
            // One column (a volume's or an area's row, at every Newton step
            // after the first): solved in place, its row the right-hand side.
            [j] => self
                .solver
                .solve_with_guess(
                    &next[j * n..(j + 1) * n],
                    &mut self.ycols[j * n..(j + 1) * n],
                    1,
                )
                .map(|_| ()),
            // All of them (every estimation's first step): in place too.
            _ if changed.len() == k => self
                .solver
                .solve_with_guess(next, &mut self.ycols, k)
                .map(|_| ()),
            _ => {
                let mut rhs = Vec::with_capacity(n * changed.len());
                let mut x = Vec::with_capacity(n * changed.len());
                for &j in &changed {
                    rhs.extend_from_slice(&next[j * n..(j + 1) * n]);
                    x.extend_from_slice(&self.ycols[j * n..(j + 1) * n]);
                }
                let solved = self.solver.solve_with_guess(&rhs, &mut x, changed.len());
                if solved.is_ok() {
                    for (c, &j) in changed.iter().enumerate() {
                        self.ycols[j * n..(j + 1) * n].copy_from_slice(&x[c * n..(c + 1) * n]);
                    }
                }
                solved.map(|_| ())
            }
        };
        if let Err(e) = solved {
            self.rows.clear();
            self.ycols.clear();
            return Err(e.into());
        }
        std::mem::swap(&mut self.rows, next);
        Ok(())
    }

    /// Solve Eq. 3 by sequential linearly constrained Newton steps from `s = 1`.
    pub fn estimate(
        &mut self,
        constraints: &[ScaleConstraint],
        mode: Multipliers,
    ) -> Result<(Vec<f64>, ScaleInfo)> {
        let n = self.n;
        let mut s = vec![1.0; n];
        let mut info = ScaleInfo::default();
        let groups: Vec<usize> = constraints.iter().map(|c| c.group).collect();
        let max_iter = match mode {
            Multipliers::PerConstraint => 30,
            Multipliers::PerKind => 60,
        };
        // The same steps on the solver's device, where it takes them (the
        // GPU: no host round trip between the steps).
        if mode == Multipliers::PerConstraint {
            let sums: Vec<PowerSum> = constraints
                .iter()
                .map(|c| PowerSum {
                    coeffs: &c.coeffs,
                    degree: c.degree,
                    target: c.target,
                })
                .collect();
            let rules = NewtonRules {
                max_steps: max_iter,
                residual: RESIDUAL,
                moved: MOVED,
                floor: FLOOR,
            };
            if let Some(done) = self.solver.power_sum_newton(&sums, &rules, &mut s) {
                let done = done?;
                info.newton_iterations = done.steps;
                info.max_residual = done.max_residual;
                return Ok((s, info));
            }
        }
        // The rows of the step being built (the previous step's buffer).
        let mut next = std::mem::take(&mut self.spare_rows);
        for it in 0..max_iter {
            let values: Vec<f64> = constraints.iter().map(|c| c.value(&s)).collect();
            let max_res = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            info.max_residual = max_res;
            info.newton_iterations = it;
            if max_res < RESIDUAL {
                break;
            }
            let values = match mode {
                Multipliers::PerConstraint => {
                    next.clear();
                    next.resize(n * values.len(), 0.0);
                    for (c, row) in constraints.iter().zip(next.chunks_mut(n.max(1))) {
                        c.gradient(&s, row);
                    }
                    values
                }
                Multipliers::PerKind => grouped_rows(constraints, &s, values, &groups, &mut next),
            };
            let k = values.len();
            self.jacobian_solutions(&mut next, k)?;
            // y = H^-1 (-grad E) = 1 - s: the smoothness term vanishes on
            // constants, so grad E = H (s - 1).
            let mut y = std::mem::take(&mut self.spare_y);
            y.clear();
            y.extend(s.iter().map(|v| 1.0 - v));
            let rows: Vec<&[f64]> = self.rows.chunks(n.max(1)).take(k).collect();
            let step = step_from_solutions(y, &values, &rows, &self.ycols)?;
            // Keep every scale factor positive (a face cannot be scaled through zero).
            let mut alpha: f64 = 1.0;
            for i in 0..n {
                if step.dx[i] < 0.0 {
                    let lim = (s[i] - FLOOR) / -step.dx[i];
                    alpha = alpha.min(0.9 * lim.max(0.0));
                }
            }
            let mut moved = 0.0f64;
            for i in 0..n {
                s[i] += alpha * step.dx[i];
                moved = moved.max((alpha * step.dx[i]).abs());
            }
            info.newton_iterations = it + 1;
            // The step's buffer is the next step's `y`.
            self.spare_y = step.dx;
            if moved < MOVED {
                break;
            }
        }
        self.spare_rows = next;
        info.max_residual = constraints
            .iter()
            .map(|c| c.value(&s).abs())
            .fold(0.0, f64::max);
        Ok((s, info))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::constrained_step::Linearized;
    use solver_cpu::{CholeskySolver, SolveInfo, SolverError, WorkCounters};
    use std::sync::{Arc, Mutex};

    /// A direct solver that records how many columns each solve had.
    struct Columns(CholeskySolver, Arc<Mutex<Vec<usize>>>);

    impl SpdSolver for Columns {
        fn prepare(&mut self, a: &SymCsc) -> std::result::Result<(), SolverError> {
            self.0.prepare(a)
        }
        fn prepare_blocks(
            &mut self,
            a: &solver_cpu::BlockSym3,
            fixed: &[bool],
        ) -> std::result::Result<(), SolverError> {
            self.0.prepare_blocks(a, fixed)
        }
        fn solve_in_place(
            &mut self,
            rhs: &mut [f64],
            ncols: usize,
        ) -> std::result::Result<SolveInfo, SolverError> {
            self.1.lock().unwrap().push(ncols);
            self.0.solve_in_place(rhs, ncols)
        }
        fn counters(&self) -> WorkCounters {
            self.0.counters()
        }
        fn name(&self) -> &str {
            "columns"
        }
    }

    /// A strip of `n` faces, each adjacent to the next, of growing areas.
    fn strip(n: usize, solver: Box<dyn SpdSolver>) -> (ScaleFactorSystem, SymCsc) {
        let pairs: Vec<[u32; 2]> = (1..n as u32).map(|f| [f - 1, f]).collect();
        let areas: Vec<f64> = (0..n).map(|f| 1.0 + 0.1 * f as f64).collect();
        let sys =
            ScaleFactorSystem::with_solver(&pairs, &areas, 1.0, 0.1, Regulariser::Area, solver)
                .unwrap();
        // The same Hessian, for the optimality check.
        let mut h = SymCsc::from_pattern(n, pairs.iter().map(|p| (p[0] as usize, p[1] as usize)));
        let mean = areas.iter().sum::<f64>() / n as f64;
        for (i, a) in areas.iter().enumerate() {
            let sl = h.slot(i, i).unwrap();
            h.values[sl] += 0.2 * a / mean;
        }
        for p in &pairs {
            let (a, b) = (p[0] as usize, p[1] as usize);
            for (r, c, v) in [(a, a, 2.0), (b, b, 2.0), (a, b, -2.0)] {
                let sl = h.slot(r, c).unwrap();
                h.values[sl] += v;
            }
        }
        (sys, h)
    }

    /// `sys`'s estimation of `constraints`, which must solve `first` columns
    /// at its first Newton step and `later` at each later one (counted by
    /// `solved`), in at least three steps, and land where the same Newton
    /// steps with every column solved, `H^-1 (-grad E)` included (Eq. 16 as
    /// printed), land (to 1e-12), having moved `s` by more than 0.05.
    fn estimate_as_every_column_solved(
        sys: &mut ScaleFactorSystem,
        solved: &Mutex<Vec<usize>>,
        h: &SymCsc,
        constraints: &[ScaleConstraint],
        first: usize,
        later: usize,
    ) -> Vec<f64> {
        let (s, info) = sys
            .estimate(constraints, Multipliers::PerConstraint)
            .unwrap();
        assert!(info.max_residual < 1e-12, "{info:?}");
        assert!(info.newton_iterations >= 3, "{info:?}");
        let calls = solved.lock().unwrap().clone();
        assert_eq!(calls.len(), info.newton_iterations, "{calls:?}");
        assert_eq!(calls[0], first, "{calls:?}");
        assert!(calls[1..].iter().all(|&c| c == later), "{calls:?}");
        let r = every_column_solved(h, constraints, info.newton_iterations);
        let apart = s
            .iter()
            .zip(&r)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let moved = s.iter().map(|v| (v - 1.0).abs()).fold(0.0, f64::max);
        assert!(moved > 0.05, "the constraints move s: {moved}");
        assert!(apart < 1e-12, "{apart:e} from the reference");
        s
    }

    /// `steps` Newton steps from `s = 1` with every column solved, `H^-1
    /// (-grad E)` included (Eq. 16 as printed), by the direct solver.
    fn every_column_solved(h: &SymCsc, constraints: &[ScaleConstraint], steps: usize) -> Vec<f64> {
        let n = h.n;
        let mut reference = CholeskySolver::new();
        reference.prepare(h).unwrap();
        let mut r = vec![1.0; n];
        let mut warm = Vec::new();
        for _ in 0..steps {
            let rm1: Vec<f64> = r.iter().map(|v| v - 1.0).collect();
            let mut grad = vec![0.0; n];
            h.mul_vec(&rm1, &mut grad);
            let lin = Linearized {
                values: constraints.iter().map(|c| c.value(&r)).collect(),
                rows: constraints
                    .iter()
                    .map(|c| {
                        let mut row = vec![0.0; n];
                        c.gradient(&r, &mut row);
                        row
                    })
                    .collect(),
            };
            let neg = grad.iter().map(|g| -g).collect();
            let step =
                crate::constrained_step::constrained_step_warm(&mut reference, neg, lin, &mut warm)
                    .unwrap();
            assert!(step.dx.iter().all(|d| *d > -0.5), "no step is clipped here");
            r.iter_mut().zip(&step.dx).for_each(|(v, d)| *v += d);
        }
        r
    }

    #[test]
    fn newton_steps_solve_only_the_jacobian_columns_that_changed() {
        let n = 40;
        let solved = Arc::new(Mutex::new(Vec::new()));
        let (mut sys, h) = strip(n, Box::new(Columns(CholeskySolver::new(), solved.clone())));
        let constraints = [
            // A length (degree 1: its row does not depend on s), 20 % longer.
            ScaleConstraint {
                coeffs: (0..20).map(|f| (f, 1.0)).collect(),
                degree: 1,
                target: 24.0,
                group: 0,
            },
            // An area (degree 2), 30 % smaller.
            ScaleConstraint {
                coeffs: (10..40).map(|f| (f, 1.0 + 0.01 * f as f64)).collect(),
                degree: 2,
                target: 0.7 * (10..40).map(|f| 1.0 + 0.01 * f as f64).sum::<f64>(),
                group: 1,
            },
        ];
        // Both columns once, then the area's alone at every later step; no
        // solve for H^-1 grad E.
        let s = estimate_as_every_column_solved(&mut sys, &solved, &h, &constraints, 2, 1);
        // A second estimation with the same constraints starts from s = 1:
        // its first step's rows differ from the last ones (the area's), except
        // the length's, which is kept.
        solved.lock().unwrap().clear();
        let (s2, _) = sys
            .estimate(&constraints, Multipliers::PerConstraint)
            .unwrap();
        assert_eq!(s, s2);
        assert!(solved.lock().unwrap().iter().all(|&c| c == 1));
    }

    #[test]
    fn newton_steps_gather_the_columns_that_changed_among_kept_ones() {
        let n = 40;
        let solved = Arc::new(Mutex::new(Vec::new()));
        let (mut sys, h) = strip(n, Box::new(Columns(CholeskySolver::new(), solved.clone())));
        let constraints = [
            // An area (degree 2), 20 % larger.
            ScaleConstraint {
                coeffs: (0..25).map(|f| (f, 1.0 + 0.02 * f as f64)).collect(),
                degree: 2,
                target: 1.2 * (0..25).map(|f| 1.0 + 0.02 * f as f64).sum::<f64>(),
                group: 0,
            },
            // A length (degree 1: its column is kept after the first step),
            // 10 % shorter.
            ScaleConstraint {
                coeffs: (15..40).map(|f| (f, 1.0)).collect(),
                degree: 1,
                target: 0.9 * 25.0,
                group: 1,
            },
            // A volume (degree 3), kept.
            ScaleConstraint {
                coeffs: (5..35).map(|f| (f, 0.5)).collect(),
                degree: 3,
                target: 15.0,
                group: 2,
            },
        ];
        // All three columns, then the area's and the volume's together (the
        // length's between them kept) at every later step.
        estimate_as_every_column_solved(&mut sys, &solved, &h, &constraints, 3, 2);
    }

    #[test]
    fn grouped_rows_are_the_linearized_grouping_to_the_bit() {
        let n = 30;
        let s: Vec<f64> = (0..n).map(|f| 0.8 + 0.013 * f as f64).collect();
        // Two lengths in group 0 (one with a face listed twice), a volume in
        // group 1, an area in group 0 again: groups out of order.
        let constraints = [
            ScaleConstraint {
                coeffs: (0..12).map(|f| (f, 1.0 + 0.1 * f as f64)).collect(),
                degree: 1,
                target: 9.0,
                group: 0,
            },
            ScaleConstraint {
                coeffs: vec![(3, 0.5), (4, 0.25), (3, 0.75)],
                degree: 1,
                target: 1.7,
                group: 0,
            },
            ScaleConstraint {
                coeffs: (5..30).map(|f| (f, 0.3)).collect(),
                degree: 3,
                target: 4.0,
                group: 1,
            },
            ScaleConstraint {
                coeffs: (10..20).map(|f| (f, 2.0)).collect(),
                degree: 2,
                target: 21.0,
                group: 0,
            },
        ];
        let groups: Vec<usize> = constraints.iter().map(|c| c.group).collect();
        let values: Vec<f64> = constraints.iter().map(|c| c.value(&s)).collect();
        let lin = Linearized {
            values: values.clone(),
            rows: constraints
                .iter()
                .map(|c| {
                    let mut r = vec![0.0; n];
                    c.gradient(&s, &mut r);
                    r
                })
                .collect(),
        }
        .grouped(&groups);
        // A buffer holding an earlier step's rows, longer than needed.
        let mut rows = vec![7.0; 5 * n];
        let got = grouped_rows(&constraints, &s, values, &groups, &mut rows);
        assert_eq!(got.len(), 2);
        assert_eq!(rows.len(), 2 * n);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got), bits(&lin.values));
        for g in 0..2 {
            assert_eq!(
                bits(&rows[g * n..(g + 1) * n]),
                bits(&lin.rows[g]),
                "group {g}"
            );
        }
        assert!(rows[..n].iter().any(|&r| r != 0.0) && rows[n..].iter().any(|&r| r != 0.0));
    }

    #[test]
    fn power_is_powi_to_the_bit() {
        for &s in &[
            0.05,
            0.3,
            0.999_999_9,
            1.0,
            1.000_000_1,
            1.7,
            3.25,
            1e-3,
            7e2,
        ] {
            for p in 0..=5 {
                assert_eq!(power(s, p).to_bits(), s.powi(p).to_bits(), "{s}^{p}");
            }
        }
    }
}
