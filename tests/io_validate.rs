//! Mesh reading/writing and input validation.

use glam::DVec3;
use metricdeform::mesh::io::{read_mesh, write_mesh};
use metricdeform::mesh::topology::Topology;
use metricdeform::mesh::validate::{require_closed, validate, MeshCheck};
use metricdeform::{Error, Mesh};
use std::fs;
use std::path::{Path, PathBuf};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("data/meshes")
        .join(name)
}

fn check(mesh: &Mesh, file: &Path) -> metricdeform::Result<MeshCheck> {
    validate(mesh, &Topology::build(mesh), file)
}

fn bad_msg<T: std::fmt::Debug>(r: metricdeform::Result<T>) -> String {
    match r {
        Err(Error::BadInput(m)) => m,
        other => panic!("expected BadInput, got {other:?}"),
    }
}

fn write_file(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    fs::write(&p, text).unwrap();
    p
}

/// Positions with "ugly" binary expansions, to exercise exact round trips.
fn perturbed(mesh: &Mesh) -> Vec<DVec3> {
    mesh.positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let t = i as f64;
            *p + DVec3::new(
                (t * 0.7).sin() / 3.0,
                (t * 1.3).cos() * 1e-7,
                std::f64::consts::PI * 1e5 * (t * 0.1).sin(),
            )
        })
        .collect()
}

fn dir_entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn data_mesh_counts_after_fan_triangulation() {
    for (name, nv, nf) in [
        ("spot.obj", 2930, 5856),
        ("suzanne.obj", 507, 968),
        ("stanford-bunny.obj", 35947, 69451),
        ("teapot.obj", 3644, 6320),
        ("fandisk.obj", 6475, 12946),
        ("homer.obj", 6002, 12000),
    ] {
        let m = read_mesh(&data(name)).unwrap();
        assert_eq!(m.num_vertices(), nv, "{name} vertices");
        assert_eq!(m.num_faces(), nf, "{name} faces");
    }
}

#[test]
fn data_mesh_validation() {
    let spot = read_mesh(&data("spot.obj")).unwrap();
    let c = check(&spot, &data("spot.obj")).unwrap();
    assert!(c.closed);
    assert_eq!(c.boundary_edges, 0);
    assert_eq!(c.unreferenced_vertices, 0);
    assert_eq!(c.components, 1);
    require_closed(&c, &data("spot.obj"), "volume constraint 'v'").unwrap();

    let bunny_path = data("stanford-bunny.obj");
    let bunny = read_mesh(&bunny_path).unwrap();
    let c = check(&bunny, &bunny_path).unwrap();
    assert_eq!(c.boundary_edges, 223);
    assert_eq!(c.non_manifold_edges, 0);
    assert!(c.unreferenced_vertices > 0);
    assert!(!c.closed);
    let msg = bad_msg(require_closed(&c, &bunny_path, "volume constraint 'body'"));
    assert!(msg.contains("stanford-bunny.obj"), "{msg}");
    assert!(
        msg.contains("volume constraint 'body' needs a closed mesh, but it has 223 boundary edges"),
        "{msg}"
    );

    let teapot = read_mesh(&data("teapot.obj")).unwrap();
    let c = check(&teapot, &data("teapot.obj")).unwrap();
    assert_eq!(c.boundary_edges, 1036);

    for name in ["fandisk.obj", "homer.obj"] {
        let m = read_mesh(&data(name)).unwrap();
        check(&m, &data(name)).unwrap();
    }
}

#[test]
fn suzanne_rejected_as_non_manifold() {
    let p = data("suzanne.obj");
    let m = read_mesh(&p).unwrap();
    let topo = Topology::build(&m);
    assert_eq!(topo.non_manifold_edges.len(), 1);
    let msg = bad_msg(validate(&m, &topo, &p));
    assert!(msg.contains("non-manifold"), "{msg}");
    assert!(msg.contains("suzanne.obj"), "{msg}");
    assert!(msg.contains("edge ("), "{msg}");
}

