//! Pictures of a job (the contract's `--render`), on the CPU, with no GPU:
//! the input and the result side by side from one orthographic camera, faces
//! flat-shaded by a headlight and coloured by a per-face field (the scale
//! factor `sqrt(area out / area in)`, the quasi-conformal distortion, or the
//! displacement), with a labelled colour bar; each constraint's curve drawn
//! as a polyline and each region tinted (input) or outlined (result), named
//! with `original -> result` in a legend. `measure --render` draws the input
//! alone with every selection.
//!
//! Triangles are drawn far to near (painter's algorithm) with `tiny-skia`,
//! without anti-aliasing so that adjacent faces leave no seams and a pixel
//! has exactly its face's colour; a face smaller than a pixel is one pixel.
//! Lines and text are drawn over the surfaces (text with `embedded-graphics`'
//! built-in fonts). The output is deterministic: the same inputs give the
//! same bytes.

use crate::mesh::Mesh;
use crate::selection::SurfaceCurve;
use crate::Error;
use embedded_graphics::mono_font::ascii::{FONT_10X20, FONT_6X13, FONT_9X15};
use embedded_graphics::mono_font::{MonoFont, MonoTextStyle};
use embedded_graphics::pixelcolor::Rgb888;
use embedded_graphics::prelude::{DrawTarget, OriginDimensions, Point, RgbColor, Size};
use embedded_graphics::text::{Baseline, Text};
use embedded_graphics::Drawable;
use glam::DVec3;
use std::collections::HashMap;
use std::str::FromStr;
use tiny_skia::{
    Color, FillRule, Paint, PathBuilder, Pixmap, PremultipliedColorU8, Rect, Stroke, Transform,
};

/// The camera: where the picture looks from.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Default)]
pub enum View {
    /// From the front-right and a little above (azimuth 35 degrees, elevation
    /// 20 degrees): the default.
    #[default]
    ThreeQuarter,
    /// Along -Z, +Y up.
    Front,
    /// Along -X (from +X), +Y up.
    Side,
    /// Along -Y (from above), -Z up.
    Top,
    /// The isometric view: azimuth 45 degrees, elevation 35.26 degrees.
    Iso,
}

impl FromStr for View {
    type Err = String;
    fn from_str(s: &str) -> Result<View, String> {
        match s {
            "three-quarter" => Ok(View::ThreeQuarter),
            "front" => Ok(View::Front),
            "side" => Ok(View::Side),
            "top" => Ok(View::Top),
            "iso" => Ok(View::Iso),
            other => Err(format!(
                "unknown view '{other}': expected three-quarter, front, side, top or iso"
            )),
        }
    }
}

/// The per-face field the result's faces are coloured by.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Default)]
pub enum ColorBy {
    /// The realised scale factor `sqrt(area out / area in)`, on a diverging
    /// map centred at 1 (blue shrinks, red grows), symmetric in log scale.
    #[default]
    Scale,
    /// The quasi-conformal distortion (1 is a similarity), from 1 to the largest.
    Distortion,
    /// The mean displacement of the face's corners, as a % of the input's
    /// bbox diagonal, from 0 to the largest.
    Displacement,
}

impl FromStr for ColorBy {
    type Err = String;
    fn from_str(s: &str) -> Result<ColorBy, String> {
        match s {
            "scale" => Ok(ColorBy::Scale),
            "distortion" => Ok(ColorBy::Distortion),
            "displacement" => Ok(ColorBy::Displacement),
            other => Err(format!(
                "unknown colour '{other}': expected scale, distortion or displacement"
            )),
        }
    }
}

/// What a picture is made with.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct RenderParams {
    pub width: u32,
    pub height: u32,
    pub view: View,
    pub color: ColorBy,
}

impl Default for RenderParams {
    fn default() -> RenderParams {
        RenderParams {
            width: 1600,
            height: 800,
            view: View::default(),
            color: ColorBy::default(),
        }
    }
}

