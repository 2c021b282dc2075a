//! The library without files: a mesh from arrays, typed demands, a run in
//! memory; bad typed input is a clear `Error::BadInput`, never a panic.

use metricdeform::job::Job;
use metricdeform::pipeline::Options;
use metricdeform::{
    deform, measure, Curvature, Curve, Demand, Error, FacePoint, Handle, Mesh, Problem, Region,
};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// A unit cube's surface: 8 vertices, 12 outward triangles.
fn cube() -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let v = vec![
        [0., 0., 0.],
        [1., 0., 0.],
        [1., 1., 0.],
        [0., 1., 0.],
        [0., 0., 1.],
        [1., 0., 1.],
        [1., 1., 1.],
        [0., 1., 1.],
    ];
    let f = vec![
        [0, 2, 1],
        [0, 3, 2],
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [1, 2, 6],
        [1, 6, 5],
        [2, 3, 7],
        [2, 7, 6],
        [3, 0, 4],
        [3, 4, 7],
    ];
    (v, f)
}

fn cube_mesh() -> Mesh {
    let (v, f) = cube();
    Mesh::from_arrays(&v, &f).unwrap()
}

/// The cube asked for 8 times its volume.
fn cube_volume_x8() -> Problem {
    Problem::new(
        cube_mesh(),
        "cube",
        &[Demand::volume().scale(8.0)],
        &[],
        &[],
    )
    .unwrap()
}

fn bad(r: metricdeform::Result<Problem>) -> String {
    match r {
        Err(Error::BadInput(m)) => m,
        Err(e) => panic!("expected bad input, got {e}"),
        Ok(_) => panic!("expected bad input, got a problem"),
    }
}

#[test]
fn bad_typed_input_is_named_never_a_panic() {
    let (v, f) = cube();
    let one = |d: Demand| Problem::new(cube_mesh(), "cube", &[d], &[], &[]);
    let cases: Vec<(metricdeform::Result<Problem>, &str)> = vec![
        (
            Problem::new(Mesh::from_arrays(&v, &[]).unwrap(), "cube", &[], &[], &[]),
            "no faces",
        ),
        (
            Problem::new(
                Mesh::from_arrays(&v, &[[0, 1, 8]]).unwrap(),
                "cube",
                &[],
                &[],
                &[],
            ),
            "out of range",
        ),
        (
            Problem::new(
                Mesh::from_arrays(
                    &[[f64::NAN, 0., 0.], [1., 0., 0.], [0., 1., 0.]],
                    &[[0, 1, 2]],
                )
                .unwrap(),
                "tri",
                &[],
                &[],
                &[],
            ),
            "non-finite",
        ),
        (
            one(Demand::area(Region::Vertices(vec![0])).named("lid")),
            "constraint 1 ('lid'): region `vertices` is only allowed for handles",
        ),
        (
            one(Demand::area(Region::Faces(vec![12]))),
            "constraint 1 (area): region face index 12 is out of range",
        ),
        (
            one(Demand::area(Region::Group("top".into()))),
            "group 'top' not found",
        ),
        (
            one(Demand::area(Region::Sphere {
                center: [9.0; 3],
                radius: 0.1,
            })),
            "selects no faces",
        ),
        (
            one(Demand::length(Curve::Path {
                vertices: vec![0],
                closed: false,
            })),
            "a path needs at least 2 vertices",
        ),
        (
            one(Demand::length(Curve::Plane {
                origin: [0.5; 3],
                normal: [0.0; 3],
            })),
            "plane normal is zero",
        ),
        (
            one(Demand::length(Curve::Points(vec![
                FacePoint {
                    face: 0,
                    bary: [0.5, 0.5, 0.5],
                },
                FacePoint {
                    face: 0,
                    bary: [1.0, 0.0, 0.0],
                },
            ]))),
            "must sum to 1",
        ),
        (
            one(Demand::volume().scale(-1.0)),
            "scale must be a finite number > 0",
        ),
        (one(Demand::volume().value(f64::INFINITY)), "value must be"),
        (
            Problem::new(
                cube_mesh(),
                "cube",
                &[],
                &[Handle {
                    region: Region::Vertices(vec![0]),
                    translate: [f64::NAN, 0.0, 0.0],
                }],
                &[],
            ),
            "handle 1: translate must be finite",
        ),
        (
            Problem::new(
                cube_mesh(),
                "cube",
                &[],
                &[],
                &[Curvature {
                    region: Region::Faces(vec![0]),
                    scale: f64::NAN,
                }],
            ),
            "curvature 1: scale must be a finite number",
        ),
    ];
    for (result, words) in cases {
        let msg = bad(result);
        assert!(msg.contains(words), "{msg:?} should say {words:?}");
    }
    // An index beyond 32 bits is refused when the mesh is built.
    let Err(Error::BadInput(msg)) = Mesh::from_arrays(&v, &[[0, 1, 1 << 40]]) else {
        panic!("a 2^40 index must be refused");
    };
    assert!(msg.contains("face 0 corner 2"), "{msg}");
    let _ = f;
}