#[test]
fn small_obj_fans_groups_and_index_syntax() {
    let dir = tempfile::tempdir().unwrap();
    let text = "\
# comment
mtllib x.mtl
v 0 0 0
v 1 0 0 1.0
v 1 1 0 0.5 0.5 0.5
v 0 1 0
vt 0 0
vn 0 0 1
v 2 0 0
v 2 1 0

f 1 2 3 4
g left both
usemtl m
s 1
f 1/1/1 2/1/1 4/1/1
f 2//1 -2//1 3//1
g right both
f -1/1 -2/1 -4/1 -3/1 -5/1
o thing one
f 1 3 6
g
f 2 3 4
";
    let p = write_file(dir.path(), "small.OBJ", text);
    let m = read_mesh(&p).unwrap();
    assert_eq!(m.num_vertices(), 6);
    assert_eq!(m.positions[2], DVec3::new(1.0, 1.0, 0.0));
    assert_eq!(
        m.faces,
        vec![
            // quad 1 2 3 4 fanned from its first corner
            [0, 1, 2],
            [0, 2, 3],
            [0, 1, 3],
            [1, 4, 2],
            // pentagon 6 5 3 4 2
            [5, 4, 2],
            [5, 2, 3],
            [5, 3, 1],
            [0, 2, 5],
            [1, 2, 3],
        ]
    );
    let names: Vec<&str> = m.groups.iter().map(|g| g.name.as_str()).collect();
    assert_eq!(names, ["left", "both", "right", "thing one"]);
    assert_eq!(m.groups[0].faces, vec![2, 3]);
    assert_eq!(m.groups[1].faces, vec![2, 3, 4, 5, 6]);
    assert_eq!(m.groups[2].faces, vec![4, 5, 6]);
    assert_eq!(m.groups[3].faces, vec![7]);
}

#[test]
fn obj_errors_name_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            "range.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n",
            &["range.obj", "line 5", "corner 3", "vertex 4", "3 vertices"][..],
        ),
        (
            "num.obj",
            "v 0 0 0\nv 1 x 0\n",
            &["num.obj", "line 2", "'x'"][..],
        ),
        (
            "zero.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
            &["zero.obj", "line 4", "index 0"][..],
        ),
        (
            "short.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n",
            &["short.obj", "line 4", "2 corners"][..],
        ),
        (
            "neg.obj",
            "v 0 0 0\nv 1 0 0\nf -1 -2 -3\nv 0 1 0\n",
            &["neg.obj", "line 3", "-3"][..],
        ),
        (
            "badidx.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x/1\n",
            &["badidx.obj", "line 4", "corner 3"][..],
        ),
    ];
    for (name, text, needles) in cases {
        let p = write_file(dir.path(), name, text);
        let msg = bad_msg(read_mesh(&p));
        for n in needles {
            assert!(msg.contains(n), "{name}: '{n}' not in: {msg}");
        }
    }
    // A forward reference to a vertex defined later is fine.
    let p = write_file(
        dir.path(),
        "fwd.obj",
        "f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n",
    );
    assert_eq!(read_mesh(&p).unwrap().faces, vec![[0, 1, 2]]);
}

#[test]
fn missing_file_and_unsupported_extension() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.obj");
    match read_mesh(&missing) {
        Err(e @ Error::Io { .. }) => assert!(e.to_string().contains("nope.obj"), "{e}"),
        other => panic!("expected Io error, got {other:?}"),
    }
    let p = write_file(dir.path(), "mesh.off", "OFF\n");
    let msg = bad_msg(read_mesh(&p));
    assert!(
        msg.contains("mesh.off") && msg.contains(".obj") && msg.contains(".stl"),
        "{msg}"
    );
}

#[test]
fn obj_round_trip_is_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let src = data("spot.obj");
    let m = read_mesh(&src).unwrap();
    let x = perturbed(&m);

    // Plain OBJ.
    let out = dir.path().join("plain.obj");
    write_mesh(&out, &m, &x, None).unwrap();
    let back = read_mesh(&out).unwrap();
    assert_eq!(back.faces, m.faces);
    assert_eq!(back.positions.len(), x.len());
    for (a, b) in back.positions.iter().zip(&x) {
        assert_eq!(
            a.to_array().map(f64::to_bits),
            b.to_array().map(f64::to_bits)
        );
    }

    // Source-preserving OBJ: every non-`v` line verbatim.
    let out = dir.path().join("kept.obj");
    write_mesh(&out, &m, &x, Some(&src)).unwrap();
    let back = read_mesh(&out).unwrap();
    assert_eq!(back.faces, m.faces);
    for (a, b) in back.positions.iter().zip(&x) {
        assert_eq!(
            a.to_array().map(f64::to_bits),
            b.to_array().map(f64::to_bits)
        );
    }
    let orig = fs::read_to_string(&src).unwrap();
    let new = fs::read_to_string(&out).unwrap();
    let ol: Vec<&str> = orig.lines().collect();
    let nl: Vec<&str> = new.lines().collect();
    assert_eq!(ol.len(), nl.len());
    for (a, b) in ol.iter().zip(&nl) {
        if a.starts_with("v ") {
            assert!(b.starts_with("v "));
        } else {
            assert_eq!(a, b);
        }
    }
    assert_eq!(dir_entries(dir.path()), ["kept.obj", "plain.obj"]);
}