/// Smallest and largest picture sides (the layout needs room for the colour
/// bar and the legend; the largest keeps a picture under 1 GiB of pixels).
pub const MIN_SIZE: (u32, u32) = (320, 240);
pub const MAX_SIDE: u32 = 16384;

/// Parse `WxH` (`--render-size`).
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("render size '{s}': expected WIDTHxHEIGHT in pixels, e.g. 1600x800");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    check_size(w, h)?;
    Ok((w, h))
}

/// Whether a picture of `w` x `h` pixels is within [`MIN_SIZE`] and [`MAX_SIDE`].
fn check_size(w: u32, h: u32) -> Result<(), String> {
    if w < MIN_SIZE.0 || h < MIN_SIZE.1 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(format!(
            "render size {w}x{h}: each side must be from {}x{} to {MAX_SIDE}x{MAX_SIDE} pixels",
            MIN_SIZE.0, MIN_SIZE.1
        ));
    }
    Ok(())
}

/// What a selection marks on the mesh.
#[derive(Clone, Debug)]
pub enum Marked<'a> {
    /// A curve on the surface (it moves with the mesh).
    Curve(&'a SurfaceCurve),
    /// A set of faces.
    Faces(&'a [u32]),
    /// A set of vertices (handles, curvature regions), drawn as dots.
    Vertices(Vec<u32>),
    /// The whole mesh (a volume): in the legend only.
    Whole,
}

/// One selection to draw: its name, what it is (`length`, `handle`, ...) and
/// its numbers (`1.23 -> 1.476` for a result, `1.23` for an input). The
/// result panel labels the selection `name: values`, the input panel `name`,
/// and the legend `name (kind): values`.
#[derive(Clone, Debug)]
pub struct Annotation<'a> {
    pub name: String,
    pub kind: String,
    pub values: String,
    pub marked: Marked<'a>,
}

/// The colour map's value at `t` in [0, 1] for a field, as RGB: what a face
/// with that value is painted before shading, and what the colour bar shows.
pub fn color_map(color: ColorBy, t: f64) -> [u8; 3] {
    let t = if t.is_nan() { 0.5 } else { t.clamp(0.0, 1.0) };
    let c = match color {
        // RdBu runs red to blue; reversed so that growth is red.
        ColorBy::Scale => colorous::RED_BLUE.eval_continuous(1.0 - t),
        ColorBy::Distortion => colorous::YELLOW_ORANGE_RED.eval_continuous(t),
        ColorBy::Displacement => colorous::VIRIDIS.eval_continuous(t),
    };
    [c.r, c.g, c.b]
}

/// The field's per-face values and the range its map spans, with the bar's
/// title and the value at its middle.
struct Field {
    values: Vec<f64>,
    /// Maps a value to [0, 1].
    lo: f64,
    hi: f64,
    log: bool,
    title: &'static str,
}

impl Field {
    fn of(color: ColorBy, mesh: &Mesh, input: &[DVec3], output: &[DVec3]) -> Field {
        match color {
            ColorBy::Scale => {
                let values = crate::distortion::face_scales(mesh, input, output);
                // Symmetric in log scale around 1: [1/m, m].
                let m = values
                    .iter()
                    .filter(|s| s.is_finite() && **s > 0.0)
                    .map(|&s| s.max(1.0 / s))
                    .fold(1.0f64, f64::max)
                    .max(1.0 + 1e-6);
                Field {
                    values,
                    lo: 1.0 / m,
                    hi: m,
                    log: true,
                    title: "scale factor sqrt(area out / area in)",
                }
            }
            ColorBy::Distortion => {
                let values = crate::distortion::face_distortions(mesh, input, output);
                let hi = values
                    .iter()
                    .filter(|d| d.is_finite())
                    .fold(1.0f64, |a, &b| a.max(b))
                    .max(1.0 + 1e-6);
                Field {
                    values,
                    lo: 1.0,
                    hi,
                    log: false,
                    title: "quasi-conformal distortion (1 = similarity)",
                }
            }
            ColorBy::Displacement => {
                let diag = mesh.bbox_diagonal(input).max(f64::MIN_POSITIVE);
                let moved = crate::distortion::vertex_displacements(input, output, diag);
                let values: Vec<f64> = mesh
                    .faces
                    .iter()
                    .map(|t| t.iter().map(|&v| moved[v as usize]).sum::<f64>() / 3.0)
                    .collect();
                let hi = values
                    .iter()
                    .filter(|d| d.is_finite())
                    .fold(0.0f64, |a, &b| a.max(b))
                    .max(1e-12);
                Field {
                    values,
                    lo: 0.0,
                    hi,
                    log: false,
                    title: "displacement, % of the bbox diagonal",
                }
            }
        }
    }

