//! Issue 16, "Real meshes and no lost data": zero-area, needle and duplicate faces
//! are handled (warned, named), not refused; a volume constraint needs a closed,
//! consistently oriented mesh and says what to do when it is not (weld split seams,
//! fill holes, re-orient).

mod common;

use glam::DVec3;
use metricdeform::job::{Job, JobFormat};
use metricdeform::mesh::io::{read_mesh, write_mesh};
use metricdeform::mesh::topology::Topology;
use metricdeform::pipeline::{deform, Options, SolverBackend};
use metricdeform::problem::Problem;
use metricdeform::report::constraint_rows;
use metricdeform::{Error, Mesh};
use std::path::{Path, PathBuf};

fn spot() -> Mesh {
    read_mesh(&common::meshes().join("spot.obj")).unwrap()
}

fn bad_msg<T>(r: metricdeform::Result<T>) -> String {
    match r {
        Err(Error::BadInput(m)) => m,
        Err(e) => panic!("expected BadInput, got {e:?}"),
        Ok(_) => panic!("expected BadInput, got Ok"),
    }
}

/// Writes `mesh` as OBJ into `dir` and a job on it with `constraints` (TOML
/// `[[constraint]]` tables); returns the loaded job.
fn job_on(dir: &Path, mesh: &Mesh, constraints: &str) -> Job {
    let mesh_path = dir.join("m.obj");
    write_mesh(&mesh_path, mesh, &mesh.positions, None).unwrap();
    let job_path = dir.join("job.toml");
    std::fs::write(&job_path, format!("mesh = \"m.obj\"\n{constraints}")).unwrap();
    Job::load(&job_path).unwrap()
}

/// Runs `job` on the CPU backend; returns the problem, the result and whether every
/// constraint is met.
fn run(job: &Job) -> (Problem, Vec<DVec3>, bool) {
    let problem = Problem::load(job).unwrap();
    let mut options = Options::from_spec(&job.spec.solver);
    options.backend = SolverBackend::Cpu;
    let out = deform(&problem, &options, &mut |_| {}).unwrap();
    let rows = constraint_rows(&problem, &out.positions, options.tolerance);
    for r in &rows {
        eprintln!(
            "{} '{}': {} -> {} (target {}), error {} %",
            r.kind, r.name, r.original, r.result, r.target, r.error_percent
        );
    }
    let met = rows.iter().all(|r| r.met);
    (problem, out.positions, met)
}

/// The face across edge (a, b) from face `f`.
fn neighbour(topo: &Topology, f: usize, a: u32, b: u32) -> usize {
    let e = topo.face_edges[f]
        .iter()
        .find(|&&e| topo.edges[e as usize] == [a.min(b), a.max(b)])
        .unwrap();
    let fs = topo.edge_faces(*e as usize);
    let g = if fs[0] as usize == f { fs[1] } else { fs[0] };
    g as usize
}

/// spot with face `f` = (a, b, c) split at a new vertex m on side (a, b):
/// (a, m, c), (m, b, c) and the sliver (a, b, m), which keeps side (a, b) for the
/// neighbour. With `lift = 0` m is the midpoint and the sliver has zero area; a
/// small lift off the side makes it a needle. The mesh stays closed and
/// consistently oriented. Returns the mesh and the sliver's index.
fn spot_with_sliver(f: usize, lift: f64) -> (Mesh, usize) {
    let mut m = spot();
    let topo = Topology::build(&m);
    let [a, b, c] = m.faces[f];
    let _ = neighbour(&topo, f, a, b);
    let (pa, pb, pc) = (
        m.positions[a as usize],
        m.positions[b as usize],
        m.positions[c as usize],
    );
    let mid = 0.5 * (pa + pb);
    let toward_c = (pc - mid).normalize();
    m.positions.push(mid + lift * (pb - pa).length() * toward_c);
    let mv = (m.positions.len() - 1) as u32;
    m.faces[f] = [a, mv, c];
    m.faces.push([mv, b, c]);
    m.faces.push([a, b, mv]);
    let sliver = m.faces.len() - 1;
    (m, sliver)
}

const AREA_AND_VOLUME: &str = "[[constraint]]\nkind = \"area\"\nname = \"head\"\n\
     region = { sphere = { center = [0.0, 0.55, -0.4], radius = 0.35 } }\nscale = 1.3\n\
     [[constraint]]\nkind = \"volume\"\n";