#[test]
fn source_preserving_write_keeps_everything_but_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let text = "# head\r\nv 0 0 0\r\nvn 0 0 1\r\n  v\t1 0 0 0.2 0.3 0.4 # rgb\r\nv 0 1 0\r\ng a\r\nf 1//1 2//1 3//1\r\n";
    let src = write_file(dir.path(), "src.obj", text);
    let m = read_mesh(&src).unwrap();
    let x = vec![
        DVec3::new(0.1, -0.0, 1e-300),
        DVec3::new(1.5, 2.0, -3.25),
        DVec3::new(1.0 / 3.0, 2.0f64.sqrt(), 1e22),
    ];
    let out = dir.path().join("out.obj");
    write_mesh(&out, &m, &x, Some(&src)).unwrap();
    let got = fs::read_to_string(&out).unwrap();
    let want = format!(
        "# head\r\nv {} {} {}\r\nvn 0 0 1\r\n  v\t{} {} {} 0.2 0.3 0.4 # rgb\r\nv {} {} {}\r\ng a\r\nf 1//1 2//1 3//1\r\n",
        x[0].x, x[0].y, x[0].z, x[1].x, x[1].y, x[1].z, x[2].x, x[2].y, x[2].z
    );
    assert_eq!(got, want);
    let back = read_mesh(&out).unwrap();
    for (a, b) in back.positions.iter().zip(&x) {
        assert_eq!(
            a.to_array().map(f64::to_bits),
            b.to_array().map(f64::to_bits)
        );
    }
    assert_eq!(back.groups, m.groups);
    // The input itself is untouched, and writing onto it is refused.
    assert_eq!(fs::read_to_string(&src).unwrap(), text);
    let msg = bad_msg(write_mesh(&src, &m, &x, Some(&src)));
    assert!(msg.contains("output path equals the input mesh"), "{msg}");
    let same_via_dot = dir.path().join(".").join("src.obj");
    bad_msg(write_mesh(&same_via_dot, &m, &x, Some(&src)));
    assert_eq!(fs::read_to_string(&src).unwrap(), text);
}

#[test]
fn plain_obj_keeps_groups() {
    let dir = tempfile::tempdir().unwrap();
    let text =
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\ng a b\nf 2 4 3\ng b\nf 1 2 4\ng\nf 1 3 4\n";
    let src = write_file(dir.path(), "g.obj", text);
    let m = read_mesh(&src).unwrap();
    let out = dir.path().join("g2.obj");
    write_mesh(&out, &m, &m.positions, None).unwrap();
    let back = read_mesh(&out).unwrap();
    assert_eq!(back.faces, m.faces);
    assert_eq!(back.groups, m.groups);
    assert_eq!(m.groups[1].faces, vec![1, 2]);
}

#[test]
fn ply_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let m = read_mesh(&data("fandisk.obj")).unwrap();
    let x = perturbed(&m);
    let out = dir.path().join("out.PLY");
    write_mesh(&out, &m, &x, Some(&data("fandisk.obj"))).unwrap();
    let back = read_mesh(&out).unwrap();
    assert_eq!(back.faces, m.faces);
    assert_eq!(back.positions, x);
    assert!(back.groups.is_empty());
    assert_eq!(dir_entries(dir.path()), ["out.PLY"]);
}