#[test]
fn cube_volume_x8_is_the_cube_doubled() {
    let problem = cube_volume_x8();
    let result = deform(&problem, &Options::default()).unwrap();
    assert!(result.report.satisfied, "{:?}", result.report.reason);
    assert_eq!(result.face_scale.len(), 12);
    assert_eq!(result.face_distortion.len(), 12);
    for s in &result.face_scale {
        assert!((s - 2.0).abs() < 1e-3, "face scale {s}");
    }
    for d in &result.face_distortion {
        assert!((d - 1.0).abs() < 1e-3, "distortion {d}");
    }
    let (v, _) = cube();
    let shift = result.positions[0] - glam::DVec3::from_array(v[0]) * 2.0;
    for (p, q) in result.positions.iter().zip(&v) {
        let want = glam::DVec3::from_array(*q) * 2.0 + shift;
        assert!((*p - want).length() < 1e-3, "{p} vs {want}");
    }
}

#[test]
fn measure_reports_the_input() {
    let demands = [
        Demand::length(Curve::Plane {
            origin: [0.5, 0.5, 0.5],
            normal: [0.0, 0.0, 1.0],
        })
        .named("girth"),
        Demand::area(Region::Box {
            min: [-1.0, -1.0, 0.9],
            max: [2.0, 2.0, 1.1],
        }),
        Demand::volume().value(2.0),
    ];
    let problem = Problem::new(cube_mesh(), "cube", &demands, &[], &[]).unwrap();
    let report = measure(&problem, 1e-5);
    let originals: Vec<f64> = report.constraints.iter().map(|r| r.original).collect();
    for (got, want) in originals.iter().zip([4.0, 1.0, 1.0]) {
        assert!((got - want).abs() < 1e-12, "{originals:?}");
    }
    assert_eq!(report.constraints[0].name, "girth");
    assert_eq!(report.constraints[1].faces, Some(2));
    assert!(report.constraints[0].met && !report.constraints[2].met);
    assert!(!report.satisfied);
}

#[test]
fn an_interrupt_stops_the_run() {
    let problem = cube_volume_x8();
    let options = Options {
        interrupt: Some(Arc::new(AtomicBool::new(true))),
        ..Options::default()
    };
    assert!(matches!(
        deform(&problem, &options),
        Err(Error::Interrupted)
    ));
    assert_eq!(Error::Interrupted.exit_code(), 130);
}

/// The job file is a front end of the same types: a job and its typed
/// equivalent give the same problem.
#[test]
fn the_job_file_builds_the_same_problem() {
    let dir = tempfile::tempdir().unwrap();
    let job_path = dir.path().join("job.toml");
    std::fs::write(
        &job_path,
        r#"mesh = "cube.obj"
[[constraint]]
kind = "length"
curve = { path = [0, 1, 2], closed = true }
scale = 1.2
[[constraint]]
kind = "area"
name = "top"
region = { faces = [2, 3] }
value = 3.0
[[handle]]
vertices = [0]
translate = [0.0, 0.0, 0.5]
[[curvature]]
region = { sphere = { center = [0.5, 0.5, 1.0], radius = 0.6 } }
scale = 2.0
"#,
    )
    .unwrap();
    let job = Job::load(&job_path).unwrap();
    let from_job = Problem::build(&job, cube_mesh(), Path::new("cube.obj")).unwrap();
    let typed = Problem::new(
        cube_mesh(),
        "cube.obj",
        &[
            Demand::length(Curve::Path {
                vertices: vec![0, 1, 2],
                closed: true,
            })
            .scale(1.2),
            Demand::area(Region::Faces(vec![2, 3]))
                .value(3.0)
                .named("top"),
        ],
        &[Handle {
            region: Region::Vertices(vec![0]),
            translate: [0.0, 0.0, 0.5],
        }],
        &[Curvature {
            region: Region::Sphere {
                center: [0.5, 0.5, 1.0],
                radius: 0.6,
            },
            scale: 2.0,
        }],
    )
    .unwrap();
    let rows = |p: &Problem| -> Vec<(String, f64, f64)> {
        p.constraints
            .iter()
            .map(|c| (c.name.clone(), c.original, c.target))
            .collect()
    };
    assert_eq!(rows(&from_job), rows(&typed));
    assert_eq!(from_job.handles.len(), 1);
    assert_eq!(
        from_job.handles[0].target.to_array(),
        typed.handles[0].target.to_array()
    );
    assert_eq!(from_job.curvature[0].vertices, typed.curvature[0].vertices);
    assert!((rows(&typed)[0].2 - 1.2 * (2.0 + 2f64.sqrt())).abs() < 1e-12);
}
