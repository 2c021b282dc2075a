//! Candidate preconditioners for the GPU's shape systems (Eq. 7), counted in
//! f64 on the host: PCG iterations to a relative residual of 1e-8 on the real
//! shape system of spot refined 1, 2 and 3 times and of homer with every edge
//! cut in 3 (108k faces), every face asked to grow 10 %.
//!
//! The shape matrix is `A = K (x) I3 + sum_i L_i^T C_i L_i` (`IsoRingSym3`), and
//! its isotropic part `K` carries almost all of it: the CPU backend's exact
//! Cholesky of `K` needs 2-10 iterations. A GPU needs a preconditioner of `K`
//! whose set-up is cheap and whose application streams: not a factor. Two are
//! counted here, each applied to x, y and z as three scalar columns:
//!
//! * **`K`-AMG**: one smoothed-aggregation V-cycle ([`Hierarchy`]) of the
//!   scalar `K`. `K` is dominated by E_m's bi-Laplacian
//!   `S diag(m) S` (`S` the input's cotangent Laplacian, `m_i = k_m / (2 A_i)`),
//!   which aggregation coarsens poorly.
//! * **Factored**: with `Mt = diag(m)^-1`, `K ~ S Mt^-1 S + c S` (`c = 2 k_f / A`,
//!   E_f's Hessian being `c S` at the reference positions), preconditioned by
//!   `P = B^-1 Mt B^-1`, `B = S + eps Mt`, so that
//!   `P^-1 = S Mt^-1 S + 2 eps S + eps^2 Mt`; in the eigenbasis of `(S, Mt)` the
//!   ratio `(l^2 + c l) / (l + eps)^2` is bounded independently of the mesh, for
//!   `eps = max(sqrt(c lambda), lambda)` with `lambda = tau / sum(Mt)` an
//!   estimate of the smallest nonzero eigenvalue (`tau` = 50). The held vertex
//!   `v0` enters as `Pi P Pi^T` with `Pi = I - 1 e_v0^T` (the pinned system's
//!   inverse is `Pi K^+ Pi^T`). `B` is a screened Laplacian (an easy matrix for
//!   AMG) that depends on the input mesh only: built once per run, never
//!   refreshed. Each `B^-1` is approximated by `v` V-cycles (Richardson) of
//!   2 Jacobi sweeps before and after, or by one V-cycle of 4 sweeps.
//!
//! The last column is what the GPU runs (`solver_gpu::Preconditioner::
//! SquaredLaplacian`): held rows identity in `B` (Dirichlet) instead of `Pi`,
//! `squared_laplacian_vcycles(n)` V-cycles of `SQUARED_LAPLACIAN_SWEEPS` sweeps
//! per `B^-1` (`SWEEPS=.. VCYCLES=..` in the environment override them).
//!
//! `cargo bench --bench shape_preconditioner` (`-- --quick`: spot refined 1
//! and 2 times only; `-- --homer`: homer only; `-- --homer --homer-1m`: homer
//! with every edge cut in 10, 1.2M faces; `--gpu-form-only`: B alone and the
//! GPU's form only).

use metricdeform::shape::{cotangent_laplacian, vertex_areas, ShapeModel, ShapeWeights};
use metricdeform::Mesh;
use solver_gpu::amg::{squared_laplacian, AmgOptions, Bsr, Hierarchy, SQUARED_LAPLACIAN_TAU};
use std::path::Path;

/// A test mesh: spot refined `k` times 1-to-4 (`k` > 0), or homer with every
/// edge cut in 3 (`k` = 0: the pipeline bench's 108k-face row).
fn load(k: usize) -> (String, Mesh) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    if k == 0 || k == 10 {
        let cut = if k == 0 { 3 } else { 10 };
        let mesh = metricdeform::mesh::io::read_mesh(&dir.join("homer.obj")).unwrap();
        return (format!("homer x{}", cut * cut), mesh.subdivide_uniform(cut));
    }
    let mut mesh = metricdeform::mesh::io::read_mesh(&dir.join("spot.obj")).unwrap();
    for _ in 0..k {
        mesh = mesh.subdivide_midpoint();
    }
    (format!("spot x{}", 4usize.pow(k as u32)), mesh)
}