#[test]
fn ascii_ply_with_polygons_and_extra_properties() {
    let dir = tempfile::tempdir().unwrap();
    let text = "ply
format ascii 1.0
comment test
element vertex 5
property float x
property float y
property float z
property uchar red
element face 2
property uchar flags
property list uchar uint vertex_index
element edge 1
property int vertex1
property int vertex2
end_header
0 0 0 255
1 0 0 255
1 1 0 255
0 1 0 255
0.5 0.5 1 0
7 4 0 1 2 3
0 3 4 0 1
0 1
";
    let p = write_file(dir.path(), "poly.ply", text);
    let m = read_mesh(&p).unwrap();
    assert_eq!(m.num_vertices(), 5);
    assert_eq!(m.positions[4], DVec3::new(0.5, 0.5, 1.0));
    assert_eq!(m.faces, vec![[0, 1, 2], [0, 2, 3], [4, 0, 1]]);

    let bad = text.replace("0 3 4 0 1", "0 3 4 0 9");
    let p = write_file(dir.path(), "bad.ply", &bad);
    let msg = bad_msg(read_mesh(&p));
    assert!(
        msg.contains("bad.ply") && msg.contains("face 1") && msg.contains("9"),
        "{msg}"
    );
}

#[test]
fn stl_round_trip_and_vertex_numbering() {
    let dir = tempfile::tempdir().unwrap();
    let m = read_mesh(&data("spot.obj")).unwrap();
    let out = dir.path().join("spot.stl");
    write_mesh(&out, &m, &m.positions, None).unwrap();
    let back = read_mesh(&out).unwrap();
    // spot is closed and every vertex is used, so merging recovers all vertices; they are
    // numbered by first occurrence.
    assert_eq!(back.num_faces(), m.num_faces());
    assert_eq!(back.num_vertices(), m.num_vertices());
    let mut map = vec![u32::MAX; m.num_vertices()];
    let mut next = 0u32;
    for (f, t) in m.faces.iter().enumerate() {
        for (k, &v) in t.iter().enumerate() {
            let v = v as usize;
            if map[v] == u32::MAX {
                map[v] = next;
                next += 1;
            }
            assert_eq!(back.faces[f][k], map[v]);
            let (a, b) = (back.positions[map[v] as usize], m.positions[v]);
            assert!((a - b).abs().max_element() <= b.abs().max_element() * 1e-7 + 1e-30);
            assert_eq!(a, b.as_vec3().as_dvec3());
        }
    }
    // Deterministic: the same file reads the same.
    let again = read_mesh(&out).unwrap();
    assert_eq!(again.faces, back.faces);
    assert_eq!(again.positions, back.positions);
    check(&back, &out).unwrap();
}

#[test]
fn ascii_stl_and_binary_stl_with_solid_header() {
    let dir = tempfile::tempdir().unwrap();
    let text = "solid t
facet normal 0 0 1
outer loop
vertex 0 0 0
vertex 1 0 0
vertex 0 1 0
endloop
endfacet
facet normal 0 0 1
outer loop
vertex 1 0 0
vertex 1 1 0
vertex -0 1 0
endloop
endfacet
endsolid t
";
    let p = write_file(dir.path(), "a.stl", text);
    let m = read_mesh(&p).unwrap();
    assert_eq!(m.faces, vec![[0, 1, 2], [1, 3, 2]]);
    assert_eq!(m.positions[3], DVec3::new(1.0, 1.0, 0.0));

    // Binary STL whose header happens to start with "solid ".
    let out = dir.path().join("b.stl");
    write_mesh(&out, &m, &m.positions, None).unwrap();
    let mut bytes = fs::read(&out).unwrap();
    bytes[..11].copy_from_slice(b"solid junk ");
    fs::write(&out, &bytes).unwrap();
    let b = read_mesh(&out).unwrap();
    assert_eq!(b.faces, m.faces);
    assert_eq!(b.positions, m.positions);
}

