//! The Cholesky preconditioner's triangular solves on the GPU (the shape
//! systems' `z = (P^T L L^T P)^-1 r`, `solver-gpu/src/supernodal.rs`) with one
//! lane per dot product against teams of lanes: per application, the chain
//! of dependent steps (`KernelWork::serial_steps`), dispatches, device seconds
//! (timestamp queries, where the adapter has them) and wall seconds, on the
//! shape system of homer's `girths-homer` rows (the first outer iteration of
//! a demanding job: every face asked to grow 10 %), one PCG column (x, y, z).
//!
//! `cargo bench --features bench-kernels --bench cholesky_teams [-- 100k 1m]`
//! (rows: 100k, 1m; default 100k). On lavapipe (a CPU emulation) the seconds
//! are not GPU seconds; the steps and dispatches are the same on any adapter
//! whose storage bindings hold the factor's updates in one buffer.
//! `scripts/gpu-bench.sh` runs it where its binary is given.

#[path = "../tests/common/mod.rs"]
mod common;

use metricdeform::shape::ShapeModel;
use solver_cpu::{SpdSolver, SystemKind};
use solver_gpu::kernels;
use std::path::Path;
use std::time::Instant;

/// Applications timed in one pass per layout.
const REPS: usize = 20;

fn row(name: &str) {
    let cut = match name {
        "100k" => 3,
        "1m" => 10,
        other => {
            eprintln!("cholesky_teams: unknown row {other} (100k or 1m)");
            return;
        }
    };
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let mesh = metricdeform::mesh::io::read_mesh(&dir.join("homer.obj"))
        .expect("data/meshes/homer.obj")
        .subdivide_uniform(cut);
    let topo = metricdeform::mesh::topology::Topology::build(&mesh);
    let mut model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
    common::assemble_growing_tenth(&mut model, &mesh);
    let (a, fixed) = model.system();
    let (a, fixed) = (a.clone(), fixed.to_vec());
    let n = 3 * a.n();
    let mut gpu = solver_gpu::open().expect("a GPU adapter");
    gpu.set_system_kind(SystemKind::ScaleDriven);
    let t = Instant::now();
    gpu.prepare_shape_owned(a, &fixed).unwrap();
    let setup = t.elapsed().as_secs_f64();
    let Some((levels, nnz)) = kernels::cholesky_shape(&gpu) else {
        eprintln!("cholesky_teams: {name}: the Cholesky preconditioner is not active");
        return;
    };
    let r: Vec<f64> = (0..n)
        .map(|i| ((i * 7919) % 1013) as f64 / 1013.0 - 0.5)
        .collect();
    let one = kernels::time_cholesky(&mut gpu, &r, 1, REPS, 1).unwrap();
    let teams = kernels::time_cholesky(&mut gpu, &r, 1, REPS, 64).unwrap();
    let scale = one.z.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = one
        .z
        .iter()
        .zip(&teams.z)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    let ms = |t: Option<f64>| t.map_or("n/a".into(), |t| format!("{:.3}", t * 1e3));
    let f64 = kernels::cholesky_is_f64(&gpu).unwrap_or(false);
    for (layout, t) in [("one lane", &one), ("teams", &teams)] {
        println!(
            "| girths-homer-{name} | {} | {levels} | {nnz} ({}) | {layout} | {} | {} | {} | {:.3} |",
            mesh.num_faces(),
            if f64 { "f64" } else { "f32" },
            t.serial_steps,
            t.dispatches,
            ms(t.device_seconds),
            t.wall_seconds * 1e3
        );
    }
    println!(
        "girths-homer-{name}: teams against one lane, largest difference {:.2e} of the largest entry; \
         factor set-up (host) and upload {setup:.1} s",
        diff / scale.max(f64::MIN_POSITIVE)
    );
}

fn main() {
    let rows: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let rows = if rows.is_empty() {
        vec!["100k".to_string()]
    } else {
        rows
    };
    println!(
        "adapter: {}",
        solver_gpu::default_adapter().map_or("none".into(), |a| a.name)
    );
    println!(
        "| row | faces | levels | factor values | layout | serial steps | dispatches | device ms | wall ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        row(r);
    }
}