/// Item 1: a zero-area face and a needle are warned (named, 0-based) and the job
/// runs to exact metrics with finite positions (it was exit 2, "degenerate faces").
#[test]
fn zero_area_and_needle_faces_are_warned_and_the_job_is_exact() {
    for (lift, what) in [(0.0, "1 zero-area face"), (1e-7, "needle")] {
        let dir = tempfile::tempdir().unwrap();
        let (mesh, sliver) = spot_with_sliver(100, lift);
        let job = job_on(dir.path(), &mesh, AREA_AND_VOLUME);
        let (problem, x, met) = run(&job);
        assert!(
            problem
                .warnings
                .iter()
                .any(|w| w.contains(what) && w.contains(&format!("0-based: {sliver})"))),
            "lift {lift}: {:?}",
            problem.warnings
        );
        assert_eq!(problem.check.zero_area_faces, vec![sliver]);
        assert!(x.iter().all(|p| p.is_finite()));
        assert!(met, "lift {lift}: every constraint met");
    }
}

/// Item 1: a face with a huge cotangent (libigl would give an unbounded weight) is
/// clamped: the cotangent Laplacian stays finite and bounded.
#[test]
fn needle_cotangents_are_clamped() {
    let (mesh, sliver) = spot_with_sliver(100, 1e-9);
    assert!(mesh.degenerate_faces(&mesh.positions)[sliver]);
    let l = metricdeform::shape::cotangent_laplacian(&mesh, &mesh.positions);
    let max = (0..l.len())
        .flat_map(|i| l.row(i).map(|(_, w)| w.abs()).collect::<Vec<_>>())
        .fold(0.0f64, f64::max);
    assert!(max.is_finite() && max < 1e4, "largest |weight| {max}");
}

/// Item 2: a duplicate face (same vertices, reversed) was refused as a non-manifold
/// edge; now it is warned and the volume job runs, counting the face once. The
/// output keeps every face in order.
#[test]
fn duplicate_faces_are_warned_and_kept() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = spot();
    let original_volume = mesh.signed_volume(&mesh.positions);
    let [a, b, c] = mesh.faces[7];
    mesh.faces.push([c, b, a]);
    mesh.faces.push([b, c, a]);
    let nf = mesh.num_faces();
    let job = job_on(dir.path(), &mesh, AREA_AND_VOLUME);
    let (problem, x, met) = run(&job);
    assert!(
        problem
            .warnings
            .iter()
            .any(|w| w.contains("2 duplicate faces")
                && w.contains(&format!("{} repeats 7", nf - 2))
                && w.contains(&format!("{} repeats 7", nf - 1))),
        "{:?}",
        problem.warnings
    );
    assert!(problem.check.closed);
    let volume = problem
        .constraints
        .iter()
        .find(|c| c.kind == metricdeform::job::MetricKind::Volume)
        .unwrap();
    assert!((volume.original - original_volume).abs() <= 1e-12 * original_volume);
    assert!(met);
    assert!(x.iter().all(|p| p.is_finite()));
    // The duplicates still move with their original.
    let out = dir.path().join("out.obj");
    write_mesh(&out, &problem.mesh, &x, Some(&job.mesh_path())).unwrap();
    let back = read_mesh(&out).unwrap();
    assert_eq!(back.faces, mesh.faces);
    assert_eq!(back.num_vertices(), mesh.num_vertices());
}

/// Item 3: every other face flipped gives a meaningless signed volume: a volume job
/// is bad input naming an edge (two vertices) and its two faces. All faces flipped
/// (inward, consistent) is fine.
#[test]
fn inconsistent_orientation_refuses_a_volume_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = spot();
    for (f, t) in mesh.faces.iter_mut().enumerate() {
        if f % 2 == 1 {
            t.swap(1, 2);
        }
    }
    let job = job_on(dir.path(), &mesh, "[[constraint]]\nkind = \"volume\"\n");
    let msg = bad_msg(Problem::load(&job));
    assert!(
        msg.contains("job.toml")
            && msg.contains("constraint 1 (volume)")
            && msg.contains("consistently oriented")
            && msg.contains("edge (")
            && msg.contains("faces "),
        "{msg}"
    );
    // An area job on the same mesh does not care.
    let job = job_on(
        dir.path(),
        &mesh,
        "[[constraint]]\nkind = \"area\"\nregion = { faces = [0, 1, 2] }\n",
    );
    Problem::load(&job).unwrap();

    // Inward but consistent: accepted.
    let mut mesh = spot();
    for t in mesh.faces.iter_mut() {
        t.swap(1, 2);
    }
    let job = job_on(dir.path(), &mesh, "[[constraint]]\nkind = \"volume\"\n");
    Problem::load(&job).unwrap();
}