    /// `v` on the map's [0, 1].
    fn t(&self, v: f64) -> f64 {
        if self.log {
            (v.ln() - self.lo.ln()) / (self.hi.ln() - self.lo.ln())
        } else {
            (v - self.lo) / (self.hi - self.lo)
        }
    }

    /// The value at `t` on the map (for the bar's labels).
    fn value_at(&self, t: f64) -> f64 {
        if self.log {
            (self.lo.ln() + t * (self.hi.ln() - self.lo.ln())).exp()
        } else {
            self.lo + t * (self.hi - self.lo)
        }
    }
}

/// Orthographic camera: screen axes `right`, `up`, and `forward` into the scene.
struct Camera {
    right: DVec3,
    up: DVec3,
    forward: DVec3,
    /// Pixels per model unit, and the model point at each panel's centre.
    scale: f64,
    center: (f64, f64),
}

impl Camera {
    fn new(view: View, points: &[&[DVec3]], panel: (f64, f64)) -> Camera {
        let (az, el): (f64, f64) = match view {
            View::ThreeQuarter => (35.0, 20.0),
            View::Front => (0.0, 0.0),
            View::Side => (90.0, 0.0),
            View::Top => (0.0, 90.0),
            View::Iso => (45.0, 35.264_389_682_754_654),
        };
        let (az, el) = (az.to_radians(), el.to_radians());
        // From the scene to the eye.
        let eye = DVec3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos());
        let forward = -eye;
        let hint = if el >= 89.0f64.to_radians() {
            -DVec3::Z
        } else {
            DVec3::Y
        };
        let right = forward.cross(hint).normalize();
        let up = right.cross(forward);
        let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for p in points.iter().flat_map(|x| x.iter()) {
            let (u, v) = (p.dot(right), p.dot(up));
            if u.is_finite() && v.is_finite() {
                u0 = u0.min(u);
                u1 = u1.max(u);
                v0 = v0.min(v);
                v1 = v1.max(v);
            }
        }
        if u0 > u1 {
            (u0, u1, v0, v1) = (-1.0, 1.0, -1.0, 1.0);
        }
        let extent_u = (u1 - u0).max(1e-300);
        let extent_v = (v1 - v0).max(1e-300);
        let scale = (0.9 * panel.0 / extent_u).min(0.9 * panel.1 / extent_v);
        let scale = if scale.is_finite() { scale } else { 1.0 };
        Camera {
            right,
            up,
            forward,
            scale,
            center: (0.5 * (u0 + u1), 0.5 * (v0 + v1)),
        }
    }

    /// Pixel coordinates of `p` in a panel whose centre is at `origin`.
    fn project(&self, p: DVec3, origin: (f64, f64)) -> (f32, f32) {
        let x = origin.0 + (p.dot(self.right) - self.center.0) * self.scale;
        let y = origin.1 - (p.dot(self.up) - self.center.1) * self.scale;
        (x as f32, y as f32)
    }
}

/// Picture layout: two panels (or one) above a band for the bar and legend.
struct Layout {
    width: f64,
    height: f64,
    /// Each panel's width and height.
    panel: (f64, f64),
    /// Top of the bottom band.
    band: f64,
    /// Titles, and labels and legend (smaller on pictures under 1200 pixels wide).
    title_font: &'static MonoFont<'static>,
    label_font: &'static MonoFont<'static>,
}