/// PCG iterations to `||r|| <= tol ||b||` (None past `max`).
fn pcg(
    op: &dyn Fn(&[f64], &mut [f64]),
    b: &[f64],
    tol: f64,
    max: usize,
    prec: &dyn Fn(&[f64]) -> Vec<f64>,
) -> Option<usize> {
    solver_gpu::amg::pcg_op(op, b, tol, max, prec).map(|(_, it)| it)
}

/// `v` V-cycles of `h` on `B x = r` from zero (a fixed symmetric operator).
fn vcycles(h: &Hierarchy, b: &Bsr, r: &[f64], v: usize) -> Vec<f64> {
    let mut x = h.vcycle(r);
    let mut t = vec![0.0; r.len()];
    for _ in 1..v {
        b.matvec(&x, &mut t);
        t.iter_mut().zip(r).for_each(|(t, r)| *t = r - *t);
        let d = h.vcycle(&t);
        x.iter_mut().zip(&d).for_each(|(x, d)| *x += d);
    }
    x
}

/// A scalar preconditioner applied to x, y and z of the 3n-vector `r`.
fn per_component(n: usize, scalar: &dyn Fn(&[f64]) -> Vec<f64>, r: &[f64]) -> Vec<f64> {
    let mut z = vec![0.0; 3 * n];
    for c in 0..3 {
        let rc: Vec<f64> = (0..n).map(|i| r[3 * i + c]).collect();
        for (i, v) in scalar(&rc).into_iter().enumerate() {
            z[3 * i + c] = v;
        }
    }
    z
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    // The GPU's form: sweeps and V-cycles per B^-1 (the solver's choices,
    // or SWEEPS / VCYCLES from the environment to compare others).
    let env = |k: &str, d: usize| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let gpu_sweeps = env("SWEEPS", solver_gpu::SQUARED_LAPLACIAN_SWEEPS);
    let w = ShapeWeights {
        k_f: 1000.0,
        k_m: 1.0,
        k_l: 1.0,
        k_p: 1000.0,
    };
    println!(
        "| mesh | faces | K-AMG | B alone | factored, 1 V-cycle | 2 | 3 | 4 | 8 (about exact) | 1 V-cycle, 4 sweeps | the GPU's form |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let only_homer = std::env::args().any(|a| a == "--homer");
    let levels: &[usize] = match (quick, only_homer) {
        (_, true) if std::env::args().any(|a| a == "--homer-1m") => &[10],
        (_, true) => &[0],
        (true, _) => &[1, 2],
        _ => &[1, 2, 3, 0],
    };
    for &sub in levels {
        let (name, mesh) = load(sub);
        let topo = metricdeform::mesh::topology::Topology::build(&mesh);
        let mut model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
        let (nf, n) = (mesh.num_faces(), mesh.num_vertices());
        let gpu_vcycles = env("VCYCLES", solver_gpu::squared_laplacian_vcycles(n));
        eprintln!("{name}, the GPU's form: {gpu_vcycles} V-cycles of {gpu_sweeps} sweeps per B^-1");
        model
            .assemble_and_factor(&mesh, &mesh.positions, &vec![1.1; nf], &vec![1.1; n], &w)
            .unwrap();
        let (iso, fixed) = model.system();
        let held = |v: usize| fixed[v];
        let mut b: Vec<f64> = model.reference_gradient().iter().map(|g| -g).collect();
        for v in (0..n).filter(|&v| held(v)) {
            b[3 * v..3 * v + 3].fill(0.0);
        }
        if std::env::args().any(|a| a == "--floor") {
            // The GPU solver's f64 rounding floor eps ||A|| ||x|| / ||b|| of
            // this system (||A||_2 by power iterations, <= ||A||_inf).
            let mut q: Vec<f64> = (0..3 * n)
                .map(|i| ((i as f64 * 12.9898).sin() * 43758.5453).fract() - 0.5)
                .collect();
            let mut aq = vec![0.0; 3 * n];
            let mut a2 = 0.0;
            for _ in 0..30 {
                let qn = q.iter().map(|v| v * v).sum::<f64>().sqrt();
                q.iter_mut().for_each(|v| *v /= qn);
                iso.mul_vec(&q, &mut aq);
                a2 = aq.iter().map(|v| v * v).sum::<f64>().sqrt();
                std::mem::swap(&mut q, &mut aq);
            }
            let mut x = b.clone();
            let mut model2 = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
            model2
                .assemble_and_factor(&mesh, &mesh.positions, &vec![1.1; nf], &vec![1.1; n], &w)
                .unwrap();
            model2.solver().solve_in_place(&mut x, 1).unwrap();
            let nrm = |v: &[f64]| v.iter().map(|v| v * v).sum::<f64>().sqrt();
            eprintln!(
                "{name}: ||A||_2 ~ {a2:.3e}, ||x|| {:.3e}, ||b|| {:.3e}, floor eps ||A|| ||x|| / ||b|| = {:.3e}",
                nrm(&x),
                nrm(&b),
                f64::EPSILON * a2 * nrm(&x) / nrm(&b)
            );
            continue;
        }
        // The shape system with held rows and columns identity.
        let op = |x: &[f64], y: &mut [f64]| {
            let mut xm = x.to_vec();
            for v in (0..n).filter(|&v| held(v)) {
                xm[3 * v..3 * v + 3].fill(0.0);
            }
            iso.mul_vec(&xm, y);
            for v in (0..n).filter(|&v| held(v)) {
                y[3 * v..3 * v + 3].copy_from_slice(&x[3 * v..3 * v + 3]);
            }
        };
        // K-AMG.
        let k = &iso.iso;
        let mut rows: Vec<Vec<(u32, f64)>> = vec![Vec::new(); n];
        for j in 0..n {
            for s in k.col_ptr[j]..k.col_ptr[j + 1] {
                let i = k.row_idx[s];
                if held(i) || held(j) {
                    if i == j {
                        rows[i].push((i as u32, 1.0));
                    }
                    continue;
                }
                rows[i].push((j as u32, k.values[s]));
                if i != j {
                    rows[j].push((i as u32, k.values[s]));
                }
            }
        }
        let kb = Bsr::scalar_from_rows(rows);
        let hk = Hierarchy::build(kb, &AmgOptions::default(), None).unwrap();
        // `--gpu-form-only`: B alone and the GPU's form (the other columns
        // take hours at 1.2M faces on two cores).
        let full = !std::env::args().any(|a| a == "--gpu-form-only");
        let k_amg = full.then(|| {
            pcg(&op, &b, 1e-8, 3000, &|r| {
                per_component(n, &|q| hk.vcycle(q), r)
            })
        });

        // Factored.
        let area = vertex_areas(&mesh, &mesh.positions);
        let total: f64 = area.iter().sum();
        let c = 2.0 * w.k_f / total;
        let mt: Vec<f64> = area.iter().map(|a| 2.0 * a / w.k_m).collect();
        let lambda = 50.0 / mt.iter().sum::<f64>();
        let eps = (c * lambda).sqrt().max(lambda);
        let cot = cotangent_laplacian(&mesh, &mesh.positions);
        let bm = Bsr::scalar_from_rows(
            (0..n)
                .map(|i| {
                    let mut r: Vec<(u32, f64)> = cot.row(i).map(|(j, v)| (j as u32, v)).collect();
                    r[0].1 += eps * mt[i];
                    r
                })
                .collect(),
        );
        let opts = AmgOptions {
            sweeps: 2,
            ..AmgOptions::default()
        };
        let hb = Hierarchy::build(bm.clone(), &opts, None).unwrap();
        let bop = |x: &[f64], y: &mut [f64]| bm.matvec(x, y);
        let rb: Vec<f64> = (0..n).map(|i| b[3 * i + 1]).collect();
        let b_alone = pcg(&bop, &rb, 1e-8, 3000, &|r| hb.vcycle(r));
        let v0 = (0..n).find(|&v| held(v)).expect("a held vertex");
        let hb4 = Hierarchy::build(
            bm.clone(),
            &AmgOptions {
                sweeps: 4,
                ..AmgOptions::default()
            },
            None,
        )
        .unwrap();
        let factored_with = |hb: &Hierarchy, v: usize| {
            let scalar = |r: &[f64]| -> Vec<f64> {
                let mut t = r.to_vec();
                let s: f64 = t.iter().sum();
                t[v0] -= s;
                let mut y = vcycles(hb, &bm, &t, v);
                y.iter_mut().zip(&mt).for_each(|(y, m)| *y *= m);
                let y = vcycles(hb, &bm, &y, v);
                (0..n)
                    .map(|i| if held(i) { 0.0 } else { y[i] - y[v0] })
                    .collect()
            };
            pcg(&op, &b, 1e-8, 3000, &|r| per_component(n, &scalar, r))
        };
        let factored = |v: usize| full.then(|| factored_with(&hb, v));
        // What the GPU runs: held rows identity in B instead of Pi, 4 sweeps.
        let model = solver_cpu::ShapeOperatorModel {
            laplacian: std::sync::Arc::new(cot.clone()),
            mt: mt.clone(),
            c,
        };
        let (bg, mtg) = squared_laplacian(&model, fixed, SQUARED_LAPLACIAN_TAU);
        let hg = Hierarchy::build(
            bg.clone(),
            &AmgOptions {
                sweeps: gpu_sweeps,
                ..AmgOptions::default()
            },
            None,
        )
        .unwrap();
        if std::env::args().any(|a| a == "--rho") {
            // The V-cycle's contraction on B: Richardson on B e = 0 from a
            // pseudo-random e, the B-norm of e per cycle.
            let bn = |e: &[f64]| {
                let mut t = vec![0.0; e.len()];
                bg.matvec(e, &mut t);
                t.iter().zip(e).map(|(a, b)| a * b).sum::<f64>().sqrt()
            };
            let mut e: Vec<f64> = (0..n)
                .map(|i| ((i as f64 * 12.9898).sin() * 43758.5453).fract() - 0.5)
                .collect();
            let mut t = vec![0.0; n];
            let mut last = bn(&e);
            let levels: Vec<String> = hg
                .levels
                .iter()
                .map(|l| {
                    format!(
                        "omega {:.3}, {} rows in no aggregate",
                        l.omega,
                        l.agg.iter().filter(|&&g| g == u32::MAX).count()
                    )
                })
                .collect();
            eprintln!(
                "{name}: B sizes {:?}, operator complexity {:.2}, levels {levels:?}",
                hg.sizes(),
                hg.operator_complexity()
            );
            for k in 0..12 {
                bg.matvec(&e, &mut t);
                t.iter_mut().for_each(|v| *v = -*v);
                let d = hg.vcycle(&t);
                e.iter_mut().zip(&d).for_each(|(e, d)| *e += d);
                let now = bn(&e);
                eprintln!("{name}: V-cycle {}: B-norm ratio {:.4}", k + 1, now / last);
                last = now;
            }
            continue;
        }
        let gpu_form = {
            let scalar = |r: &[f64]| -> Vec<f64> {
                let t: Vec<f64> = (0..n).map(|i| if held(i) { 0.0 } else { r[i] }).collect();
                let mut y = vcycles(&hg, &bg, &t, gpu_vcycles);
                y.iter_mut().zip(&mtg).for_each(|(y, m)| *y *= m);
                let y = vcycles(&hg, &bg, &y, gpu_vcycles);
                (0..n).map(|i| if held(i) { 0.0 } else { y[i] }).collect()
            };
            pcg(&op, &b, 1e-8, 3000, &|r| per_component(n, &scalar, r))
        };
        let f = |it: Option<usize>| it.map_or("> 3000".to_string(), |i| i.to_string());
        let g = |it: Option<Option<usize>>| it.map_or("-".to_string(), f);
        println!(
            "| {name} | {nf} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            g(k_amg),
            f(b_alone),
            g(factored(1)),
            g(factored(2)),
            g(factored(3)),
            g(factored(4)),
            g(factored(8)),
            g(full.then(|| factored_with(&hb4, 1))),
            f(gpu_form),
        );
    }
}
