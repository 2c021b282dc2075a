//! Picture benchmark (`--render`): seconds to draw input and result side by
//! side on the CPU at 12k, 108k, 1.2M faces (homer, every edge cut in n), with
//! the result a smooth synthetic deformation and the job's curves and regions
//! as annotations.
//!
//! `cargo bench --bench render` (add `-- --quick` to skip the 1.2M row,
//! `-- --save DIR` to keep the pictures as DIR/render-FACES.png).

#[path = "../tests/common/mod.rs"]
mod common;

use glam::DVec3;
use metricdeform::job::{Job, JobFormat};
use metricdeform::metrics::Selection;
use metricdeform::problem::Problem;
use metricdeform::render::{render_deformation, Annotation, Marked, RenderParams};
use std::path::Path;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let save = args
        .iter()
        .position(|a| a == "--save")
        .and_then(|i| args.get(i + 1))
        .map(std::path::PathBuf::from);
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let job = Job::from_str(common::TABLE1_HOMER, JobFormat::Toml, &dir, "homer").unwrap();
    let base = metricdeform::mesh::io::read_mesh(&job.mesh_path()).unwrap();
    println!("| faces | selections | render s | PNG kB |");
    println!("|---|---|---|---|");
    for n in [1usize, 3, 10] {
        if quick && n == 10 {
            continue;
        }
        let mesh = if n == 1 {
            base.clone()
        } else {
            base.subdivide_uniform(n)
        };
        let problem = Problem::build(&job, mesh, &job.mesh_path()).unwrap();
        let x = &problem.mesh.positions;
        // A smooth bulge: scaled by up to 30 % with the height.
        let (lo, hi) = x
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.y), b.max(p.y)));
        let y: Vec<DVec3> = x
            .iter()
            .map(|p| {
                let t = (p.y - lo) / (hi - lo);
                DVec3::new(p.x * (1.0 + 0.3 * t), p.y, p.z * (1.0 + 0.3 * t))
            })
            .collect();
        let notes: Vec<Annotation> = problem
            .constraints
            .iter()
            .map(|c| Annotation {
                name: c.name.clone(),
                kind: c.kind.to_string(),
                values: String::new(),
                marked: match &c.selection {
                    Selection::Curve(curve) => Marked::Curve(curve),
                    Selection::Region(r) => Marked::Faces(&r.faces),
                    Selection::Whole => Marked::Whole,
                },
            })
            .collect();
        let t0 = Instant::now();
        let png =
            render_deformation(&problem.mesh, x, &y, &notes, &RenderParams::default()).unwrap();
        let secs = t0.elapsed().as_secs_f64();
        if let Some(dir) = &save {
            let path = dir.join(format!("render-{}.png", problem.mesh.num_faces()));
            std::fs::write(&path, &png).unwrap();
        }
        println!(
            "| {} | {} | {secs:.3} | {} |",
            problem.mesh.num_faces(),
            notes.len(),
            png.len() / 1024
        );
    }
}