impl Layout {
    fn new(p: &RenderParams, panels: u32) -> Layout {
        let (w, h) = (p.width as f64, p.height as f64);
        let band = (h * 0.2).clamp(90.0, 160.0);
        let title = 30.0;
        let (title_font, label_font) = if w >= 1200.0 {
            (&FONT_10X20, &FONT_9X15)
        } else {
            (&FONT_9X15, &FONT_6X13)
        };
        Layout {
            width: w,
            height: h,
            panel: (w / panels as f64, h - band - title),
            band: h - band,
            title_font,
            label_font,
        }
    }

    /// The centre of panel `i`.
    fn origin(&self, i: u32) -> (f64, f64) {
        (self.panel.0 * (i as f64 + 0.5), 30.0 + 0.5 * self.panel.1)
    }
}

const BACKGROUND: [u8; 3] = [255, 255, 255];
const NEUTRAL: [u8; 3] = [200, 200, 200];

/// Per-selection colours (Tableau 10 without its red and blue, which the
/// scale map uses).
fn annotation_color(i: usize) -> [u8; 3] {
    const PICK: [usize; 8] = [1, 2, 4, 5, 6, 7, 8, 9];
    let c = colorous::TABLEAU10[PICK[i % PICK.len()]];
    [c.r, c.g, c.b]
}

fn rgb(c: [u8; 3]) -> Color {
    Color::from_rgba8(c[0], c[1], c[2], 255)
}

/// The picture of a run: input (left) and result (right), result faces
/// coloured by `params.color`, with a colour bar and each annotation. PNG bytes.
pub fn render_deformation(
    mesh: &Mesh,
    input: &[DVec3],
    output: &[DVec3],
    annotations: &[Annotation],
    params: &RenderParams,
) -> Result<Vec<u8>, Error> {
    let layout = Layout::new(params, 2);
    let mut pix = canvas(params)?;
    let cam = Camera::new(params.view, &[input, output], layout.panel);
    let field = Field::of(params.color, mesh, input, output);
    let tints = region_tints(mesh, annotations);
    // Input: neutral grey, regions tinted.
    let input_colors: Vec<[u8; 3]> = tints
        .iter()
        .map(|t| t.map_or(NEUTRAL, |c| mix(NEUTRAL, c, 0.6)))
        .collect();
    draw_surface(&mut pix, mesh, input, &input_colors, &cam, layout.origin(0));
    let result_colors: Vec<[u8; 3]> = field
        .values
        .iter()
        .map(|&v| color_map(params.color, field.t(v)))
        .collect();
    draw_surface(
        &mut pix,
        mesh,
        output,
        &result_colors,
        &cam,
        layout.origin(1),
    );
    draw_annotations(&mut pix, mesh, input, annotations, &cam, &layout, 0);
    draw_annotations(&mut pix, mesh, output, annotations, &cam, &layout, 1);
    let font = layout.title_font;
    text(&mut pix, "input", (10, 6), font, None);
    text(
        &mut pix,
        "result",
        ((layout.panel.0 + 10.0) as i32, 6),
        font,
        None,
    );
    draw_color_bar(&mut pix, &layout, &field, params.color);
    draw_legend(&mut pix, &layout, annotations, layout.width * 0.5 + 20.0);
    encode(pix)
}

/// The picture `measure --render` writes: the input alone with every
/// selection (regions tinted, curves drawn, vertex sets dotted). PNG bytes.
pub fn render_selections(
    mesh: &Mesh,
    input: &[DVec3],
    annotations: &[Annotation],
    params: &RenderParams,
) -> Result<Vec<u8>, Error> {
    let layout = Layout::new(params, 1);
    let mut pix = canvas(params)?;
    let cam = Camera::new(params.view, &[input], layout.panel);
    let colors: Vec<[u8; 3]> = region_tints(mesh, annotations)
        .iter()
        .map(|t| t.map_or(NEUTRAL, |c| mix(NEUTRAL, c, 0.6)))
        .collect();
    draw_surface(&mut pix, mesh, input, &colors, &cam, layout.origin(0));
    draw_annotations(&mut pix, mesh, input, annotations, &cam, &layout, 0);
    text(&mut pix, "input", (10, 6), layout.title_font, None);
    draw_legend(&mut pix, &layout, annotations, 20.0);
    encode(pix)
}