#[test]
fn validation_rejections() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("t.obj");
    let quad = Mesh {
        positions: vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(1.0, 1.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
            DVec3::new(5.0, 5.0, 5.0), // unreferenced
        ],
        faces: vec![[0, 1, 2], [0, 2, 3]],
        groups: vec![],
    };
    let c = check(&quad, &f).unwrap();
    assert_eq!(
        c,
        MeshCheck {
            boundary_edges: 4,
            non_manifold_edges: 0,
            unreferenced_vertices: 1,
            components: 1,
            closed: false,
            warnings: vec![format!(
                "mesh {}: 1 vertex is not used by any face (ignored; 0-based: 4)",
                f.display()
            )],
            ..MeshCheck::default()
        }
    );
    let msg = bad_msg(require_closed(&c, &f, "volume constraint 'x'"));
    assert!(
        msg.contains("t.obj") && msg.contains("4 boundary edges"),
        "{msg}"
    );

    // Unreferenced vertices may be anything.
    let mut m = quad.clone();
    m.positions[4].x = f64::NAN;
    check(&m, &f).unwrap();

    // NaN on a used vertex.
    let mut m = quad.clone();
    m.positions[2].y = f64::NAN;
    let msg = bad_msg(check(&m, &f));
    assert!(
        msg.contains("t.obj") && msg.contains("vertex 2") && msg.contains("NaN"),
        "{msg}"
    );

    // Empty.
    let mut m = quad.clone();
    m.faces.clear();
    let msg = bad_msg(check(&m, &f));
    assert!(msg.contains("no faces"), "{msg}");

    // Out of range.
    let mut m = quad.clone();
    m.faces.push([0, 2, 9]);
    let msg = bad_msg(check(&m, &f));
    assert!(msg.contains("face 2") && msg.contains("vertex 9"), "{msg}");

    // Repeated vertex index (an STL triangle with two equal corners reads so): a
    // zero-area face, accepted and named.
    let mut m = quad.clone();
    m.faces.push([0, 2, 2]);
    let c = check(&m, &f).unwrap();
    assert_eq!(c.zero_area_faces, vec![2]);
    assert!(
        c.warnings.iter().any(|w| w.contains("0-based: 2)")),
        "{:?}",
        c.warnings
    );
    assert_eq!(c.boundary_edges, 4);
    assert_eq!(c.non_manifold_edges, 0);

    // Zero area (collinear corners): accepted, named in a warning.
    let mut m = quad.clone();
    m.positions[3] = DVec3::new(2.0, 2.0, 0.0);
    let c = check(&m, &f).unwrap();
    assert_eq!(c.zero_area_faces, vec![1]);
    assert!(
        c.warnings.iter().any(|w| w.contains("t.obj")
            && w.contains("1 zero-area face")
            && w.contains("0-based: 1)")),
        "{:?}",
        c.warnings
    );

    // Many offenders: at most five listed, then "and N more".
    let mut m = quad.clone();
    for i in 0..8 {
        m.faces.push([1, 2, 9 + i]);
    }
    let msg = bad_msg(check(&m, &f));
    assert!(msg.contains("and 3 more"), "{msg}");
    assert!(msg.contains("face 6") && !msg.contains("face 7"), "{msg}");

    // Non-manifold edge: three triangles on edge (0, 1).
    let mut m = quad.clone();
    m.faces = vec![[0, 1, 2], [1, 0, 3], [0, 1, 4]];
    let msg = bad_msg(check(&m, &f));
    assert!(
        msg.contains("non-manifold") && msg.contains("edge (0, 1) has 3 faces"),
        "{msg}"
    );

    // Two components.
    let mut m = quad.clone();
    m.positions.push(DVec3::new(6.0, 5.0, 5.0));
    m.positions.push(DVec3::new(5.0, 6.0, 5.0));
    m.faces.push([4, 5, 6]);
    let c = check(&m, &f).unwrap();
    assert_eq!(c.components, 2);
    assert_eq!(c.unreferenced_vertices, 0);
}

#[test]
fn nan_in_obj_file_rejected_by_validation() {
    let dir = tempfile::tempdir().unwrap();
    let p = write_file(
        dir.path(),
        "nan.obj",
        "v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n",
    );
    let m = read_mesh(&p).unwrap();
    let msg = bad_msg(check(&m, &p));
    assert!(msg.contains("nan.obj") && msg.contains("vertex 2"), "{msg}");
}

#[test]
fn atomic_write_leaves_no_temporaries() {
    let dir = tempfile::tempdir().unwrap();
    let m = read_mesh(&data("homer.obj")).unwrap();
    for name in ["a.obj", "b.ply", "c.stl"] {
        let out = dir.path().join(name);
        write_mesh(&out, &m, &m.positions, None).unwrap();
        // Overwriting an existing output works too.
        write_mesh(&out, &m, &m.positions, None).unwrap();
    }
    assert_eq!(dir_entries(dir.path()), ["a.obj", "b.ply", "c.stl"]);

    // Missing directory: an error, and nothing is created anywhere.
    let missing = dir.path().join("no/such/dir/out.obj");
    match write_mesh(&missing, &m, &m.positions, None) {
        Err(e @ Error::Io { .. }) => assert!(e.to_string().contains("out.obj"), "{e}"),
        other => panic!("expected Io error, got {other:?}"),
    }
    assert!(!dir.path().join("no").exists());
    assert_eq!(dir_entries(dir.path()), ["a.obj", "b.ply", "c.stl"]);

    // Unsupported extension: nothing written.
    bad_msg(write_mesh(
        &dir.path().join("x.off"),
        &m,
        &m.positions,
        None,
    ));
    // Source with a different vertex count: error, nothing written.
    let r = write_mesh(
        &dir.path().join("d.obj"),
        &m,
        &m.positions,
        Some(&data("spot.obj")),
    );
    assert!(r.is_err());
    assert_eq!(dir_entries(dir.path()), ["a.obj", "b.ply", "c.stl"]);
}

