//! Shared by the integration tests: the paper's jobs (Fig. 3, Table 1, Fig. 9),
//! running a job on a backend and reading the written mesh back, and the
//! assertions on the written result.
#![allow(dead_code)]

use glam::DVec3;
use metricdeform::distortion::quasi_conformal;
use metricdeform::job::{Job, JobFormat};
use metricdeform::mesh::io;
use metricdeform::pipeline::{deform, Options, SolverBackend};
use metricdeform::problem::Problem;
use metricdeform::report::constraint_rows;
use metricdeform::shape::{ShapeModel, ShapeWeights};
use metricdeform::Mesh;
use std::path::{Path, PathBuf};

/// Table 1 style on spot: two lengths (plane section, edge path), an area, the volume.
/// The demo's job on spot: belly girth +10 %, head area x1.3, volume kept.
pub const SPOT_DEMO: &str = r#"
mesh = "spot.obj"
[[constraint]]
kind = "length"
curve = { plane = { origin = [0.0, -0.1, 0.3], normal = [0.0, 0.0, 1.0] } }
scale = 1.1
[[constraint]]
kind = "area"
region = { sphere = { center = [0.0, 0.55, -0.4], radius = 0.35 } }
scale = 1.3
[[constraint]]
kind = "volume"
"#;

pub const TABLE1_SPOT: &str = r#"
mesh = "spot.obj"
[[constraint]]
kind = "length"
name = "belly girth"
curve = { plane = { origin = [0.0, -0.1, 0.3], normal = [0.0, 0.0, 1.0] } }
scale = 1.15
[[constraint]]
kind = "length"
name = "back path"
curve = { path = [100, 1500, 2500] }
scale = 0.9
[[constraint]]
kind = "area"
name = "head"
region = { sphere = { center = [0.0, 0.55, -0.4], radius = 0.35 } }
scale = 1.4
[[constraint]]
kind = "volume"
"#;

/// Table 1 style on homer: two girths, an area, the volume.
pub const TABLE1_HOMER: &str = r#"
mesh = "homer.obj"
[[constraint]]
kind = "length"
name = "waist"
curve = { plane = { origin = [0.5, 0.5, 0.49], normal = [0.0, 1.0, 0.0] } }
scale = 1.2
[[constraint]]
kind = "length"
name = "head girth"
curve = { plane = { origin = [0.5, 0.85, 0.49], normal = [0.0, 1.0, 0.0] } }
scale = 1.0
[[constraint]]
kind = "area"
name = "upper body"
region = { box = { min = [-10.0, 0.6, -10.0], max = [10.0, 10.0, 10.0] } }
scale = 1.2
[[constraint]]
kind = "volume"
scale = 1.1
"#;

/// The million-face issue's job on homer: a girth +15 %, another girth and the volume kept.
pub const GIRTHS_HOMER: &str = r#"
mesh = "homer.obj"
[[constraint]]
kind = "length"
name = "waist"
curve = { plane = { origin = [0.5, 0.5, 0.49], normal = [0.0, 1.0, 0.0] } }
scale = 1.15
[[constraint]]
kind = "length"
name = "head girth"
curve = { plane = { origin = [0.5, 0.85, 0.49], normal = [0.0, 1.0, 0.0] } }
[[constraint]]
kind = "volume"
"#;

/// Paper Fig. 9: fandisk top area times `scale`, the bottom area kept.
pub fn fig9_fandisk(scale: f64) -> String {
    format!(
        r#"
mesh = "fandisk.obj"
[[constraint]]
kind = "area"
name = "top"
region = {{ box = {{ min = [-100.0, 16.0, -100.0], max = [100.0, 100.0, 100.0] }} }}
scale = {scale}
[[constraint]]
kind = "area"
name = "bottom"
region = {{ box = {{ min = [-100.0, -100.0, -100.0], max = [100.0, 14.0, 100.0] }} }}
"#
    )
}

pub fn meshes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes")
}

/// A bench's sizes of homer, as edge cuts: 3 (108k faces) with `--quick`,
/// 10 (1.2M) with `--1m`, else `all`; and homer itself.
pub fn homer_cuts(all: &'static [usize]) -> (&'static [usize], Mesh) {
    let args: Vec<String> = std::env::args().collect();
    let cuts: &[usize] = if args.iter().any(|a| a == "--quick") {
        &[3]
    } else if args.iter().any(|a| a == "--1m") {
        &[10]
    } else {
        all
    };
    let homer = metricdeform::mesh::io::read_mesh(&meshes().join("homer.obj")).unwrap();
    (cuts, homer)
}

