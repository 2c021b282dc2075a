//! The fine-tune (paper Eq. 8, Sec. 4): the metrics as hard constraints on
//! the shape energy, solved by sequential linearly constrained Newton steps
//! ([`crate::constrained_step`], Eqs. 15-18) on one factored Hessian, with an
//! exact-penalty line search.

use crate::constrained_step::{
    constrained_step_given, constrained_step_stacked, constrained_step_warm, Linearized,
    Multipliers,
};
use crate::problem::Problem;
use crate::shape::{ShapeModel, ShapeWeights};
use crate::Result;
use glam::DVec3;
use rayon::prelude::*;
use solver_cpu::SystemKind;

/// The fine-tune's settings.
#[derive(Debug, Clone, Copy)]
pub struct FineTuneParams {
    /// The shape weights of Eq. 8 (the paper's k_f, k_m, k_l = 1, 100, 100).
    pub weights: ShapeWeights,
    /// The run's relative metric tolerance; the fine-tune aims at 1 % of it.
    pub tolerance: f64,
    /// Most Newton steps.
    pub max_iterations: usize,
    pub multipliers: Multipliers,
}

/// Eq. 8 (and Eq. 20 with handles): minimise the shape energy relative to
/// the scale-driven result `xstart` subject to the metrics as hard
/// constraints. `groups[j]` is constraint j's multiplier group (used with
/// [`Multipliers::PerKind`]); `progress(iteration, max_error)` is called
/// before each step, and an error it returns stops the fine-tune. Returns the positions and the steps taken.
pub fn fine_tune(
    p: &Problem,
    params: &FineTuneParams,
    model: &mut ShapeModel,
    groups: &[usize],
    xstart: &[DVec3],
    progress: &mut dyn FnMut(usize, f64) -> Result<()>,
) -> Result<(Vec<DVec3>, usize)> {
    let mesh = &p.mesh;
    let n = mesh.num_vertices();
    let nf = mesh.num_faces();
    let ones_f = vec![1.0; nf];
    let ones_v = vec![1.0; n];
    // One factorization for the whole fine-tune (symbolic analysis reused).
    crate::memory::release_free_memory();
    model.solver().set_system_kind(SystemKind::FineTune);
    // The fine-tune Hessian (k_m = k_l = 100 k_f) is nearly blind to local
    // affine motions: an AMG of the matrix itself (the GPU's `affine-amg`)
    // takes them as its near-null space (4-7x fewer GPU PCG iterations on
    // spot, BENCHMARKS.md); the GPU's default squared Laplacian ignores them.
    model.assemble_with_positions(mesh, xstart, &ones_f, &ones_v, &params.weights, true)?;
    let goal = 0.01 * params.tolerance;
    let mut dx = vec![0.0; 3 * n];
    // Each vertex apart, on rayon's threads (as the trials below).
    let apply = |dx: &[f64]| -> Vec<DVec3> {
        (0..n)
            .into_par_iter()
            .map(|v| xstart[v] + DVec3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]))
            .collect()
    };
    let mut x = xstart.to_vec();
    let mut mu: f64 = 0.0;
    let mut it = 0;
    let residuals = |x: &[DVec3]| -> Vec<f64> { crate::problem::residuals(p, x) };
    let merit = |energy: f64, c: &[f64], mu: f64| -> f64 {
        energy + mu * c.iter().map(|v| v.abs()).sum::<f64>()
    };
    let mut c = residuals(&x);
    // The energy at `dx`: 0 at the start, then the accepted trial's (each
    // is a product with `H`, 0.04-0.06 s at homer 1.2M: made once).
    let mut energy = 0.0;
    // Solutions of the previous Newton step: the initial guess of iterative solvers.
    let mut warm = Vec::new();
    // y0 = H^-1 (-g0), the first step's y. The energy is quadratic in dx
    // with gradient H dx + g0 (zero at held vertices, where dx is zero too),
    // so later steps' y = H^-1 (-grad E) is y0 - dx, with no solve.
    let mut y0: Option<Vec<f64>> = None;
    while it < params.max_iterations {
        let err = c.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        progress(it, err)?;
        if err <= goal {
            break;
        }
        let t_step = std::time::Instant::now();
        let t_rows;
        // The constraints' gradients (`L`'s rows, held dofs zero), at once.
        let gradient_into = |con: &crate::metrics::Constraint, r: &mut [f64]| {
            con.add_gradient(mesh, &x, 1.0 / con.target, r);
            for v in 0..n {
                if model.fixed[v] {
                    r[3 * v..3 * v + 3].iter_mut().for_each(|e| *e = 0.0);
                }
            }
        };
        let solve_y = y0.is_none();
        let y_given = |dx: &[f64]| -> Option<Vec<f64>> {
            y0.as_ref()
                .map(|y0| y0.iter().zip(dx).map(|(a, d)| a - d).collect())
        };
        let step = match params.multipliers {
            // The rows written straight into the right-hand sides, after
            // `-grad E` where `y` is solved: no copies.
            Multipliers::PerConstraint => {
                let first = usize::from(solve_y) * 3 * n;
                let mut rhs = vec![0.0; first + p.constraints.len() * 3 * n];
                let (neg, rows) = rhs.split_at_mut(first);
                rows.par_chunks_mut(3 * n)
                    .zip(&p.constraints)
                    .for_each(|(r, con)| gradient_into(con, r));
                if solve_y {
                    for (o, g) in neg.iter_mut().zip(model.gradient_at(&dx)) {
                        *o = -g;
                    }
                }
                t_rows = t_step.elapsed().as_secs_f64();
                constrained_step_stacked(model.solver(), y_given(&dx), &c, rhs, &mut warm)?
            }
            Multipliers::PerKind => {
                let rows: Vec<Vec<f64>> = p
                    .constraints
                    .iter()
                    .map(|con| {
                        let mut r = vec![0.0; 3 * n];
                        gradient_into(con, &mut r);
                        r
                    })
                    .collect();
                let lin = Linearized {
                    values: c.clone(),
                    rows,
                }
                .grouped(groups);
                t_rows = t_step.elapsed().as_secs_f64();
                match y_given(&dx) {
                    None => {
                        let neg: Vec<f64> = model.gradient_at(&dx).iter().map(|v| -v).collect();
                        constrained_step_warm(model.solver(), neg, lin, &mut warm)?
                    }
                    Some(y) => constrained_step_given(model.solver(), y, lin, &mut warm)?,
                }
            }
        };
        if solve_y {
            y0 = Some(warm.drain(..3 * n).collect());
        }
        let lam_max = match params.multipliers {
            Multipliers::PerConstraint => step.lambda.iter().fold(0.0f64, |m, l| m.max(l.abs())),
            Multipliers::PerKind => groups
                .iter()
                .zip(&c)
                .map(|(&g, cj)| (2.0 * step.lambda[g] * cj).abs())
                .fold(0.0, f64::max),
        };
        mu = mu.max(2.0 * lam_max + 1e-6);
        let t_solved = t_step.elapsed().as_secs_f64();
        let phi0 = merit(energy, &c, mu);
        let mut alpha = 1.0;
        let mut accepted = false;
        while alpha > 1.0 / 1024.0 {
            let trial: Vec<f64> = dx
                .par_iter()
                .zip(&step.dx)
                .map(|(a, b)| a + alpha * b)
                .collect();
            let xt = apply(&trial);
            let ct = residuals(&xt);
            let et = model.energy(&trial);
            if merit(et, &ct, mu) < phi0 {
                energy = et;
                dx = trial;
                x = xt;
                c = ct;
                accepted = true;
                break;
            }
            alpha *= 0.5;
        }
        it += 1;
        log::debug!(
            "fine-tune step {it}: step length {alpha}; the constraints' rows {t_rows:.3} s, \
             the step (its solves included) {:.3} s, the line search {:.3} s; resident {:.0} MiB \
             (peak {:.0})",
            t_solved - t_rows,
            t_step.elapsed().as_secs_f64() - t_solved,
            crate::memory::resident_memory_mb(),
            crate::memory::peak_memory_mb()
        );
        if !accepted {
            log::info!("fine-tune: line search stalled at iteration {it}");
            break;
        }
    }
    Ok((x, it))
}