fn canvas(p: &RenderParams) -> Result<Pixmap, Error> {
    check_size(p.width, p.height).map_err(Error::bad)?;
    let mut pix = Pixmap::new(p.width, p.height).ok_or_else(|| {
        Error::Internal(format!("cannot make a {}x{} picture", p.width, p.height))
    })?;
    pix.fill(rgb(BACKGROUND));
    Ok(pix)
}

fn encode(pix: Pixmap) -> Result<Vec<u8>, Error> {
    pix.encode_png()
        .map_err(|e| Error::Internal(format!("PNG encoding failed: {e}")))
}

fn mix(a: [u8; 3], b: [u8; 3], t: f64) -> [u8; 3] {
    std::array::from_fn(|i| (a[i] as f64 * (1.0 - t) + b[i] as f64 * t).round() as u8)
}

/// Per face, the colour of the last region annotation that holds it.
fn region_tints(mesh: &Mesh, annotations: &[Annotation]) -> Vec<Option<[u8; 3]>> {
    let mut tint = vec![None; mesh.num_faces()];
    for (i, a) in annotations.iter().enumerate() {
        if let Marked::Faces(faces) = &a.marked {
            for &f in faces.iter() {
                if let Some(t) = tint.get_mut(f as usize) {
                    *t = Some(annotation_color(i));
                }
            }
        }
    }
    tint
}

/// Flat-shaded faces, far to near. A face's colour is scaled by
/// `0.3 + 0.7 |n . forward|` (a headlight, both sides lit).
fn draw_surface(
    pix: &mut Pixmap,
    mesh: &Mesh,
    x: &[DVec3],
    colors: &[[u8; 3]],
    cam: &Camera,
    origin: (f64, f64),
) {
    let mut order: Vec<(f64, u32)> = (0..mesh.num_faces())
        .map(|f| (mesh.centroid(x, f).dot(cam.forward), f as u32))
        .filter(|(d, _)| d.is_finite())
        .collect();
    // Far first; ties by face index, so the picture is deterministic.
    order.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let (w, h) = (pix.width() as f32, pix.height() as f32);
    let stride = pix.width() as usize;
    let mut paint = Paint {
        anti_alias: false,
        ..Paint::default()
    };
    let mut builder = PathBuilder::new();
    for (_, f) in order {
        let f = f as usize;
        let [a, b, c] = mesh.corners(x, f);
        let n = (b - a).cross(c - a).normalize_or_zero();
        let shade = 0.3 + 0.7 * n.dot(cam.forward).abs();
        let col = colors[f].map(|v| (v as f64 * shade).round() as u8);
        let p = [a, b, c].map(|q| cam.project(q, origin));
        let (x0, x1) = (
            p[0].0.min(p[1].0).min(p[2].0),
            p[0].0.max(p[1].0).max(p[2].0),
        );
        let (y0, y1) = (
            p[0].1.min(p[1].1).min(p[2].1),
            p[0].1.max(p[1].1).max(p[2].1),
        );
        if x1 < 0.0 || y1 < 0.0 || x0 >= w || y0 >= h {
            continue;
        }
        if x1 - x0 < 1.0 && y1 - y0 < 1.0 {
            // Smaller than a pixel: the pixel under its centroid.
            let cx = (p[0].0 + p[1].0 + p[2].0) / 3.0;
            let cy = (p[0].1 + p[1].1 + p[2].1) / 3.0;
            if cx >= 0.0 && cy >= 0.0 && cx < w && cy < h {
                pix.pixels_mut()[cy as usize * stride + cx as usize] =
                    PremultipliedColorU8::from_rgba(col[0], col[1], col[2], 255)
                        .expect("opaque colours are valid premultiplied colours");
            }
            continue;
        }
        builder.move_to(p[0].0, p[0].1);
        builder.line_to(p[1].0, p[1].1);
        builder.line_to(p[2].0, p[2].1);
        builder.close();
        if let Some(path) = builder.finish() {
            paint.set_color(rgb(col));
            pix.fill_path(
                &path,
                &paint,
                FillRule::Winding,
                Transform::identity(),
                None,
            );
            builder = path.clear();
        } else {
            builder = PathBuilder::new();
        }
    }
}

