//! Pictures (`--render`): the PNG's size, the two meshes where they should be,
//! the colour bar, a face's colour from its scale, and the CPU path with no
//! Vulkan driver at all.

use glam::DVec3;
use metricdeform::render::{color_map, render_deformation, ColorBy, RenderParams, View};
use metricdeform::Mesh;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use tiny_skia::Pixmap;

fn meshes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes")
}

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_metricdeform"));
    c.env_remove("METRICDEFORM_BACKEND");
    c
}

const DEMO_JOB: &str = include_str!("../examples/spot-demo.toml");

/// A directory with spot and the demo job (its mesh beside it).
fn demo_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    let job = DEMO_JOB.replace("../data/meshes/spot.obj", "spot.obj");
    std::fs::write(dir.path().join("job.toml"), job).unwrap();
    dir
}

fn run(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = bin();
    c.args(args).current_dir(dir);
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

fn rgb(p: &Pixmap, x: u32, y: u32) -> [u8; 3] {
    let c = p.pixel(x, y).unwrap().demultiply();
    [c.red(), c.green(), c.blue()]
}

/// Pixels in the rectangle that are not the white background.
fn drawn(p: &Pixmap, x0: u32, x1: u32, y0: u32, y1: u32) -> usize {
    (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .filter(|&(x, y)| rgb(p, x, y) != [255, 255, 255])
        .count()
}

/// A row holding the map's bottom and top colours, bottom left of top, at
/// least a fifth of the picture apart, with about the map's middle halfway.
fn has_color_bar(p: &Pixmap, color: ColorBy) -> bool {
    let (lo, mid, hi) = (
        color_map(color, 0.0),
        color_map(color, 0.5),
        color_map(color, 1.0),
    );
    (0..p.height()).any(|y| {
        let row: Vec<[u8; 3]> = (0..p.width()).map(|x| rgb(p, x, y)).collect();
        let first = |c: [u8; 3]| row.iter().position(|&r| r == c);
        match (first(lo), first(hi)) {
            (Some(a), Some(c)) if a < c && c - a > p.width() as usize / 5 => {
                let m = row[(a + c) / 2];
                (0..3).all(|k| m[k].abs_diff(mid[k]) <= 8)
            }
            _ => false,
        }
    })
}

/// `deform job.toml --backend cpu --quiet --render pic.png EXTRA` in `dir`
/// with `env`: it must exit 0 and say it wrote the picture; the picture.
fn deform_picture(dir: &Path, extra: &[&str], env: &[(&str, &str)]) -> Pixmap {
    let mut args = vec![
        "deform",
        "job.toml",
        "--backend",
        "cpu",
        "--quiet",
        "--render",
        "pic.png",
    ];
    args.extend(extra);
    let out = run(dir, &args, env);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("wrote pic.png"));
    Pixmap::load_png(dir.join("pic.png")).unwrap()
}

#[test]
fn deform_render_writes_both_meshes_and_the_color_bar() {
    let dir = demo_dir();
    let p = deform_picture(dir.path(), &["--render-size", "900x500"], &[]);
    assert_eq!((p.width(), p.height()), (900, 500));
    // Each half's mesh area (below the titles, above the bottom band) holds
    // a mesh: at least 5 % of its pixels are drawn.
    let (top, bottom) = (40, 500 - 100);
    let area = (450 * (bottom - top)) as usize;
    let left = drawn(&p, 0, 450, top, bottom);
    let right = drawn(&p, 450, 900, top, bottom);
    assert!(left > area / 20, "left half: {left} of {area} pixels drawn");
    assert!(
        right > area / 20,
        "right half: {right} of {area} pixels drawn"
    );
    assert!(has_color_bar(&p, ColorBy::Scale), "no colour bar");
}

#[test]
fn the_picture_needs_no_vulkan_driver() {
    let dir = demo_dir();
    let p = deform_picture(
        dir.path(),
        &["--color", "distortion", "--view", "front"],
        &[("VK_ICD_FILENAMES", "/nonexistent")],
    );
    assert_eq!((p.width(), p.height()), (1600, 800));
    assert!(has_color_bar(&p, ColorBy::Distortion), "no colour bar");
}

/// The same inputs give the same bytes (the CPU path is deterministic).
#[test]
fn the_picture_is_deterministic() {
    let dir = demo_dir();
    for name in ["a.png", "b.png"] {
        let out = run(
            dir.path(),
            &["measure", "job.toml", "--render", name, "--view", "iso"],
            &[],
        );
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let a = std::fs::read(dir.path().join("a.png")).unwrap();
    let b = std::fs::read(dir.path().join("b.png")).unwrap();
    assert!(a == b, "two renders of the same job differ");
}

/// `measure --render`: the input alone, its regions tinted in their legend
/// colour: the head region's tint shows.
#[test]
fn measure_render_draws_the_input_and_its_selections() {
    let dir = demo_dir();
    let out = run(
        dir.path(),
        &[
            "measure",
            "job.toml",
            "--render",
            "sel.png",
            "--render-size",
            "800x600",
        ],
        &[],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let p = Pixmap::load_png(dir.path().join("sel.png")).unwrap();
    assert_eq!((p.width(), p.height()), (800, 600));
    assert!(drawn(&p, 0, 800, 40, 480) > 800 * 440 / 20);
    // Grey faces (the untinted input) have r = g = b; the head's tint does not.
    let tinted = (40..480)
        .flat_map(|y| (0..800).map(move |x| (x, y)))
        .map(|(x, y)| rgb(&p, x, y))
        .filter(|c| *c != [255, 255, 255] && (c[0] != c[1] || c[1] != c[2]))
        .count();
    assert!(tinted > 500, "only {tinted} tinted pixels");
}

/// Bad picture arguments are usage errors (exit 2), and nothing is written.
#[test]
fn bad_picture_arguments_exit_2_and_write_nothing() {
    let dir = demo_dir();
    let before: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    for args in [
        vec!["--render", "p.png", "--render-size", "10x10"],
        vec!["--render", "p.png", "--view", "underneath"],
        vec!["--render", "p.png", "--color", "mood"],
        vec!["--render", "spot.obj"],
        vec!["--render", "missing/p.png"],
        vec!["--render", "same.png", "--report", "same.png"],
    ] {
        let mut all = vec!["deform", "job.toml", "--backend", "cpu", "--quiet"];
        all.extend(args.iter());
        let out = run(dir.path(), &all, &[]);
        assert_eq!(
            out.status.code(),
            Some(2),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let after: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(after.len(), before.len(), "{args:?} wrote a file");
    }
    let spot = std::fs::read(dir.path().join("spot.obj")).unwrap();
    assert_eq!(spot, std::fs::read(meshes().join("spot.obj")).unwrap());
}

/// A flat plate seen from the front (every face lit fully, so a pixel has
/// exactly its face's colour), stretched along x more and more towards its
/// right edge: the faces there have the largest scale and get the colour of
/// the top of the map; the input is the neutral grey.
#[test]
fn the_largest_scale_gets_the_top_colour() {
    let n = 20;
    let mut positions = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            positions.push(DVec3::new(i as f64 / n as f64, j as f64 / n as f64, 0.0));
        }
    }
    let mut faces = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let v = (j * (n + 1) + i) as u32;
            let w = v + (n + 1) as u32;
            faces.push([v, v + 1, w + 1]);
            faces.push([v, w + 1, w]);
        }
    }
    let mesh = Mesh {
        positions: positions.clone(),
        faces,
        groups: Vec::new(),
    };
    // x -> x + x^2: the stretch 1 + 2x grows to the right.
    let out: Vec<DVec3> = positions
        .iter()
        .map(|p| DVec3::new(p.x + p.x * p.x, p.y, 0.0))
        .collect();
    // Growth is red, shrinking blue (the documented map).
    let top = color_map(ColorBy::Scale, 1.0);
    let bottom = color_map(ColorBy::Scale, 0.0);
    assert!(
        top[0] > top[2] && bottom[2] > bottom[0],
        "{top:?} {bottom:?}"
    );
    let params = RenderParams {
        width: 800,
        height: 400,
        view: View::Front,
        color: ColorBy::Scale,
    };
    let png = render_deformation(&mesh, &positions, &out, &[], &params).unwrap();
    let p = Pixmap::decode_png(&png).unwrap();
    // The middle row of the mesh area; the rightmost drawn pixel of each half.
    let y = 40 + (400 - 40 - 90) / 2;
    let rightmost = |x0: u32, x1: u32| (x0..x1).rev().find(|&x| rgb(&p, x, y) != [255, 255, 255]);
    let r = rightmost(400, 800).expect("the result is drawn");
    assert_eq!(rgb(&p, r - 2, y), color_map(ColorBy::Scale, 1.0));
    let leftmost = (400..800)
        .find(|&x| rgb(&p, x, y) != [255, 255, 255])
        .unwrap();
    assert_ne!(rgb(&p, leftmost + 2, y), color_map(ColorBy::Scale, 1.0));
    let l = rightmost(0, 400).expect("the input is drawn");
    assert_eq!(rgb(&p, l - 2, y), [200, 200, 200]);
}

/// The gallery's jobs (`scripts/gallery.sh`) stay valid: each measures, and
/// names each of its constraints.
#[test]
fn the_gallery_jobs_measure() {
    let examples = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    for (job, names) in [
        ("bunny-ears.toml", &["ears", "body girth"][..]),
        (
            "homer-table1.toml",
            &["waist", "head girth", "upper body", "volume"][..],
        ),
    ] {
        let out = bin()
            .arg("measure")
            .arg(examples.join(job))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{job}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let stdout = String::from_utf8_lossy(&out.stdout);
        for name in names {
            assert!(stdout.contains(name), "{job}: no {name} in\n{stdout}");
        }
    }
}