/// spot with its seams split: every vertex on the border between the faces with
/// centroid z > `z` and the rest is duplicated (same position) and the upper faces
/// use the copies, as a UV-seam export does.
fn spot_with_split_seam(z: f64) -> Mesh {
    let mut m = spot();
    let nf = m.num_faces();
    let upper: Vec<bool> = (0..nf).map(|f| m.centroid(&m.positions, f).z > z).collect();
    let nv = m.num_vertices();
    let mut in_upper = vec![false; nv];
    let mut in_lower = vec![false; nv];
    for (f, t) in m.faces.iter().enumerate() {
        for &v in t {
            if upper[f] {
                in_upper[v as usize] = true;
            } else {
                in_lower[v as usize] = true;
            }
        }
    }
    let mut copy = vec![u32::MAX; nv];
    for v in 0..nv {
        if in_upper[v] && in_lower[v] {
            m.positions.push(m.positions[v]);
            copy[v] = (m.positions.len() - 1) as u32;
        }
    }
    for (t, &up) in m.faces.iter_mut().zip(&upper) {
        if up {
            for v in t.iter_mut() {
                if copy[*v as usize] != u32::MAX {
                    *v = copy[*v as usize];
                }
            }
        }
    }
    m
}

/// Item 4: a mesh open only because its seams are split: the volume message says to
/// weld vertices.
#[test]
fn split_seams_say_weld() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = spot_with_split_seam(0.0);
    let topo = Topology::build(&mesh);
    assert!(!topo.boundary_edges.is_empty());
    let job = job_on(dir.path(), &mesh, "[[constraint]]\nkind = \"volume\"\n");
    let msg = bad_msg(Problem::load(&job));
    assert!(
        msg.contains("job.toml") && msg.contains("boundary edges") && msg.contains("weld"),
        "{msg}"
    );
    assert!(
        msg.contains("open only because its seams are split"),
        "{msg}"
    );

    // Copies one ulp off (an exporter that rounds the seam copies differently): still
    // recognised as split seams.
    let mut mesh = spot_with_split_seam(0.0);
    let nv = spot().num_vertices();
    for p in mesh.positions[nv..].iter_mut() {
        p.x = f64::from_bits(p.x.to_bits() + 1);
    }
    let job = job_on(dir.path(), &mesh, "[[constraint]]\nkind = \"volume\"\n");
    let msg = bad_msg(Problem::load(&job));
    assert!(
        msg.contains("open only because its seams are split"),
        "{msg}"
    );
}

/// Item 5: a mesh with a real hole: "boundary edges", fill the holes or drop the
/// volume constraint, no weld hint.
#[test]
fn open_mesh_says_fill_holes_or_drop_the_volume() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = spot();
    mesh.faces.drain(0..3);
    let job = job_on(
        dir.path(),
        &mesh,
        "[[constraint]]\nkind = \"volume\"\nname = \"body\"\n",
    );
    let msg = bad_msg(Problem::load(&job));
    assert!(
        msg.contains("job.toml")
            && msg.contains("constraint 1 ('body')")
            && msg.contains("boundary edges")
            && msg.contains("fill the holes")
            && msg.contains("drop the volume constraint")
            && !msg.contains("weld"),
        "{msg}"
    );
}

fn ogre() -> Option<PathBuf> {
    let p = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/meshes/ogre.obj"
    ));
    if p.exists() {
        Some(p)
    } else {
        eprintln!(
            "skipped: {} is not here (the shared test meshes are outside the repository)",
            p.display()
        );
        None
    }
}

