//! Job file parsing/validation and selections (curves, regions, handles).

use glam::DVec3;
use metricdeform::job::{build_curve, build_handle_vertices, build_region};
use metricdeform::job::{
    BoxSpec, CurveSpec, HandleSpec, Job, JobFormat, MetricKind, PlaneSpec, PointSpec, RegionSpec,
    SphereSpec,
};
use metricdeform::mesh::topology::Topology;
use metricdeform::mesh::{FaceGroup, Mesh};
use metricdeform::problem::Problem;
use metricdeform::selection::SurfaceCurve;
use metricdeform::Error;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

// ---------------------------------------------------------------------------
// helpers
// ---------------------------------------------------------------------------

/// Minimal OBJ reader: `v` and `f` lines (fan triangulation), `g`/`o` groups.
fn read_obj(path: &Path) -> Mesh {
    let text = std::fs::read_to_string(path).unwrap();
    let mut m = Mesh::default();
    let mut group: Option<usize> = None;
    for line in text.lines() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let c: Vec<f64> = it.take(3).map(|s| s.parse().unwrap()).collect();
                m.positions.push(DVec3::new(c[0], c[1], c[2]));
            }
            Some("f") => {
                let idx: Vec<u32> = it
                    .map(|s| s.split('/').next().unwrap().parse::<i64>().unwrap())
                    .map(|i| {
                        if i < 0 {
                            (m.positions.len() as i64 + i) as u32
                        } else {
                            (i - 1) as u32
                        }
                    })
                    .collect();
                for k in 1..idx.len() - 1 {
                    if let Some(g) = group {
                        m.groups[g].faces.push(m.faces.len());
                    }
                    m.faces.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            Some("g") | Some("o") => {
                let name = it.collect::<Vec<_>>().join(" ");
                m.groups.push(FaceGroup {
                    name,
                    faces: vec![],
                });
                group = Some(m.groups.len() - 1);
            }
            _ => {}
        }
    }
    m
}

fn spot() -> Mesh {
    read_obj(&Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes/spot.obj"))
}

/// Unit cube [0,1]^3 (shifted by `off`) as 12 outward triangles; vertex i = x + 2y + 4z.
fn add_cube(m: &mut Mesh, off: DVec3) {
    let base = m.positions.len() as u32;
    for i in 0..8 {
        let p = DVec3::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64);
        m.positions.push(p + off);
    }
    let quads = [
        [0, 2, 3, 1], // z = 0
        [4, 5, 7, 6], // z = 1
        [0, 1, 5, 4], // y = 0
        [2, 6, 7, 3], // y = 1
        [0, 4, 6, 2], // x = 0
        [1, 3, 7, 5], // x = 1
    ];
    for q in quads {
        let q = q.map(|v| v + base);
        m.faces.push([q[0], q[1], q[2]]);
        m.faces.push([q[0], q[2], q[3]]);
    }
}

fn cube() -> Mesh {
    let mut m = Mesh::default();
    add_cube(&mut m, DVec3::ZERO);
    m
}

fn job_in(dir: &Path) -> Job {
    Job::from_str("mesh = \"m.obj\"\n", JobFormat::Toml, dir, "test.toml").unwrap()
}

fn bad_msg<T: std::fmt::Debug>(r: metricdeform::Result<T>) -> String {
    match r {
        Err(Error::BadInput(m)) => m,
        other => panic!("expected BadInput, got {other:?}"),
    }
}

fn toml_job(text: &str) -> metricdeform::Result<Job> {
    Job::from_str(text, JobFormat::Toml, Path::new("."), "job.toml")
}

fn plane(origin: [f64; 3], normal: [f64; 3]) -> CurveSpec {
    CurveSpec {
        plane: Some(PlaneSpec { origin, normal }),
        ..Default::default()
    }
}

/// Consecutive segments of the curve meet (end of one = start of next in space).
fn assert_connected(c: &SurfaceCurve, m: &Mesh) {
    let n = c.segments.len();
    let last = if c.closed { n } else { n - 1 };
    for i in 0..last {
        let (_, b) = c.segments[i].ends(m, &m.positions);
        let (a, _) = c.segments[(i + 1) % n].ends(m, &m.positions);
        assert!(
            (a - b).length() < 1e-12,
            "segments {i} and {} don't meet",
            (i + 1) % n
        );
    }
}

// ---------------------------------------------------------------------------
// job file
// ---------------------------------------------------------------------------

const JOB_TOML: &str = r#"
mesh = "spot.obj"
output = "out/spot-deformed.obj"

[[constraint]]
kind = "length"
name = "neck girth"
curve = { plane = { origin = [0.0, 0.9, 0.3], normal = [0.0, 1.0, 0.0] } }
scale = 1.2

[[constraint]]
kind = "length"
curve = { path = [1, 2, 3], closed = true }
value = 2.5

[[constraint]]
kind = "length"
curve = { points = [ { face = 0, bary = [0.2, 0.3, 0.5] }, { face = 0, bary = [1.0, 0.0, 0.0] } ] }

[[constraint]]
kind = "area"
region = { sphere = { center = [0.3, 1.4, 0.1], radius = 0.15 } }
scale = 2.0

[[constraint]]
kind = "area"
region = { box = { min = [-1.0, -1.0, -1.0], max = [1.0, 0.0, 1.0] } }

[[constraint]]
kind = "area"
name = "ear"
region = { group = "ear" }

[[constraint]]
kind = "volume"
scale = 1.0

[[handle]]
region = { sphere = { center = [0.0, 0.0, 0.0], radius = 0.1 } }
translate = [0.0, 0.1, 0.0]

[[handle]]
vertices = [4, 5]

[[curvature]]
region = { faces_file = "ear.txt" }
scale = 2.0

[solver]
backend = "auto"
tolerance = 1e-5
max_iterations = 100
weights = { k_f = 1000.0, k_m = 1.0, k_l = 1.0, k_d = 1.0, k_r = 0.01, k_p = 1000.0 }
multipliers = "per_constraint"
regulariser = "uniform"
"#;