pub fn job(text: &str) -> Job {
    Job::from_str(text, JobFormat::Toml, &meshes(), "test job").unwrap()
}

pub struct Run {
    pub problem: Problem,
    pub written: Mesh,
    pub options: Options,
}

/// Run a job on the CPU reference backend, write the result as OBJ and read it back.
pub fn run(text: &str) -> Run {
    run_on(text, SolverBackend::Cpu)
}

/// Run a job on `backend`, write the result as OBJ and read it back.
pub fn run_on(text: &str, backend: SolverBackend) -> Run {
    let job = job(text);
    let problem = Problem::load(&job).unwrap();
    let mut options = Options::from_spec(&job.spec.solver);
    options.backend = backend;
    let out = deform(&problem, &options, &mut |_| {}).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("out.obj");
    io::write_mesh(
        &path,
        &problem.mesh,
        &out.positions,
        Some(&problem.mesh_path),
    )
    .unwrap();
    let written = io::read_mesh(&path).unwrap();
    Run {
        problem,
        written,
        options,
    }
}

/// Every metric of the written mesh within the tolerance; returns (qc mean, qc max).
pub fn assert_all_met(r: &Run) -> (f64, f64) {
    let rows = constraint_rows(&r.problem, &r.written.positions, r.options.tolerance);
    for row in &rows {
        assert!(
            row.error_percent <= 1e-3,
            "{} '{}': result {} target {} error {} %",
            row.kind,
            row.name,
            row.result,
            row.target,
            row.error_percent
        );
        assert!(row.met);
    }
    let qc = quasi_conformal(
        &r.problem.mesh,
        &r.problem.mesh.positions,
        &r.written.positions,
    );
    eprintln!(
        "quasi-conformal distortion: mean {:.4}, max {:.4}",
        qc.0, qc.1
    );
    qc
}

/// Paper Fig. 3: the result must be the input scaled by 2 up to translation.
pub fn assert_scaled_by_two(r: &Run) {
    let x0 = &r.problem.mesh.positions;
    let x1 = &r.written.positions;
    let n = x0.len() as f64;
    let c0 = x0.iter().fold(DVec3::ZERO, |a, p| a + *p) / n;
    let c1 = x1.iter().fold(DVec3::ZERO, |a, p| a + *p) / n;
    let diag = r.problem.mesh.bbox_diagonal(x1);
    let dev = x0
        .iter()
        .zip(x1)
        .map(|(a, b)| ((b - c1) - 2.0 * (a - c0)).length())
        .fold(0.0, f64::max);
    assert!(
        dev <= 1e-4 * diag,
        "max deviation {:.3e} % of the bbox diagonal",
        100.0 * dev / diag
    );
    let (mean, _max) = assert_all_met(r);
    assert!(mean <= 1.001, "mean quasi-conformal distortion {mean}");
}

/// Paper Fig. 3 job: the volume or the total area of `mesh` times `scale`.
pub fn fig3_job(mesh: &str, kind: &str, scale: f64) -> String {
    match kind {
        "volume" => format!("mesh = \"{mesh}\"\n[[constraint]]\nkind = \"volume\"\nscale = {scale}\n"),
        _ => format!(
            "mesh = \"{mesh}\"\n[[constraint]]\nkind = \"area\"\nregion = {{ box = {{ min = [-1e9, -1e9, -1e9], max = [1e9, 1e9, 1e9] }} }}\nscale = {scale}\n"
        ),
    }
}

/// Largest distance between corresponding vertices of `a` and `b` on `mesh`,
/// relative to the bbox diagonal of `a`.
pub fn max_deviation(mesh: &Mesh, a: &[DVec3], b: &[DVec3]) -> f64 {
    let diag = mesh.bbox_diagonal(a);
    a.iter()
        .zip(b)
        .map(|(p, q)| (*p - *q).length())
        .fold(0.0, f64::max)
        / diag
}

/// The shape system of the first outer iteration of a demanding job, assembled
/// (and factored) in `model`: every face asked to grow 10 % (`s` and `c` 1.1),
/// weights `k_f` 1000, `k_m = k_l` 1, `k_p` 1000.
pub fn assemble_growing_tenth(model: &mut ShapeModel, mesh: &Mesh) {
    let s = vec![1.1; mesh.num_faces()];
    let c = vec![1.1; mesh.num_vertices()];
    let w = ShapeWeights {
        k_f: 1000.0,
        k_m: 1.0,
        k_l: 1.0,
        k_p: 1000.0,
    };
    model
        .assemble_and_factor(mesh, &mesh.positions, &s, &c, &w)
        .unwrap();
}