/// Curves as polylines, region outlines and vertex dots, each labelled
/// beside it: with its name, and on the result panel (panel 1, where
/// regions are outlined rather than tinted) with its values too.
fn draw_annotations(
    pix: &mut Pixmap,
    mesh: &Mesh,
    x: &[DVec3],
    annotations: &[Annotation],
    cam: &Camera,
    layout: &Layout,
    panel: u32,
) {
    // Panel 1 is always a result (a picture of one panel is an input).
    let result = panel == 1;
    let origin = layout.origin(panel);
    // Labels stay inside their panel.
    let right_edge = origin.0 + 0.5 * layout.panel.0;
    for (i, a) in annotations.iter().enumerate() {
        let color = annotation_color(i);
        let mut segments: Vec<[(f32, f32); 2]> = Vec::new();
        let mut dots: Vec<(f32, f32)> = Vec::new();
        match &a.marked {
            Marked::Curve(curve) => {
                for s in &curve.segments {
                    let (p, q) = s.ends(mesh, x);
                    segments.push([cam.project(p, origin), cam.project(q, origin)]);
                }
            }
            Marked::Faces(faces) if result => {
                for [p, q] in boundary_edges(mesh, faces) {
                    segments.push([
                        cam.project(x[p as usize], origin),
                        cam.project(x[q as usize], origin),
                    ]);
                }
            }
            Marked::Vertices(vs) => {
                dots.extend(vs.iter().map(|&v| cam.project(x[v as usize], origin)));
            }
            Marked::Faces(_) | Marked::Whole => {}
        }
        stroke_segments(pix, &segments, [20, 20, 20], 4.5);
        stroke_segments(pix, &segments, color, 2.5);
        for &(px, py) in &dots {
            if let Some(r) = Rect::from_xywh(px - 2.5, py - 2.5, 5.0, 5.0) {
                let mut paint = Paint::default();
                paint.set_color(rgb(color));
                pix.fill_rect(r, &paint, Transform::identity(), None);
            }
        }
        // The name beside the selection: right of its rightmost point, or
        // at the projected centroid of a region.
        let anchor = match &a.marked {
            Marked::Faces(faces) if !faces.is_empty() => {
                let c = faces
                    .iter()
                    .map(|&f| mesh.centroid(x, f as usize))
                    .fold(DVec3::ZERO, |s, p| s + p)
                    / faces.len() as f64;
                Some(cam.project(c, origin))
            }
            _ => segments
                .iter()
                .flatten()
                .chain(dots.iter())
                .copied()
                .max_by(|a, b| a.0.total_cmp(&b.0)),
        };
        if let Some((ax, ay)) = anchor {
            let label = if result && !a.values.is_empty() {
                format!("{}: {}", a.name, a.values)
            } else {
                a.name.clone()
            };
            let font = layout.label_font;
            let width = label.len() as f64 * font.character_size.width as f64;
            let x = (ax as f64 + 8.0).min(right_edge - width - 4.0).max(0.0);
            text(pix, &label, (x as i32, ay as i32 - 8), font, Some(color));
        }
    }
}