const JOB_JSON: &str = r#"{
  "mesh": "spot.obj",
  "output": "out/spot-deformed.obj",
  "constraint": [
    { "kind": "length", "name": "neck girth",
      "curve": { "plane": { "origin": [0.0, 0.9, 0.3], "normal": [0.0, 1.0, 0.0] } },
      "scale": 1.2 },
    { "kind": "length", "curve": { "path": [1, 2, 3], "closed": true }, "value": 2.5 },
    { "kind": "length", "curve": { "points": [ { "face": 0, "bary": [0.2, 0.3, 0.5] },
                                               { "face": 0, "bary": [1.0, 0.0, 0.0] } ] } },
    { "kind": "area", "region": { "sphere": { "center": [0.3, 1.4, 0.1], "radius": 0.15 } },
      "scale": 2.0 },
    { "kind": "area", "region": { "box": { "min": [-1.0, -1.0, -1.0], "max": [1.0, 0.0, 1.0] } } },
    { "kind": "area", "name": "ear", "region": { "group": "ear" } },
    { "kind": "volume", "scale": 1.0 }
  ],
  "handle": [
    { "region": { "sphere": { "center": [0.0, 0.0, 0.0], "radius": 0.1 } },
      "translate": [0.0, 0.1, 0.0] },
    { "vertices": [4, 5] }
  ],
  "curvature": [ { "region": { "faces_file": "ear.txt" }, "scale": 2.0 } ],
  "solver": {
    "backend": "auto", "tolerance": 1e-5, "max_iterations": 100,
    "weights": { "k_f": 1000.0, "k_m": 1.0, "k_l": 1.0, "k_d": 1.0, "k_r": 0.01, "k_p": 1000.0 },
    "multipliers": "per_constraint", "regulariser": "uniform"
  }
}"#;

#[test]
fn toml_and_json_parse_to_equal_specs() {
    let dir = tempfile::tempdir().unwrap();
    let tp = dir.path().join("job.toml");
    let jp = dir.path().join("job.json");
    std::fs::write(&tp, JOB_TOML).unwrap();
    std::fs::write(&jp, JOB_JSON).unwrap();
    let t = Job::load(&tp).unwrap();
    let j = Job::load(&jp).unwrap();
    assert_eq!(t.spec, j.spec);
    assert_eq!(t.dir, dir.path());
    assert_eq!(t.path.as_deref(), Some(tp.as_path()));
    let s = &t.spec;
    assert_eq!(s.constraint.len(), 7);
    assert_eq!(s.constraint[0].kind, MetricKind::Length);
    assert_eq!(s.constraint[0].name.as_deref(), Some("neck girth"));
    assert_eq!(s.constraint[0].scale, Some(1.2));
    assert_eq!(s.constraint[1].curve.as_ref().unwrap().closed, Some(true));
    assert_eq!(s.constraint[6].kind, MetricKind::Volume);
    assert_eq!(
        s.constraint[4]
            .region
            .as_ref()
            .unwrap()
            .box_
            .as_ref()
            .unwrap()
            .max,
        [1.0, 0.0, 1.0]
    );
    assert_eq!(s.handle.len(), 2);
    assert_eq!(s.handle[1].translation(), [0.0; 3]);
    assert_eq!(s.solver.weights.as_ref().unwrap().k_r, Some(0.01));
    assert_eq!(s.solver.max_iterations, Some(100));
    assert_eq!(t.mesh_path(), dir.path().join("spot.obj"));
    assert_eq!(t.output_path(), dir.path().join("out/spot-deformed.obj"));
    // Constraints are numbered from 1 in messages (contract: "1-based number").
    assert_eq!(t.constraint_label(0), "constraint 1 ('neck girth')");
    assert_eq!(t.constraint_label(1), "constraint 2 (length)");
    assert_eq!(MetricKind::Area.to_string(), "area");
}

#[test]
fn unknown_fields_and_kinds_are_rejected() {
    let cases: [(&str, &str); 6] = [
        ("mesh = \"a.obj\"\nmeshes = \"b.obj\"\n", "meshes"),
        (
            "mesh = \"a.obj\"\n[[constraint]]\nkind = \"volume\"\nscael = 2.0\n",
            "scael",
        ),
        (
            "mesh = \"a.obj\"\n[[constraint]]\nkind = \"lenght\"\n",
            "lenght",
        ),
        (
            "mesh = \"a.obj\"\n[[constraint]]\nkind = \"area\"\nregion = { cylinder = { radius = 1.0 } }\n",
            "cylinder",
        ),
        (
            "mesh = \"a.obj\"\n[solver]\nbackend = \"cuda\"\n",
            "cuda",
        ),
        (
            "mesh = \"a.obj\"\n[solver]\nweights = { k_q = 1.0 }\n",
            "k_q",
        ),
    ];
    for (text, key) in cases {
        let msg = bad_msg(toml_job(text));
        assert!(msg.contains(key), "message {msg:?} should mention {key:?}");
        assert!(
            msg.contains("job.toml"),
            "message {msg:?} should name the file"
        );
    }
    // Same in JSON.
    let msg = bad_msg(Job::from_str(
        r#"{"mesh": "a.obj", "constraint": [{"kind": "area", "region": {"faces": [1], "colour": 3}}]}"#,
        JobFormat::Json,
        Path::new("."),
        "job.json",
    ));
    assert!(msg.contains("colour") && msg.contains("job.json"), "{msg}");
    // Missing mesh.
    let msg = bad_msg(toml_job("output = \"x.obj\"\n"));
    assert!(msg.contains("mesh"), "{msg}");
}

#[test]
fn load_errors() {
    let dir = tempfile::tempdir().unwrap();
    // Wrong extension.
    let p = dir.path().join("job.yaml");
    std::fs::write(&p, "mesh: a.obj").unwrap();
    let msg = bad_msg(Job::load(&p));
    assert!(msg.contains("job.yaml"), "{msg}");
    // Missing file.
    match Job::load(&dir.path().join("nope.toml")) {
        Err(Error::Io { path, .. }) => assert!(path.ends_with("nope.toml")),
        other => panic!("expected Io error, got {other:?}"),
    }
    // Syntax error names the file and the line.
    let p = dir.path().join("broken.toml");
    std::fs::write(&p, "mesh = \"a.obj\"\n[[constraint]\n").unwrap();
    let msg = bad_msg(Job::load(&p));
    assert!(
        msg.contains("broken.toml") && msg.contains("line 2"),
        "{msg}"
    );
}

