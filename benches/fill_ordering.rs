//! The fill-reducing orderings of the two patterns the pipeline factors on
//! the host, on homer with every edge cut in 3, 6 and 10 (108k, 432k and
//! 1.2M faces): the shape systems' `K` (vertices, 2-ring) and the scale
//! factors' system (Eq. 3; faces, sharing an edge). For each: faer's minimum
//! degree (inside the symbolic analysis), METIS's nested dissection (one
//! thread) and the nested dissection of the unknowns' positions
//! (`solver_cpu::coordinate_nested_dissection`, every thread): the
//! ordering's and the analysis's seconds, the factor's values and flops, one
//! numeric factorization's seconds, its supernodes and the levels a GPU
//! solves them in; then, per factor, what its numeric factorization on a
//! GPU (`solver_gpu::factorize`) would take, counted from its structure:
//! dispatches, the chain of dependent steps through them, modelled bytes.
//!
//! `cargo bench --bench fill_ordering` (`-- --quick`: 108k only; `-- --1m`:
//! 1.2M only).

#[path = "../tests/common/mod.rs"]
mod common;

use glam::DVec3;
use metricdeform::shape::ShapeModel;
use solver_cpu::{
    coordinate_nested_dissection, coordinate_nested_dissection_of_pairs,
    nested_dissection_of_pattern, CholeskySolver, FillOrdering, SpdSolver, SymCsc,
};
use std::time::Instant;

/// The orderings compared.
#[derive(Clone, Copy)]
enum Ordering {
    MinimumDegree,
    Metis,
    Positions,
}

fn row(
    pattern: &str,
    faces: usize,
    a: &SymCsc,
    ordering: Ordering,
    positions: impl Fn() -> Option<Vec<usize>>,
) {
    let t = Instant::now();
    let (name, fill) = match ordering {
        Ordering::MinimumDegree => ("minimum degree", FillOrdering::Amd),
        Ordering::Metis => (
            "METIS",
            FillOrdering::Given(
                nested_dissection_of_pattern(a.n, &a.col_ptr, &a.row_idx)
                    .unwrap()
                    .0
                    .into(),
            ),
        ),
        Ordering::Positions => (
            "positions",
            FillOrdering::Given(positions().unwrap().into()),
        ),
    };
    let ordered = t.elapsed().as_secs_f64();
    let mut c = CholeskySolver::new();
    c.supernodal = true;
    c.set_fill_ordering(fill);
    let t = Instant::now();
    c.analyse(a).unwrap();
    let analysed = t.elapsed().as_secs_f64();
    let mut twin = c.numeric_twin(false).unwrap();
    let t = Instant::now();
    twin.prepare(a).unwrap();
    let factored = t.elapsed().as_secs_f64();
    let f = twin.take_supernodal_factor().unwrap();
    let levels = f.levels().unwrap().iter().max().map_or(0, |&l| l + 1);
    let ordering_s = match ordering {
        Ordering::MinimumDegree => "in the analysis".to_string(),
        _ => format!("{ordered:.3}"),
    };
    println!(
        "| {pattern} | {faces} | {name} | {ordering_s} | {analysed:.3} | {:.1}M | {:.1}G | {factored:.3} | {} | {levels} |",
        c.factor_nnz() as f64 / 1e6,
        c.factor_flops() / 1e9,
        f.len(),
    );
    // What factoring it on a GPU would take (solver_gpu::factorize),
    // counted from its structure.
    if let Some(w) = solver_gpu::factorization_work(&f, a.row_idx.len()) {
        let widest = (0..f.len()).map(|s| f.shape(s).0).max().unwrap_or(0);
        // The device memory it takes beside the factor: the inverse
        // diagonal blocks' scratch (one f64 a diagonal block's entry).
        let scratch: usize = (0..f.len()).map(|s| f.shape(s).0.pow(2)).sum();
        GPU_ROWS.lock().unwrap().push(format!(
            "| {pattern} | {faces} | {name} | {} | {} | {:.1} | {widest} | {:.0} | {:.0} |",
            w.dispatches,
            w.serial_steps,
            w.bytes as f64 / 1e9,
            8.0 * f.nnz() as f64 / 1e6,
            8.0 * scratch as f64 / 1e6,
        ));
    }
}

/// The second table's rows: each factor's GPU factorization, counted.
static GPU_ROWS: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());

fn main() {
    let _ = env_logger::try_init();
    let (cuts, homer) = common::homer_cuts(&[3, 6, 10]);
    let w = metricdeform::pipeline::Options::default().shape;
    println!(
        "| pattern | faces | ordering | ordering s | analysis s | factor values | flops | numeric factorization s | supernodes | levels |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let all = [
        Ordering::MinimumDegree,
        Ordering::Metis,
        Ordering::Positions,
    ];
    for &cut in cuts {
        let mesh = homer.subdivide_uniform(cut);
        let nf = mesh.faces.len();
        let topo = metricdeform::mesh::topology::Topology::build(&mesh);
        let model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
        let k = model.isotropic_part(&mesh, &mesh.positions, &w);
        drop(model);
        for ordering in all {
            row("shape K", nf, &k, ordering, || {
                coordinate_nested_dissection(&mesh.positions, &k.col_ptr, &k.row_idx)
            });
        }
        // The scale factors' pattern, with a graph Laplacian's values plus
        // the identity (SPD).
        let pairs = &topo.face_pairs;
        let mut faces =
            SymCsc::from_pattern(nf, pairs.iter().map(|p| (p[0] as usize, p[1] as usize)));
        for i in 0..nf {
            let d = faces.slot(i, i).unwrap();
            faces.values[d] += 1.0;
        }
        for p in pairs {
            let (a, b) = (p[0] as usize, p[1] as usize);
            for (r, c, v) in [(a, a, 1.0), (b, b, 1.0), (a, b, -1.0)] {
                let s = faces.slot(r, c).unwrap();
                faces.values[s] += v;
            }
        }
        let centroids: Vec<DVec3> = mesh
            .faces
            .iter()
            .map(|f| f.iter().map(|&v| mesh.positions[v as usize]).sum::<DVec3>() / 3.0)
            .collect();
        for ordering in all {
            row("scale factors", nf, &faces, ordering, || {
                coordinate_nested_dissection_of_pairs(&centroids, pairs)
            });
        }
    }
    println!();
    println!(
        "| pattern | faces | ordering | GPU factorization: dispatches | serial steps | modelled GB | widest supernode | factor MB | scratch MB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in GPU_ROWS.lock().unwrap().iter() {
        println!("{r}");
    }
}