/// Issue 16 item 7: files with old-Mac line ends (a lone CR) read like LF files
/// (OBJ said "no faces (1 vertex)" before).
#[test]
fn cr_only_line_endings_read_like_lf() {
    let dir = tempfile::tempdir().unwrap();
    let obj = "# cr\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\ng top\nf 1 2 3 4\nf 1/1 3/1 2/1\n";
    let lf = read_mesh(&write_file(dir.path(), "lf.obj", obj)).unwrap();
    assert_eq!(lf.num_faces(), 3);
    for (name, text) in [
        ("cr.obj", obj.replace('\n', "\r")),
        ("crlf.obj", obj.replace('\n', "\r\n")),
    ] {
        let m = read_mesh(&write_file(dir.path(), name, &text)).unwrap();
        assert_eq!(m.positions, lf.positions, "{name}");
        assert_eq!(m.faces, lf.faces, "{name}");
        assert_eq!(m.groups, lf.groups, "{name}");
    }
    // Line numbers in messages count CR line ends too.
    let bad = "v 0 0 0\rv 1 0 0\rv 0 1 0\rf 1 2 x\r";
    let msg = bad_msg(read_mesh(&write_file(dir.path(), "bad.obj", bad)));
    assert!(msg.contains("bad.obj line 4"), "{msg}");

    let ply = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
               property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
               end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    let p = read_mesh(&write_file(dir.path(), "cr.ply", &ply.replace('\n', "\r"))).unwrap();
    assert_eq!(p.faces, vec![[0, 1, 2]]);
    assert_eq!(p.positions[1], DVec3::new(1.0, 0.0, 0.0));

    // Binary PLY with a CR-terminated header: the body is left alone (its bytes
    // may contain 0x0d).
    let mut bin = b"ply\rformat binary_little_endian 1.0\relement vertex 3\rproperty double x\r\
property double y\rproperty double z\relement face 1\rproperty list uchar int vertex_indices\r\
end_header\r"
        .to_vec();
    let coords = [
        [13.0f64 / 1024.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    for c in coords {
        for v in c {
            bin.extend_from_slice(&v.to_le_bytes());
        }
    }
    bin.push(3);
    for i in [0i32, 1, 2] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let bp = dir.path().join("bin.ply");
    fs::write(&bp, &bin).unwrap();
    let b = read_mesh(&bp).unwrap();
    assert_eq!(b.faces, vec![[0, 1, 2]]);
    assert_eq!(b.positions[0].x, 13.0 / 1024.0);

    let stl = "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
               vertex 0 1 0\nendloop\nendfacet\nendsolid t\n";
    let s = read_mesh(&write_file(dir.path(), "cr.stl", &stl.replace('\n', "\r"))).unwrap();
    assert_eq!(s.faces, vec![[0, 1, 2]]);
}

/// A deformed copy of an OBJ with lone-CR line ends keeps them and replaces
/// each vertex's coordinates (the writer splits lines as the reader does).
#[test]
fn cr_only_obj_is_written_back_with_its_line_ends() {
    let dir = tempfile::tempdir().unwrap();
    let text = "# cr\rv 0 0 0\rv 1 0 0\rv 1 1 0\rf 1 2 3\r";
    let src = write_file(dir.path(), "cr.obj", text);
    let m = read_mesh(&src).unwrap();
    let x: Vec<DVec3> = m.positions.iter().map(|p| *p * 2.0).collect();
    let out = dir.path().join("out.obj");
    write_mesh(&out, &m, &x, Some(&src)).unwrap();
    let written = std::fs::read_to_string(&out).unwrap();
    assert_eq!(written, "# cr\rv 0 0 0\rv 2 0 0\rv 2 2 0\rf 1 2 3\r");
    assert_eq!(read_mesh(&out).unwrap().positions, x);
}