#[test]
fn constraint_validation() {
    let msg = bad_msg(toml_job(
        "mesh = \"a.obj\"\n[[constraint]]\nkind = \"volume\"\n\
         [[constraint]]\nkind = \"volume\"\n\
         [[constraint]]\nkind = \"volume\"\nname = \"neck girth\"\nscale = 1.0\nvalue = 2.0\n",
    ));
    assert!(
        msg.contains("constraint 3 ('neck girth'): give either scale or value, not both"),
        "{msg}"
    );
    let cases: [(&str, &str); 9] = [
        (
            "kind = \"volume\"\nscale = -1.0",
            "constraint 1 (volume): scale",
        ),
        ("kind = \"volume\"\nvalue = 0.0", "value"),
        ("kind = \"volume\"\nscale = nan", "scale"),
        ("kind = \"length\"", "needs a curve"),
        (
            "kind = \"length\"\ncurve = { path = [0, 1] }\nregion = { faces = [0] }",
            "not a region",
        ),
        ("kind = \"area\"", "needs a region"),
        (
            "kind = \"area\"\nregion = { faces = [0] }\ncurve = { path = [0, 1] }",
            "not a curve",
        ),
        ("kind = \"volume\"\nregion = { faces = [0] }", "neither"),
        (
            "kind = \"area\"\nregion = { vertices = [0] }",
            "only allowed for handles",
        ),
    ];
    for (body, want) in cases {
        let msg = bad_msg(toml_job(&format!(
            "mesh = \"a.obj\"\n[[constraint]]\n{body}\n"
        )));
        assert!(
            msg.contains(want),
            "{body:?}: message {msg:?} lacks {want:?}"
        );
    }
    // Curves and regions: exactly one kind.
    let msg = bad_msg(toml_job(
        "mesh = \"a.obj\"\n[[constraint]]\nkind = \"length\"\n\
         curve = { path = [0, 1], plane = { origin = [0.0,0.0,0.0], normal = [0.0,0.0,1.0] } }\n",
    ));
    assert!(msg.contains("exactly one"), "{msg}");
    let msg = bad_msg(toml_job(
        "mesh = \"a.obj\"\n[[constraint]]\nkind = \"area\"\nregion = { faces = [0], group = \"g\" }\n",
    ));
    assert!(msg.contains("exactly one"), "{msg}");
    let msg = bad_msg(toml_job(
        "mesh = \"a.obj\"\n[[handle]]\nvertices = [0]\nregion = { faces = [0] }\n",
    ));
    assert!(msg.contains("handle 1"), "{msg}");
    let msg = bad_msg(toml_job("mesh = \"a.obj\"\n[solver]\ntolerance = 0.0\n"));
    assert!(msg.contains("tolerance"), "{msg}");
    let msg = bad_msg(toml_job(
        "mesh = \"a.obj\"\n[solver]\nweights = { k_f = -1.0 }\n",
    ));
    assert!(msg.contains("k_f"), "{msg}");
}

#[test]
fn output_path_default_and_resolution() {
    let job = Job::from_str(
        "mesh = \"meshes/spot.obj\"\n",
        JobFormat::Toml,
        Path::new("/jobs/a"),
        "demo",
    )
    .unwrap();
    assert_eq!(job.mesh_path(), PathBuf::from("/jobs/a/meshes/spot.obj"));
    assert_eq!(
        job.output_path(),
        PathBuf::from("/jobs/a/spot.deformed.obj")
    );
    assert_eq!(
        job.resolve_path(Path::new("/abs/x.txt")),
        PathBuf::from("/abs/x.txt")
    );
    let job = Job::from_str(
        "mesh = \"x.ply\"\noutput = \"y.ply\"\n",
        JobFormat::Toml,
        Path::new("/d"),
        "demo",
    )
    .unwrap();
    assert_eq!(job.output_path(), PathBuf::from("/d/y.ply"));
    // A job file in the current directory.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("j.json"), r#"{"mesh": "bunny.stl"}"#).unwrap();
    let job = Job::load(&dir.path().join("j.json")).unwrap();
    assert_eq!(job.output_path(), dir.path().join("bunny.deformed.stl"));
}

/// `output` is a path or a table `{ path, attributes }` (both optional), in
/// TOML and JSON alike; attributes default to on.
#[test]
fn output_string_or_table() {
    let parse = |text: &str, format| Job::from_str(text, format, Path::new("/d"), "job").unwrap();
    let cases = [
        (
            "mesh = \"x.obj\"\noutput = \"y.ply\"\n",
            JobFormat::Toml,
            "/d/y.ply",
            true,
        ),
        (
            "mesh = \"x.obj\"\n[output]\npath = \"y.ply\"\nattributes = false\n",
            JobFormat::Toml,
            "/d/y.ply",
            false,
        ),
        (
            "mesh = \"x.obj\"\n[output]\npath = \"z.ply\"\n",
            JobFormat::Toml,
            "/d/z.ply",
            true,
        ),
        (
            "mesh = \"x.obj\"\n[output]\nattributes = false\n",
            JobFormat::Toml,
            "/d/x.deformed.obj",
            false,
        ),
        (
            "mesh = \"x.obj\"\n[output]\n",
            JobFormat::Toml,
            "/d/x.deformed.obj",
            true,
        ),
        (
            r#"{"mesh": "x.obj", "output": "y.ply"}"#,
            JobFormat::Json,
            "/d/y.ply",
            true,
        ),
        (
            r#"{"mesh": "x.obj", "output": {"path": "y.ply", "attributes": false}}"#,
            JobFormat::Json,
            "/d/y.ply",
            false,
        ),
        (
            r#"{"mesh": "x.obj", "output": {"attributes": true}}"#,
            JobFormat::Json,
            "/d/x.deformed.obj",
            true,
        ),
    ];
    for (text, format, path, attributes) in cases {
        let job = parse(text, format);
        assert_eq!(job.output_path(), PathBuf::from(path), "{text}");
        assert_eq!(job.output_attributes(), attributes, "{text}");
    }
    let msg = bad_msg(toml_job("mesh = \"x.obj\"\n[output]\npth = \"y.ply\"\n"));
    assert!(msg.contains("job.toml") && msg.contains("pth"), "{msg}");
    let msg = bad_msg(toml_job("mesh = \"x.obj\"\noutput = \"\"\n"));
    assert!(msg.contains("job.toml") && msg.contains("output"), "{msg}");
}

// ---------------------------------------------------------------------------
// plane sections
// ---------------------------------------------------------------------------