/// Edges of `faces` with one side outside the set, as vertex pairs.
fn boundary_edges(mesh: &Mesh, faces: &[u32]) -> Vec<[u32; 2]> {
    let mut count: HashMap<(u32, u32), u32> = HashMap::new();
    for &f in faces {
        let Some(t) = mesh.faces.get(f as usize) else {
            continue;
        };
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    let mut edges: Vec<[u32; 2]> = count
        .into_iter()
        .filter(|&(_, n)| n == 1)
        .map(|((a, b), _)| [a, b])
        .collect();
    edges.sort_unstable();
    edges
}

fn stroke_segments(pix: &mut Pixmap, segments: &[[(f32, f32); 2]], color: [u8; 3], width: f32) {
    if segments.is_empty() {
        return;
    }
    let mut b = PathBuilder::new();
    for [p, q] in segments {
        b.move_to(p.0, p.1);
        b.line_to(q.0, q.1);
    }
    if let Some(path) = b.finish() {
        let mut paint = Paint::default();
        paint.set_color(rgb(color));
        let stroke = Stroke {
            width,
            line_cap: tiny_skia::LineCap::Round,
            ..Stroke::default()
        };
        pix.stroke_path(&path, &paint, &stroke, Transform::identity(), None);
    }
}

/// The colour bar: centred in the bottom band of the result's half, its
/// title above, the values at both ends and the middle below.
fn draw_color_bar(pix: &mut Pixmap, layout: &Layout, field: &Field, color: ColorBy) {
    let x0 = (layout.width * 0.06).round();
    let width = (layout.width * 0.38).round();
    let y0 = (layout.band + 34.0).round();
    let height = 18.0;
    for i in 0..width as u32 {
        let t = i as f64 / (width - 1.0);
        if let Some(r) = Rect::from_xywh(x0 as f32 + i as f32, y0 as f32, 1.0, height as f32) {
            let mut paint = Paint {
                anti_alias: false,
                ..Paint::default()
            };
            paint.set_color(rgb(color_map(color, t)));
            pix.fill_rect(r, &paint, Transform::identity(), None);
        }
    }
    text(
        pix,
        field.title,
        (
            x0 as i32,
            y0 as i32 - 4 - layout.title_font.character_size.height as i32,
        ),
        layout.title_font,
        None,
    );
    for t in [0.0, 0.5, 1.0] {
        let label = format_value(field.value_at(t));
        let w = label.len() as f64 * layout.label_font.character_size.width as f64;
        let x = (x0 + t * (width - 1.0) - t * w).round() as i32;
        text(
            pix,
            &label,
            (x, (y0 + height) as i32 + 4),
            layout.label_font,
            None,
        );
    }
}

/// A number for a picture: 4 significant digits, in exponent form when very
/// small or large.
pub fn format_value(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    if v.abs() < 1e-3 || v.abs() >= 1e6 {
        return format!("{v:.3e}");
    }
    let decimals = (3 - v.abs().log10().floor() as i32).clamp(0, 12) as usize;
    format!("{v:.decimals$}")
}

/// One line per annotation in the bottom band from `x0`: a swatch of its
/// colour and its legend text.
fn draw_legend(pix: &mut Pixmap, layout: &Layout, annotations: &[Annotation], x0: f64) {
    let line = layout.label_font.character_size.height as f64 + 2.0;
    let lines = ((layout.height - layout.band - 12.0) / line)
        .floor()
        .max(1.0) as usize;
    for (i, a) in annotations.iter().enumerate() {
        if i >= lines {
            let more = format!("... and {} more", annotations.len() - i + 1);
            let y = layout.band + 8.0 + (lines - 1) as f64 * line;
            if let Some(r) = Rect::from_xywh(x0 as f32, y as f32, layout.width as f32, line as f32)
            {
                let mut paint = Paint::default();
                paint.set_color(rgb(BACKGROUND));
                pix.fill_rect(r, &paint, Transform::identity(), None);
            }
            text(
                pix,
                &more,
                (x0 as i32 + 18, y as i32),
                layout.label_font,
                None,
            );
            break;
        }
        let y = layout.band + 8.0 + i as f64 * line;
        if let Some(r) = Rect::from_xywh(x0 as f32, y as f32 + 2.0, 12.0, 12.0) {
            let mut paint = Paint::default();
            paint.set_color(rgb(annotation_color(i)));
            pix.fill_rect(r, &paint, Transform::identity(), None);
        }
        let legend = if a.values.is_empty() {
            format!("{} ({})", a.name, a.kind)
        } else {
            format!("{} ({}): {}", a.name, a.kind, a.values)
        };
        text(
            pix,
            &legend,
            (x0 as i32 + 18, y as i32),
            layout.label_font,
            None,
        );
    }
}

/// Text with its top-left at `at`, black on a translucent white box, or
/// (`color`) in that colour's darker shade.
fn text(pix: &mut Pixmap, s: &str, at: (i32, i32), font: &MonoFont, color: Option<[u8; 3]>) {
    // The built-in fonts are ASCII: anything else shows as '?'.
    let s: String = s
        .chars()
        .map(|c| {
            if c.is_ascii() && !c.is_ascii_control() {
                c
            } else {
                '?'
            }
        })
        .collect();
    let w = (s.len() as u32 * font.character_size.width) as f32;
    let h = font.character_size.height as f32;
    if let Some(r) = Rect::from_xywh(at.0 as f32 - 2.0, at.1 as f32 - 1.0, w + 4.0, h + 2.0) {
        let mut paint = Paint::default();
        paint.set_color(Color::from_rgba8(255, 255, 255, 200));
        pix.fill_rect(r, &paint, Transform::identity(), None);
    }
    let ink = color.map_or(Rgb888::BLACK, |c| {
        let d = mix(c, [0, 0, 0], 0.35);
        Rgb888::new(d[0], d[1], d[2])
    });
    let style = MonoTextStyle::new(font, ink);
    let mut target = Canvas(pix);
    let _ = Text::with_baseline(&s, Point::new(at.0, at.1), style, Baseline::Top).draw(&mut target);
}

/// `embedded-graphics`' view of a pixmap, for text.
struct Canvas<'a>(&'a mut Pixmap);