/// Item 9: the ogre scan (open, 4 zero-area faces) runs examples/ogre-area.toml:
/// head area x1.3 and the waist girth kept, on the CPU, every constraint met,
/// positions finite. Its volume job is bad input with "boundary edges".
#[test]
fn ogre_area_and_girth_job_runs_and_its_volume_job_is_refused() {
    let Some(path) = ogre() else { return };
    // examples/ogre-area.toml names the mesh relative to itself: the same file.
    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/ogre-area.toml");
    let job = Job::load(&example).unwrap();
    assert_eq!(
        std::fs::canonicalize(job.mesh_path()).unwrap(),
        std::fs::canonicalize(&path).unwrap()
    );
    assert_eq!(job.spec.solver.backend.as_deref(), Some("cpu"));
    let (problem, x, met) = run(&job);
    assert!(
        problem
            .warnings
            .iter()
            .any(|w| w.contains("4 zero-area faces") && w.contains("2073")),
        "{:?}",
        problem.warnings
    );
    assert!(met, "every constraint met");
    assert!(x.iter().all(|p| p.is_finite()));

    let text = format!("mesh = {path:?}\n[[constraint]]\nkind = \"volume\"\n");
    let job = Job::from_str(&text, JobFormat::Toml, Path::new("."), "ogre-volume.toml").unwrap();
    let msg = bad_msg(Problem::load(&job));
    assert!(
        msg.contains("ogre-volume.toml") && msg.contains("boundary edges"),
        "{msg}"
    );
}

/// Faces with a repeated corner index (an ASCII STL triangle with two equal corners
/// reads so) are zero-area faces: warned, and the volume job on the otherwise closed
/// mesh runs (they made an edge "non-manifold" and were refused as degenerate).
#[test]
fn collapsed_faces_are_zero_area_faces() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = spot();
    let [a, b, _] = mesh.faces[40];
    mesh.faces.push([a, a, b]);
    mesh.faces.push([b, a, b]);
    let nf = mesh.num_faces();
    let topo = Topology::build(&mesh);
    assert!(topo.is_closed());
    assert_eq!(topo.collapsed_faces, vec![nf as u32 - 2, nf as u32 - 1]);
    let job = job_on(
        dir.path(),
        &mesh,
        &format!(
            "{AREA_AND_VOLUME}[[constraint]]\nkind = \"length\"\n\
             curve = {{ path = [{a}, 1500, {b}] }}\nscale = 1.05\n"
        ),
    );
    let (problem, x, met) = run(&job);
    assert!(
        problem
            .warnings
            .iter()
            .any(|w| w.contains("2 zero-area faces")
                && w.contains(&format!("0-based: {}, {})", nf - 2, nf - 1))),
        "{:?}",
        problem.warnings
    );
    assert!(met);
    assert!(x.iter().all(|p| p.is_finite()));
}

/// Item 1: the scale-factor system (Eq. 3) stays positive definite and its solution
/// finite when faces have zero rest area, with both regularisers and even with
/// k_d = k_r = 0 (the regulariser keeps a floor on zero-area faces).
#[test]
fn scale_factor_system_is_well_posed_on_zero_area_faces() {
    use metricdeform::constrained_step::Multipliers;
    use metricdeform::scale_factors::{Regulariser, ScaleConstraint, ScaleFactorSystem};
    use solver_cpu::CholeskySolver;
    let (mut mesh, sliver) = spot_with_sliver(100, 0.0);
    // A second, isolated zero-area face: a collapsed one.
    let [a, b, _] = mesh.faces[200];
    mesh.faces.push([a, b, b]);
    let topo = Topology::build(&mesh);
    let x = &mesh.positions;
    let areas = mesh.face_areas(x);
    assert!(areas[sliver] < 1e-15);
    // Area x1.5 of the faces around the sliver, the sliver included.
    let faces: Vec<u32> = (0..mesh.num_faces() as u32)
        .filter(|&f| (mesh.centroid(x, f as usize) - mesh.centroid(x, sliver)).length() < 0.2)
        .collect();
    assert!(faces.contains(&(sliver as u32)));
    let total: f64 = faces.iter().map(|&f| areas[f as usize]).sum();
    for reg in [Regulariser::Area, Regulariser::Uniform] {
        for (k_d, k_r) in [(1.0, 0.01), (0.0, 0.0)] {
            let mut sys = ScaleFactorSystem::with_solver(
                &topo.face_pairs,
                &areas,
                k_d,
                k_r,
                reg,
                Box::new(CholeskySolver::new()),
            )
            .unwrap();
            let c = ScaleConstraint {
                coeffs: faces.iter().map(|&f| (f, areas[f as usize])).collect(),
                degree: 2,
                target: 1.5 * total,
                group: 0,
            };
            let (s, info) = sys.estimate(&[c], Multipliers::PerConstraint).unwrap();
            assert!(
                s.iter().all(|v| v.is_finite() && *v > 0.0),
                "{reg:?} k_d {k_d} k_r {k_r}"
            );
            assert!(info.max_residual < 1e-9, "{reg:?}: {}", info.max_residual);
        }
    }
}