#[test]
fn plane_section_of_cube() {
    let m = cube();
    let topo = Topology::build(&m);
    let c = build_curve(&plane([0.5, 0.5, 0.5], [0.0, 0.0, 2.0]), &m, &topo, "c").unwrap();
    assert!(c.closed);
    assert_eq!(c.segments.len(), 8);
    assert!((c.length(&m, &m.positions) - 4.0).abs() < 1e-12);
    assert_connected(&c, &m);
    for s in &c.segments {
        for w in [s.a, s.b] {
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            let p = metricdeform::selection::SurfacePoint {
                face: s.face,
                bary: w,
            }
            .position(&m, &m.positions);
            assert!((p.z - 0.5).abs() < 1e-12);
        }
    }
    // Curves move with the mesh: scale the cube by 2 -> length doubles.
    let x2: Vec<DVec3> = m.positions.iter().map(|p| *p * 2.0).collect();
    assert!((c.length(&m, &x2) - 8.0).abs() < 1e-12);
    // A tilted plane: section of the cube by x + y + z = 1.5 is a regular hexagon
    // with side sqrt(2)/2.
    let c = build_curve(&plane([0.5, 0.5, 0.5], [1.0, 1.0, 1.0]), &m, &topo, "c").unwrap();
    assert!(c.closed);
    assert!((c.length(&m, &m.positions) - 6.0 * 0.5f64.sqrt()).abs() < 1e-12);
    assert_connected(&c, &m);
}

#[test]
fn plane_section_open_piece_on_open_mesh() {
    // Cube without its top: the section at z=0.5 is still a loop; the bottom square
    // alone cut by x=0.5 is an open piece running boundary to boundary.
    let mut m = cube();
    m.faces.truncate(2); // bottom square: two triangles
    let topo = Topology::build(&m);
    let c = build_curve(&plane([0.5, 0.5, 0.0], [1.0, 0.0, 0.0]), &m, &topo, "c").unwrap();
    assert!(!c.closed);
    assert_eq!(c.segments.len(), 2);
    assert!((c.length(&m, &m.positions) - 1.0).abs() < 1e-12);
    assert_connected(&c, &m);
}

