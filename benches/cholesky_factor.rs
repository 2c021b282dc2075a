//! The numeric Cholesky factorization of the shape systems' isotropic part
//! `K` (the preconditioner of Eqs. 7 and 8, made on the host by both
//! backends), faer's loop over the supernodes one after the other against
//! the elimination tree's independent subtrees at once
//! (`solver_cpu::tree_factor`, the default), on 1 thread and on every thread
//! of the machine: homer with every edge cut in 3 (108k faces) and in 10
//! (1.2M faces), `K` at the input's positions with the pipeline's weights, in
//! the orderings the backends use (the GPU's minimum degree, the CPU's METIS
//! nested dissection).
//!
//! `cargo bench --bench cholesky_factor` (`-- --quick`: 108k only; `-- --1m`:
//! 1.2M only; `THREADS=n` for n threads instead of all). The best of
//! `REPEAT` (default 2) factorizations is printed, with the largest
//! difference between the two factors.

#[path = "../tests/common/mod.rs"]
mod common;

use metricdeform::shape::ShapeModel;
use solver_cpu::{CholeskySolver, FillOrdering, SpdSolver};
use std::time::Instant;

fn main() {
    let (cuts, homer) = common::homer_cuts(&[3, 10]);
    let repeat: usize = std::env::var("REPEAT")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2);
    // Every thread of the machine, or THREADS.
    let all = std::env::var("THREADS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    // The scale-driven kind's weights.
    let w = metricdeform::pipeline::Options::default().shape;
    println!(
        "| faces | ordering | nnz(L) | threads | faer, one supernode after another, s | subtrees at once, s | speed-up | largest difference / largest entry |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for &cut in cuts {
        let mesh = homer.subdivide_uniform(cut);
        let topo = metricdeform::mesh::topology::Topology::build(&mesh);
        let model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
        let k = model.isotropic_part(&mesh, &mesh.positions, &w);
        drop(model);
        for (name, ordering) in [
            ("minimum degree", FillOrdering::Amd),
            ("METIS", FillOrdering::NestedDissection),
        ] {
            let mut base = CholeskySolver::new();
            base.supernodal = true;
            base.set_fill_ordering(ordering);
            base.analyse(&k).unwrap();
            let mut threads = vec![1, all];
            threads.dedup();
            for &t in &threads {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .unwrap();
                let (seconds, factors): (Vec<f64>, Vec<Vec<f64>>) = [true, false]
                    .iter()
                    .map(|&sequential| {
                        let mut c = base.numeric_twin(false).unwrap();
                        c.sequential_supernodes = sequential;
                        let best = (0..repeat)
                            .map(|_| {
                                let t0 = Instant::now();
                                pool.install(|| c.prepare(&k)).unwrap();
                                t0.elapsed().as_secs_f64()
                            })
                            .fold(f64::INFINITY, f64::min);
                        (best, c.take_supernodal_factor().unwrap().values64)
                    })
                    .unzip();
                let largest = factors[0].iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let diff = factors[0]
                    .iter()
                    .zip(&factors[1])
                    .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                println!(
                    "| {} | {name} | {} | {t} | {:.3} | {:.3} | {:.2}x | {:.1e} |",
                    mesh.num_faces(),
                    base.factor_nnz(),
                    seconds[0],
                    seconds[1],
                    seconds[0] / seconds[1],
                    diff / largest
                );
            }
        }
    }
}