/// Unreferenced and non-manifold vertices join the warnings list (for the command
/// line to print), each naming the mesh and the 0-based indices.
#[test]
fn warnings_list_names_unreferenced_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = spot();
    mesh.positions.push(DVec3::new(9.0, 9.0, 9.0));
    let nv = mesh.num_vertices();
    let job = job_on(dir.path(), &mesh, "");
    let p = Problem::load(&job).unwrap();
    assert!(
        p.warnings.iter().any(|w| w.contains("m.obj")
            && w.contains("1 vertex is not used")
            && w.contains(&format!("0-based: {})", nv - 1))),
        "{:?}",
        p.warnings
    );
}

/// Item 1: vertices used only by zero-area faces (here a separate sliver
/// component) have no frame, curvature or Laplacian weight; the springs on the
/// sides of such faces keep the shape system positive definite, and they follow
/// along rigidly instead of breaking the solve.
#[test]
fn vertices_only_in_zero_area_faces_keep_the_system_well_posed() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = spot();
    let n = mesh.num_vertices() as u32;
    for p in [
        DVec3::new(2.0, 0.0, 0.0),
        DVec3::new(2.5, 0.0, 0.0),
        DVec3::new(3.0, 0.0, 0.0),
    ] {
        mesh.positions.push(p);
    }
    mesh.faces.push([n, n + 1, n + 2]);
    let sliver_before: Vec<DVec3> = mesh.positions[n as usize..].to_vec();
    let job = job_on(
        dir.path(),
        &mesh,
        "[[constraint]]\nkind = \"area\"\nregion = { sphere = { center = [0.0, 0.55, -0.4], radius = 0.35 } }\nscale = 1.3\n",
    );
    let (problem, x, met) = run(&job);
    assert_eq!(problem.check.zero_area_faces, vec![mesh.num_faces() - 1]);
    assert!(met);
    assert!(x.iter().all(|p| p.is_finite()));
    // The sliver keeps its shape (it may translate).
    let after = &x[n as usize..];
    let d = after[0] - sliver_before[0];
    for (p, q) in after.iter().zip(&sliver_before) {
        assert!((*p - *q - d).length() < 1e-6, "{p} vs {q}");
    }
}

/// Item 6 end to end: singular weights are exit 2 (they were exit 1, "linear
/// solver: matrix is not positive definite"), naming the weight and the job file,
/// and nothing is written.
#[test]
fn singular_weights_exit_2_from_the_command_line() {
    for weights in [
        "k_f = 0.0, k_m = 0.0, k_l = 0.0, k_d = 0.0, k_r = 0.0, k_p = 0.0",
        "k_f = 1e300",
    ] {
        let dir = tempfile::tempdir().unwrap();
        std::fs::copy(
            common::meshes().join("spot.obj"),
            dir.path().join("spot.obj"),
        )
        .unwrap();
        let job = dir.path().join("weights.toml");
        std::fs::write(
            &job,
            format!(
                "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.1\n\
                 [solver]\nweights = {{ {weights} }}\n"
            ),
        )
        .unwrap();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_metricdeform"))
            .args(["deform", "--backend", "cpu", "--quiet"])
            .arg(&job)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{weights}: {stderr}");
        assert!(
            stderr.contains("weights.toml") && stderr.contains("k_f"),
            "{weights}: {stderr}"
        );
        let mut files: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        files.sort();
        assert_eq!(files, ["spot.obj", "weights.toml"], "{weights}");
    }
}