#[test]
fn plane_missing_mesh_and_zero_normal() {
    let m = cube();
    let topo = Topology::build(&m);
    let msg = bad_msg(build_curve(
        &plane([0.0, 0.0, 5.0], [0.0, 0.0, 1.0]),
        &m,
        &topo,
        "constraint 3 ('waist')",
    ));
    assert!(
        msg.contains("misses") && msg.contains("constraint 3 ('waist')"),
        "{msg}"
    );
    // Through the bottom face: those vertices count as positive, so no crossing.
    let msg = bad_msg(build_curve(
        &plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
        &m,
        &topo,
        "c",
    ));
    assert!(msg.contains("misses"), "{msg}");
    let msg = bad_msg(build_curve(
        &plane([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
        &m,
        &topo,
        "c",
    ));
    assert!(msg.contains("normal"), "{msg}");
}

#[test]
fn plane_through_vertices_counts_them_positive() {
    // Plane z = 1 with normal -z: the top vertices have d = 0 (positive), the bottom
    // ones d = 1 (positive): no crossing. With normal +z the bottom is negative and
    // the top positive: the section runs through the top vertices, a square of
    // perimeter 4 with no zero-length segments.
    let m = cube();
    let topo = Topology::build(&m);
    let msg = bad_msg(build_curve(
        &plane([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]),
        &m,
        &topo,
        "c",
    ));
    assert!(msg.contains("misses"), "{msg}");
    let c = build_curve(&plane([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]), &m, &topo, "c").unwrap();
    assert!((c.length(&m, &m.positions) - 4.0).abs() < 1e-12);
    for s in &c.segments {
        assert!(s.length(&m, &m.positions) > 0.0);
    }
    assert_connected(&c, &m);
}

#[test]
fn plane_chooses_piece_nearest_origin() {
    let mut m = cube();
    add_cube(&mut m, DVec3::new(3.0, 0.0, 0.0)); // faces 12..24
    let topo = Topology::build(&m);
    let far = build_curve(&plane([3.5, 0.5, 0.5], [0.0, 0.0, 1.0]), &m, &topo, "c").unwrap();
    assert!(far.segments.iter().all(|s| s.face >= 12));
    assert!((far.length(&m, &m.positions) - 4.0).abs() < 1e-12);
    let near = build_curve(&plane([0.2, 0.5, 0.5], [0.0, 0.0, 1.0]), &m, &topo, "c").unwrap();
    assert!(near.segments.iter().all(|s| s.face < 12));
    assert_eq!(near.segments.len(), 8);
    // Origin far to the right: still picks the nearer (second) cube.
    let c = build_curve(&plane([10.0, 0.5, 0.5], [0.0, 0.0, 1.0]), &m, &topo, "c").unwrap();
    assert!(c.segments.iter().all(|s| s.face >= 12));
}

/// Independent plane section: all crossed faces, grouped into pieces by
/// union-find over shared crossed edges; returns the length and closedness of the
/// piece with the crossing point nearest to `origin`, its number of faces, and the
/// number of crossed faces in all pieces.
fn reference_section(m: &Mesh, origin: DVec3, normal: DVec3) -> (f64, bool, usize, usize) {
    let d: Vec<f64> = m
        .positions
        .iter()
        .map(|p| (*p - origin).dot(normal))
        .collect();
    let crossing = |a: u32, b: u32| {
        let (da, db) = (d[a as usize], d[b as usize]);
        let t = da / (da - db);
        m.positions[a as usize].lerp(m.positions[b as usize], t)
    };
    let nf = m.faces.len();
    let mut parent: Vec<usize> = (0..nf).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    let mut edge_face: HashMap<(u32, u32), (usize, usize)> = HashMap::new();
    let mut seg_len = vec![0.0; nf];
    let mut near = vec![f64::INFINITY; nf];
    let mut crossed = vec![false; nf];
    for (f, t) in m.faces.iter().enumerate() {
        let mut pts = vec![];
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if (d[a as usize] >= 0.0) != (d[b as usize] >= 0.0) {
                pts.push(crossing(a, b));
                let e = edge_face.entry((a.min(b), a.max(b))).or_insert((f, 0));
                e.1 += 1;
                if e.0 != f {
                    let (ra, rb) = (find(&mut parent, e.0), find(&mut parent, f));
                    parent[ra] = rb;
                }
            }
        }
        if pts.len() == 2 {
            crossed[f] = true;
            seg_len[f] = (pts[0] - pts[1]).length();
            near[f] = (pts[0] - origin).length().min((pts[1] - origin).length());
        }
    }
    let mut best = (f64::INFINITY, usize::MAX);
    for f in 0..nf {
        if crossed[f] && near[f] < best.0 {
            best = (near[f], find(&mut parent, f));
        }
    }
    let root = best.1;
    let mut len = 0.0;
    let mut count = 0;
    for f in 0..nf {
        if crossed[f] && find(&mut parent, f) == root {
            len += seg_len[f];
            count += 1;
        }
    }
    let closed = edge_face.iter().all(|(&(a, b), &(f, n))| {
        let _ = (a, b);
        find(&mut parent, f) != root || n == 2
    });
    let total = crossed.iter().filter(|&&c| c).count();
    (len, closed, count, total)
}

#[test]
fn plane_section_of_spot_matches_reference() {
    let m = spot();
    assert_eq!(m.faces.len(), 5856);
    let topo = Topology::build(&m);
    let planes = [
        ([0.0, 0.1, 0.2], [0.0, 0.0, 1.0]),
        ([0.0, 0.9, 0.3], [0.0, 1.0, 0.0]),
        ([0.1, 0.0, 0.0], [1.0, 0.3, -0.2]),
        ([0.0, -0.6, 0.2], [0.0, 1.0, 0.0]), // through the legs: several pieces
    ];
    let mut lengths = vec![];
    let mut several_pieces = false;
    for (o, n) in planes {
        let c = build_curve(&plane(o, n), &m, &topo, "c").unwrap();
        let (len, closed, count, total) = reference_section(&m, DVec3::from(o), DVec3::from(n));
        several_pieces |= count < total;
        let got = c.length(&m, &m.positions);
        assert!(
            (got - len).abs() < 1e-9 * len.max(1.0),
            "plane {o:?} {n:?}: {got} vs {len}"
        );
        assert!(
            c.closed && closed,
            "spot is closed: every section is a loop"
        );
        assert_eq!(c.segments.len(), count);
        assert_connected(&c, &m);
        lengths.push(got);
    }
    assert!(lengths.iter().all(|&l| l > 0.1), "{lengths:?}");
    assert!(
        several_pieces,
        "one of the planes should cut spot in several pieces"
    );
}

// ---------------------------------------------------------------------------
// paths and points
// ---------------------------------------------------------------------------

/// Floyd-Warshall over the mesh edges (small meshes only).
fn all_pairs(m: &Mesh) -> Vec<Vec<f64>> {
    let n = m.positions.len();
    let mut d = vec![vec![f64::INFINITY; n]; n];
    for (i, row) in d.iter_mut().enumerate() {
        row[i] = 0.0;
    }
    for t in &m.faces {
        for k in 0..3 {
            let (a, b) = (t[k] as usize, t[(k + 1) % 3] as usize);
            let l = (m.positions[a] - m.positions[b]).length();
            d[a][b] = d[a][b].min(l);
            d[b][a] = d[b][a].min(l);
        }
    }
    for k in 0..n {
        for i in 0..n {
            for j in 0..n {
                if d[i][k] + d[k][j] < d[i][j] {
                    d[i][j] = d[i][k] + d[k][j];
                }
            }
        }
    }
    d
}

fn path(vs: &[usize], closed: Option<bool>) -> CurveSpec {
    CurveSpec {
        path: Some(vs.to_vec()),
        closed,
        ..Default::default()
    }
}

#[test]
fn edge_path_on_cube() {
    let m = cube();
    let topo = Topology::build(&m);
    let d = all_pairs(&m);
    assert!((d[0][7] - (1.0 + 2f64.sqrt())).abs() < 1e-12);
    let c = build_curve(&path(&[0, 7], None), &m, &topo, "c").unwrap();
    assert!(!c.closed);
    assert!((c.length(&m, &m.positions) - d[0][7]).abs() < 1e-12);
    assert_eq!(c.segments.len(), 2);
    assert_connected(&c, &m);
    // Segments lie on mesh edges: bary coordinates are unit vectors.
    for s in &c.segments {
        for w in [s.a, s.b] {
            assert_eq!(w.iter().filter(|&&x| x == 1.0).count(), 1);
            assert_eq!(w.iter().filter(|&&x| x == 0.0).count(), 2);
        }
    }
    // First segment starts at vertex 0, last ends at vertex 7.
    let (p0, _) = c.segments[0].ends(&m, &m.positions);
    let (_, p1) = c.segments.last().unwrap().ends(&m, &m.positions);
    assert_eq!(p0, m.positions[0]);
    assert_eq!(p1, m.positions[7]);
    // Through several vertices, closed.
    let c = build_curve(&path(&[0, 3, 6], Some(true)), &m, &topo, "c").unwrap();
    assert!(c.closed);
    let want = d[0][3] + d[3][6] + d[6][0];
    assert!((c.length(&m, &m.positions) - want).abs() < 1e-12);
    assert_connected(&c, &m);
}

#[test]
fn edge_path_on_spot_matches_floyd_free_reference() {
    // Dijkstra vs. a simple Bellman-Ford relaxation on spot.
    let m = spot();
    let topo = Topology::build(&m);
    let n = m.positions.len();
    let (s, t) = (0usize, 1500usize);
    let mut dist = vec![f64::INFINITY; n];
    dist[s] = 0.0;
    loop {
        let mut changed = false;
        for tri in &m.faces {
            for k in 0..3 {
                let (a, b) = (tri[k] as usize, tri[(k + 1) % 3] as usize);
                let l = (m.positions[a] - m.positions[b]).length();
                if dist[a] + l < dist[b] {
                    dist[b] = dist[a] + l;
                    changed = true;
                }
                if dist[b] + l < dist[a] {
                    dist[a] = dist[b] + l;
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    let c = build_curve(&path(&[s, t], None), &m, &topo, "c").unwrap();
    assert!((c.length(&m, &m.positions) - dist[t]).abs() < 1e-9);
    assert_connected(&c, &m);
}

#[test]
fn edge_path_errors() {
    let mut m = cube();
    add_cube(&mut m, DVec3::new(3.0, 0.0, 0.0));
    let topo = Topology::build(&m);
    let msg = bad_msg(build_curve(
        &path(&[0, 99], None),
        &m,
        &topo,
        "constraint 1 (length)",
    ));
    assert!(
        msg.contains("99") && msg.contains("constraint 1 (length)"),
        "{msg}"
    );
    let msg = bad_msg(build_curve(&path(&[0, 12], None), &m, &topo, "c"));
    assert!(msg.contains("12") && msg.contains("reached"), "{msg}");
    let msg = bad_msg(build_curve(&path(&[3], None), &m, &topo, "c"));
    assert!(msg.contains("at least 2"), "{msg}");
    let closed_points = CurveSpec {
        points: Some(vec![]),
        closed: Some(true),
        ..Default::default()
    };
    let msg = bad_msg(build_curve(&closed_points, &m, &topo, "c"));
    assert!(msg.contains("closed"), "{msg}");
}

fn pt(face: usize, bary: [f64; 3]) -> PointSpec {
    PointSpec { face, bary }
}

fn points(p: Vec<PointSpec>) -> CurveSpec {
    CurveSpec {
        points: Some(p),
        ..Default::default()
    }
}

#[test]
fn points_across_adjacent_faces() {
    let m = cube();
    let topo = Topology::build(&m);
    // Bottom square: faces 0 = (0,2,3) and 1 = (0,3,1) share edge (0,3).
    let p_a = pt(0, [0.2, 0.6, 0.2]); // interior of face 0
    let p_edge = pt(1, [0.5, 0.5, 0.0]); // midpoint of edge (0,3), given in face 1
    let p_b = pt(1, [0.2, 0.2, 0.6]); // interior of face 1
    let c = build_curve(&points(vec![p_a, p_edge, p_b]), &m, &topo, "c").unwrap();
    assert_eq!(c.segments.len(), 2);
    assert_eq!(c.segments[0].face, 0);
    assert_eq!(c.segments[1].face, 1);
    assert!(!c.closed);
    assert_connected(&c, &m);
    let pos = |p: &PointSpec| {
        let t = m.faces[p.face];
        (0..3)
            .map(|k| m.positions[t[k] as usize] * p.bary[k])
            .sum::<DVec3>()
    };
    let want = (pos(&p_edge) - pos(&p_a)).length() + (pos(&p_b) - pos(&p_edge)).length();
    assert!((c.length(&m, &m.positions) - want).abs() < 1e-12);
    // A vertex shared by faces of different cube sides: vertex 7 given in the top
    // face 2 = (4,5,7) links to a point in the right side face 10 = (1,3,7).
    let c = build_curve(
        &points(vec![
            pt(10, [0.3, 0.3, 0.4]),
            pt(2, [0.0, 0.0, 1.0]),
            pt(2, [0.4, 0.3, 0.3]),
        ]),
        &m,
        &topo,
        "c",
    )
    .unwrap();
    assert_eq!(c.segments.len(), 2);
    assert!(m.faces[c.segments[0].face as usize].contains(&7));
    assert_connected(&c, &m);
    // Points that share no face.
    let msg = bad_msg(build_curve(
        &points(vec![pt(0, [0.3, 0.3, 0.4]), pt(2, [0.3, 0.3, 0.4])]),
        &m,
        &topo,
        "constraint 5 ('arm')",
    ));
    assert!(
        msg.contains("share no face") && msg.contains("constraint 5 ('arm')"),
        "{msg}"
    );
    // Bad points.
    let msg = bad_msg(build_curve(
        &points(vec![pt(0, [0.3, 0.3, 0.4]), pt(50, [0.3, 0.3, 0.4])]),
        &m,
        &topo,
        "c",
    ));
    assert!(msg.contains("point 1") && msg.contains("50"), "{msg}");
    let msg = bad_msg(build_curve(
        &points(vec![pt(0, [0.3, 0.3, 0.3]), pt(0, [0.3, 0.3, 0.4])]),
        &m,
        &topo,
        "c",
    ));
    assert!(msg.contains("point 0") && msg.contains("sum"), "{msg}");
    let msg = bad_msg(build_curve(
        &points(vec![pt(0, [0.3, 0.3, 0.4])]),
        &m,
        &topo,
        "c",
    ));
    assert!(msg.contains("at least 2"), "{msg}");
}

// ---------------------------------------------------------------------------
// regions and handles
// ---------------------------------------------------------------------------

fn region() -> RegionSpec {
    RegionSpec::default()
}

#[test]
fn regions_select_the_right_faces() {
    let dir = tempfile::tempdir().unwrap();
    let job = job_in(dir.path());
    let mut m = cube();
    m.groups = vec![
        FaceGroup {
            name: "top".into(),
            faces: vec![2, 3],
        },
        FaceGroup {
            name: "sides".into(),
            faces: vec![5, 4],
        },
        FaceGroup {
            name: "top".into(),
            faces: vec![3, 0],
        },
    ];
    // faces: sorted and unique.
    let r = build_region(
        &RegionSpec {
            faces: Some(vec![5, 1, 5]),
            ..region()
        },
        &m,
        &job,
        "c",
    )
    .unwrap();
    assert_eq!(r.faces, vec![1, 5]);
    assert!((r.area(&m, &m.positions) - 1.0).abs() < 1e-12);
    // sphere around the centre of the top face: its two triangles' centroids are at
    // distance sqrt(2)/6 ~ 0.2357 from (0.5, 0.5, 1).
    let r = build_region(
        &RegionSpec {
            sphere: Some(metricdeform::job::SphereSpec {
                center: [0.5, 0.5, 1.0],
                radius: 0.25,
            }),
            ..region()
        },
        &m,
        &job,
        "c",
    )
    .unwrap();
    assert_eq!(r.faces, vec![2, 3]);
    // box: the lower half z <= 0.5 contains the bottom's centroids and the side
    // triangles whose centroids have z = 1/3.
    let r = build_region(
        &RegionSpec {
            box_: Some(metricdeform::job::BoxSpec {
                min: [-1.0, -1.0, -1.0],
                max: [2.0, 2.0, 0.5],
            }),
            ..region()
        },
        &m,
        &job,
        "c",
    )
    .unwrap();
    let want: Vec<u32> = (0..m.faces.len() as u32)
        .filter(|&f| m.centroid(&m.positions, f as usize).z <= 0.5)
        .collect();
    assert_eq!(r.faces, want);
    assert_eq!(r.faces.len(), 2 + 4);
    // group: union of all groups with that name.
    let r = build_region(
        &RegionSpec {
            group: Some("top".into()),
            ..region()
        },
        &m,
        &job,
        "c",
    )
    .unwrap();
    assert_eq!(r.faces, vec![0, 2, 3]);
    let msg = bad_msg(build_region(
        &RegionSpec {
            group: Some("ear".into()),
            ..region()
        },
        &m,
        &job,
        "constraint 4 ('ear')",
    ));
    assert!(
        msg.contains("'ear'") && msg.contains("sides") && msg.contains("top"),
        "{msg}"
    );
    assert!(msg.contains("constraint 4 ('ear')"), "{msg}");
    m.groups.clear();
    let msg = bad_msg(build_region(
        &RegionSpec {
            group: Some("ear".into()),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(msg.contains("no groups"), "{msg}");
}

#[test]
fn faces_file_regions() {
    let dir = tempfile::tempdir().unwrap();
    let job = job_in(dir.path());
    let m = cube();
    std::fs::write(dir.path().join("sel.txt"), "3 7\n  1\t7\n").unwrap();
    let spec = RegionSpec {
        faces_file: Some("sel.txt".into()),
        ..region()
    };
    let r = build_region(&spec, &m, &job, "c").unwrap();
    assert_eq!(r.faces, vec![1, 3, 7]);
    // Non-integer token.
    std::fs::write(dir.path().join("bad.txt"), "3 seven 1\n").unwrap();
    let msg = bad_msg(build_region(
        &RegionSpec {
            faces_file: Some("bad.txt".into()),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(msg.contains("bad.txt") && msg.contains("seven"), "{msg}");
    // Out of range.
    std::fs::write(dir.path().join("big.txt"), "3 12\n").unwrap();
    let msg = bad_msg(build_region(
        &RegionSpec {
            faces_file: Some("big.txt".into()),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(msg.contains("big.txt") && msg.contains("12"), "{msg}");
    // Missing file.
    let msg = bad_msg(build_region(
        &RegionSpec {
            faces_file: Some("missing.txt".into()),
            ..region()
        },
        &m,
        &job,
        "handle 2",
    ));
    assert!(
        msg.contains("missing.txt") && msg.contains("handle 2"),
        "{msg}"
    );
    // Empty file selects nothing.
    std::fs::write(dir.path().join("empty.txt"), "\n").unwrap();
    let msg = bad_msg(build_region(
        &RegionSpec {
            faces_file: Some("empty.txt".into()),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(msg.contains("selects no faces"), "{msg}");
}

#[test]
fn empty_and_out_of_range_regions() {
    let job = job_in(Path::new("."));
    let m = cube();
    let msg = bad_msg(build_region(
        &RegionSpec {
            sphere: Some(metricdeform::job::SphereSpec {
                center: [10.0, 10.0, 10.0],
                radius: 1.0,
            }),
            ..region()
        },
        &m,
        &job,
        "constraint 1 ('left ear')",
    ));
    assert!(
        msg.contains("selects no faces") && msg.contains("constraint 1 ('left ear')"),
        "{msg}"
    );
    let msg = bad_msg(build_region(
        &RegionSpec {
            faces: Some(vec![0, 4321]),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(
        msg.contains("4321") && msg.contains("out of range"),
        "{msg}"
    );
    let msg = bad_msg(build_region(
        &RegionSpec {
            faces: Some(vec![]),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(msg.contains("selects no faces"), "{msg}");
    let msg = bad_msg(build_region(
        &RegionSpec {
            vertices: Some(vec![0]),
            ..region()
        },
        &m,
        &job,
        "c",
    ));
    assert!(msg.contains("handles"), "{msg}");
}

#[test]
fn handle_vertices() {
    let job = job_in(Path::new("."));
    let m = cube();
    let h = HandleSpec {
        vertices: Some(vec![5, 2, 5]),
        ..Default::default()
    };
    assert_eq!(
        build_handle_vertices(&h, &m, &job, "handle 0").unwrap(),
        vec![2, 5]
    );
    // Region: all vertices of the top face's triangles.
    let h = HandleSpec {
        region: Some(RegionSpec {
            faces: Some(vec![2, 3]),
            ..region()
        }),
        translate: Some([0.0, 0.0, 1.0]),
        ..Default::default()
    };
    assert_eq!(
        build_handle_vertices(&h, &m, &job, "handle 0").unwrap(),
        vec![4, 5, 6, 7]
    );
    // `vertices` inside a handle's region is allowed.
    let h = HandleSpec {
        region: Some(RegionSpec {
            vertices: Some(vec![1]),
            ..region()
        }),
        ..Default::default()
    };
    assert_eq!(
        build_handle_vertices(&h, &m, &job, "handle 0").unwrap(),
        vec![1]
    );
    let h = HandleSpec {
        vertices: Some(vec![8]),
        ..Default::default()
    };
    let msg = bad_msg(build_handle_vertices(&h, &m, &job, "handle 3"));
    assert!(msg.contains("handle 3") && msg.contains('8'), "{msg}");
    let msg = bad_msg(build_handle_vertices(
        &HandleSpec::default(),
        &m,
        &job,
        "handle 1",
    ));
    assert!(msg.contains("handle 1"), "{msg}");
}

/// Issue 16 item 7: a job file and a faces_file with old-Mac line ends (lone CR).
#[test]
fn cr_only_job_and_faces_file() {
    let dir = tempfile::tempdir().unwrap();
    let text = "mesh = \"m.obj\"\n[[constraint]]\nkind = \"area\"\nname = \"ear\"\n\
                region = { faces_file = \"ear.txt\" }\nscale = 2.0\n[solver]\ntolerance = 1e-6\n";
    let p = dir.path().join("job.toml");
    std::fs::write(&p, text.replace('\n', "\r")).unwrap();
    let job = Job::load(&p).unwrap();
    assert_eq!(job.spec.constraint.len(), 1);
    assert_eq!(job.spec.constraint[0].name.as_deref(), Some("ear"));
    assert_eq!(job.spec.solver.tolerance, Some(1e-6));
    // JSON too.
    let p = dir.path().join("job.json");
    std::fs::write(&p, "{\"mesh\": \"m.obj\",\r\"constraint\": []\r}\r").unwrap();
    Job::load(&p).unwrap();
    // faces_file: a comment ends at a lone CR, like at a LF.
    std::fs::write(dir.path().join("ear.txt"), "0 1 # first\r2\r# none\r3").unwrap();
    let m = cube();
    let region = job.spec.constraint[0].region.as_ref().unwrap();
    let r = build_region(region, &m, &job, "constraint 1 ('ear')").unwrap();
    assert_eq!(r.faces, vec![0, 1, 2, 3]);
}

/// Issue 16 item 6: weights that make a system singular or meaningless are bad
/// input at load time naming the weight and the job file (they ended in
/// "linear solver: matrix is not positive definite", exit 1).
#[test]
fn singular_or_absurd_weights_are_bad_input() {
    let cases: [(&str, &[&str]); 7] = [
        (
            "k_f = 0.0, k_m = 0.0, k_l = 0.0, k_d = 0.0, k_r = 0.0, k_p = 0.0",
            &["k_f", "> 0"],
        ),
        ("k_f = 0.0", &["k_f", "> 0"]),
        ("k_f = 1e300", &["k_f = 1e300"]),
        ("k_m = 1e13", &["k_m"]),
        ("k_d = -1.0", &["k_d = -1"]),
        ("k_r = inf", &["k_r = inf"]),
        ("k_f = 1e-9, k_m = 1e6", &["k_f", "k_m", "negligible"]),
    ];
    for (weights, want) in cases {
        let text = format!("mesh = \"a.obj\"\n[solver]\nweights = {{ {weights} }}\n");
        let msg = bad_msg(toml_job(&text));
        assert!(msg.contains("job.toml"), "{weights}: {msg}");
        for w in want {
            assert!(msg.contains(w), "{weights}: {msg:?} should contain {w:?}");
        }
        let e = toml_job(&text).unwrap_err();
        assert_eq!(e.exit_code(), 2);
    }
    // Sane weights pass, k_d = k_r = 0 included (the scale-factor system keeps a floor).
    for weights in [
        "k_f = 1.0, k_m = 0.0, k_l = 0.0, k_p = 0.0",
        "k_d = 0.0, k_r = 0.0",
        "k_f = 1e12",
    ] {
        let text = format!("mesh = \"a.obj\"\n[solver]\nweights = {{ {weights} }}\n");
        toml_job(&text).unwrap();
    }
}

/// Issue 16 item 8: an empty region shows the mesh's bounding box and the sphere's
/// or box's extent; a plane that misses the mesh shows the mesh's extent along the
/// normal; messages from loading a job name the job file.
#[test]
fn empty_selections_say_where_the_mesh_is() {
    let dir = tempfile::tempdir().unwrap();
    let m = cube();
    let job = job_in(dir.path());
    let msg = bad_msg(build_region(
        &RegionSpec {
            sphere: Some(SphereSpec {
                center: [5.0, 5.0, 5.0],
                radius: 0.5,
            }),
            ..region()
        },
        &m,
        &job,
        "constraint 2 ('ear')",
    ));
    assert!(
        msg.contains("constraint 2 ('ear')")
            && msg.contains("min [0, 0, 0] max [1, 1, 1]")
            && msg.contains("[4.5, 4.5, 4.5] to [5.5, 5.5, 5.5]"),
        "{msg}"
    );
    let msg = bad_msg(build_region(
        &RegionSpec {
            box_: Some(BoxSpec {
                min: [2.0, 2.0, 2.0],
                max: [3.0, 3.0, 3.0],
            }),
            ..region()
        },
        &m,
        &job,
        "handle 1",
    ));
    assert!(
        msg.contains("min [0, 0, 0] max [1, 1, 1]") && msg.contains("[2.0, 2.0, 2.0]"),
        "{msg}"
    );
    let topo = Topology::build(&m);
    let msg = bad_msg(build_curve(
        &plane([0.0, 0.0, 5.0], [0.0, 0.0, 2.0]),
        &m,
        &topo,
        "constraint 1 (length)",
    ));
    assert!(
        msg.contains("spans -5 to -4 along the unit normal"),
        "{msg}"
    );

    // Through Problem::load: the job file is named.
    let mesh_path = dir.path().join("m.obj");
    metricdeform::mesh::io::write_mesh(&mesh_path, &m, &m.positions, None).unwrap();
    let p = dir.path().join("far.toml");
    std::fs::write(
        &p,
        "mesh = \"m.obj\"\n[[constraint]]\nkind = \"area\"\n\
         region = { sphere = { center = [9.0, 9.0, 9.0], radius = 1.0 } }\n",
    )
    .unwrap();
    let msg = bad_msg(Problem::load(&Job::load(&p).unwrap()).map(|_| ()));
    assert!(
        msg.starts_with(&p.display().to_string()) && msg.contains("constraint 1 (area)"),
        "{msg}"
    );
    // A missing mesh names the job too.
    let p = dir.path().join("nomesh.toml");
    std::fs::write(&p, "mesh = \"none.obj\"\n").unwrap();
    let e = Problem::load(&Job::load(&p).unwrap()).err().unwrap();
    assert_eq!(e.exit_code(), 2);
    assert!(
        e.to_string().contains("nomesh.toml") && e.to_string().contains("none.obj"),
        "{e}"
    );
}

/// An unnamed constraint's default name counts from 1 like the messages'
/// `constraint N (kind)`: the third table, a volume, is "volume 3".
#[test]
fn default_constraint_names_count_from_one() {
    let dir = tempfile::tempdir().unwrap();
    let m = cube();
    metricdeform::mesh::io::write_mesh(&dir.path().join("m.obj"), &m, &m.positions, None).unwrap();
    let p = dir.path().join("names.toml");
    std::fs::write(
        &p,
        "mesh = \"m.obj\"\n[[constraint]]\nkind = \"area\"\nregion = { faces = [0] }\n\
         [[constraint]]\nkind = \"area\"\nname = \"top\"\nregion = { faces = [1] }\n\
         [[constraint]]\nkind = \"volume\"\n",
    )
    .unwrap();
    let problem = Problem::load(&Job::load(&p).unwrap()).unwrap();
    let names: Vec<&str> = problem
        .constraints
        .iter()
        .map(|c| c.name.as_str())
        .collect();
    assert_eq!(names, ["area 1", "top", "volume 3"]);
}
