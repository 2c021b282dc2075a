//! Scale-factor estimation (paper Sec. 2.2, Eq. 3).
//!
//! `min_s  k_d sum_{(i,j) in Q} (s_i - s_j)^2 + k_r sum_i rho_i (s_i - 1)^2`
//! `s.t.   C_j(s) = sum_f c_jf s_f^p_j / T_j - 1 = 0`  (Eqs. 9, 11, 13: p = 1, 2, 3)
//!
//! `Q` is the set of adjacent face pairs, `rho_i = A_i / mean(A)` with input face
//! areas (pitfall (a): an unweighted regulariser makes `s` non-uniform and
//! resolution-dependent; `Regulariser::Uniform` keeps the paper's literal form).
//! The Hessian is constant for the whole run: it is factored once.

use crate::constrained_step::{constrained_step_warm, Linearized, Multipliers};
use crate::Result;
use solver_cpu::{SpdSolver, SymCsc};

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
            .map(|&(f, c)| c * s[f as usize].powi(self.degree))
            .sum();
        sum / self.target - 1.0
    }
    /// Adds `dC/ds` into `out`.
    pub fn gradient(&self, s: &[f64], out: &mut [f64]) {
        let p = self.degree as f64;
        for &(f, c) in &self.coeffs {
            out[f as usize] += p * c * s[f as usize].powi(self.degree - 1) / self.target;
        }
    }
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
    hessian: SymCsc,
    solver: Box<dyn SpdSolver>,
    /// Solutions of the last Newton step (initial guess of iterative solvers).
    warm: Vec<f64>,
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
        mut solver: Box<dyn SpdSolver>,
    ) -> Result<Self> {
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
        solver.prepare(&h)?;
        Ok(ScaleFactorSystem {
            n,
            hessian: h,
            solver,
            warm: Vec::new(),
        })
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
        let mut grad = vec![0.0; n];
        let mut sm1 = vec![0.0; n];
        for it in 0..max_iter {
            let values: Vec<f64> = constraints.iter().map(|c| c.value(&s)).collect();
            let max_res = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            info.max_residual = max_res;
            info.newton_iterations = it;
            if max_res < 1e-12 {
                break;
            }
            // grad E = H (s - 1): the smoothness term vanishes on constants.
            for i in 0..n {
                sm1[i] = s[i] - 1.0;
            }
            self.hessian.mul_vec(&sm1, &mut grad);
            let neg: Vec<f64> = grad.iter().map(|g| -g).collect();
            let rows: Vec<Vec<f64>> = constraints
                .iter()
                .map(|c| {
                    let mut r = vec![0.0; n];
                    c.gradient(&s, &mut r);
                    r
                })
                .collect();
            let mut lin = Linearized { values, rows };
            if mode == Multipliers::PerKind {
                lin = lin.grouped(&groups);
            }
            let step = constrained_step_warm(self.solver.as_mut(), neg, lin, &mut self.warm)?;
            // Keep every scale factor positive (a face cannot be scaled through zero).
            let mut alpha: f64 = 1.0;
            for i in 0..n {
                if step.dx[i] < 0.0 {
                    let lim = (s[i] - 0.05) / -step.dx[i];
                    alpha = alpha.min(0.9 * lim.max(0.0));
                }
            }
            let mut moved = 0.0f64;
            for i in 0..n {
                s[i] += alpha * step.dx[i];
                moved = moved.max((alpha * step.dx[i]).abs());
            }
            info.newton_iterations = it + 1;
            if moved < 1e-13 {
                break;
            }
        }
        info.max_residual = constraints
            .iter()
            .map(|c| c.value(&s).abs())
            .fold(0.0, f64::max);
        Ok((s, info))
    }
}