impl OriginDimensions for Canvas<'_> {
    fn size(&self) -> Size {
        Size::new(self.0.width(), self.0.height())
    }
}

impl DrawTarget for Canvas<'_> {
    type Color = Rgb888;
    type Error = std::convert::Infallible;
    fn draw_iter<I>(&mut self, pixels: I) -> Result<(), Self::Error>
    where
        I: IntoIterator<Item = embedded_graphics::Pixel<Self::Color>>,
    {
        let (w, h) = (self.0.width() as i32, self.0.height() as i32);
        let stride = w as usize;
        let data = self.0.pixels_mut();
        for embedded_graphics::Pixel(p, c) in pixels {
            if p.x >= 0 && p.y >= 0 && p.x < w && p.y < h {
                data[p.y as usize * stride + p.x as usize] =
                    PremultipliedColorU8::from_rgba(c.r(), c.g(), c.b(), 255)
                        .expect("opaque colours are valid premultiplied colours");
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_and_are_bounded() {
        assert_eq!(parse_size("1600x800"), Ok((1600, 800)));
        assert_eq!(parse_size("640X480"), Ok((640, 480)));
        assert!(parse_size("16x8").is_err());
        assert!(parse_size("1600").is_err());
        assert!(parse_size("axb").is_err());
        assert!(parse_size("20000x800").is_err());
    }

    #[test]
    fn the_scale_map_is_centred_at_one_and_symmetric_in_log() {
        let mesh = Mesh {
            positions: vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(1.0, 1.0, 0.0)],
            faces: vec![[0, 1, 2], [1, 3, 2]],
            groups: Vec::new(),
        };
        let mut y = mesh.positions.clone();
        y[3] = DVec3::new(3.0, 3.0, 0.0);
        let f = Field::of(ColorBy::Scale, &mesh, &mesh.positions, &y);
        assert!((f.t(1.0) - 0.5).abs() < 1e-12);
        assert!((f.t(f.hi) - 1.0).abs() < 1e-12);
        assert!((f.t(1.0 / f.hi)).abs() < 1e-12);
        assert!((f.value_at(0.5) - 1.0).abs() < 1e-12);
    }
}
