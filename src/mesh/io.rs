//! Reading and writing meshes (OBJ, PLY, STL).
//!
//! # Index conventions (contract: "Indices")
//!
//! * **OBJ**: vertex `i` is the i-th `v` line of the file (0-based in [`Mesh`], 1-based in
//!   the file). Face lines are triangulated as fans from their first corner: a polygon with
//!   corners `c0 .. c(k-1)` becomes the triangles `(c0, ci, ci+1)` for `i = 1 .. k-2`, in
//!   that order, and triangles are numbered in file order. `g a b` puts the following faces
//!   into the groups `a` and `b`; `o name` puts them into the group `name` (the rest of the
//!   line is the name); a bare `g`/`o` puts them into no group.
//! * **PLY**: vertex `i` is the i-th `vertex` element, faces (`vertex_indices` or
//!   `vertex_index` lists) are fanned like OBJ polygons, in file order.
//! * **STL**: STL has no shared vertices. Corners with bit-for-bit identical coordinates are
//!   merged (`-0.0` counts as `0.0`); vertex `i` is the i-th *distinct* position in the
//!   order encountered when walking the triangles in file order and each triangle's three
//!   corners in file order. Face `f` is the f-th triangle of the file. This numbering is
//!   deterministic: reading the same file twice always gives the same mesh.
//!
//! # Writing
//!
//! [`write_mesh`] writes atomically (temporary file in the target directory, fsync,
//! rename) and never leaves a partial file behind. Text formats print coordinates with
//! Rust's shortest round-trip `Display` for `f64`, so reading the output back yields
//! bit-identical positions.

use crate::error::{Error, Result};
use crate::mesh::{FaceGroup, Mesh};
use glam::DVec3;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::fs;
use std::path::Path;

const SUPPORTED: &str = ".obj, .ply, .stl";

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Obj,
    Ply,
    Stl,
}

fn format_of(path: &Path) -> Result<Format> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    match ext.as_deref() {
        Some("obj") => Ok(Format::Obj),
        Some("ply") => Ok(Format::Ply),
        Some("stl") => Ok(Format::Stl),
        _ => Err(Error::bad(format!(
            "{}: unsupported mesh format (supported extensions: {SUPPORTED})",
            path.display()
        ))),
    }
}

fn io_err(path: &Path, source: std::io::Error) -> Error {
    Error::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Reads a triangle mesh; the format is chosen by the (case-insensitive) extension
/// `.obj`, `.ply` or `.stl`. See the module documentation for the index conventions.
///
/// Errors: [`Error::BadInput`] for an unsupported extension or malformed content (the
/// message names the file and, for OBJ, the line), [`Error::Io`] when the file cannot be
/// read.
pub fn read_mesh(path: &Path) -> Result<Mesh> {
    let format = format_of(path)?;
    let bytes = fs::read(path).map_err(|e| io_err(path, e))?;
    let mesh = match format {
        Format::Obj => parse_obj(&bytes, path)?,
        Format::Ply => parse_ply(&bytes, path)?,
        Format::Stl => parse_stl(&bytes, path)?,
    };
    log::debug!(
        "{}: read {} vertices, {} triangles, {} groups",
        path.display(),
        mesh.positions.len(),
        mesh.faces.len(),
        mesh.groups.len()
    );
    Ok(mesh)
}

// ---------------------------------------------------------------------------------------
// OBJ
// ---------------------------------------------------------------------------------------

/// Iterates over the lines of `bytes` with their 1-based line numbers. A line ends
/// at `\n`, `\r\n` or a lone `\r` (old Mac files), so files with any of these line
/// endings read the same.
fn lines(bytes: &[u8]) -> impl Iterator<Item = (usize, &[u8])> {
    let mut rest = bytes;
    let mut ln = 0usize;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        ln += 1;
        let end = rest
            .iter()
            .position(|&b| b == b'\n' || b == b'\r')
            .unwrap_or(rest.len());
        let line = &rest[..end];
        let mut next = end;
        if next < rest.len() {
            next += if rest[next] == b'\r' && rest.get(next + 1) == Some(&b'\n') {
                2
            } else {
                1
            };
        }
        rest = &rest[next..];
        Some((ln, line))
    })
}

/// `bytes` with every lone `\r` (a line end not followed by `\n`) turned into
/// `\n`, for parsers that only know `\n` and `\r\n`; borrowed when there is none.
fn lone_cr_to_lf(bytes: &[u8]) -> std::borrow::Cow<'_, [u8]> {
    let lone = |i: usize| bytes[i] == b'\r' && bytes.get(i + 1) != Some(&b'\n');
    if !(0..bytes.len()).any(lone) {
        return std::borrow::Cow::Borrowed(bytes);
    }
    let mut out = bytes.to_vec();
    for (i, b) in out.iter_mut().enumerate() {
        if lone(i) {
            *b = b'\n';
        }
    }
    std::borrow::Cow::Owned(out)
}

/// A PLY file whose header lines end in a lone `\r`: the header's (and, for an
/// ASCII body, the whole file's) line ends made `\n`; a binary body is left alone.
fn ply_line_ends(bytes: &[u8]) -> std::borrow::Cow<'_, [u8]> {
    let Some(pos) = bytes.windows(10).position(|w| w == b"end_header") else {
        return std::borrow::Cow::Borrowed(bytes);
    };
    let head_end = pos + 10;
    if bytes.get(head_end) != Some(&b'\r') || bytes.get(head_end + 1) == Some(&b'\n') {
        return std::borrow::Cow::Borrowed(bytes);
    }
    let ascii = bytes[..pos].windows(12).any(|w| w == b"format ascii");
    if ascii {
        return lone_cr_to_lf(bytes);
    }
    let mut out = lone_cr_to_lf(&bytes[..=head_end]).into_owned();
    out.extend_from_slice(&bytes[head_end + 1..]);
    std::borrow::Cow::Owned(out)
}

#[inline]
fn is_space(b: u8) -> bool {
    b == b' ' || b == b'\t' || b == b'\x0b' || b == b'\x0c' || b == b'\r'
}

/// Whitespace-separated tokens of a line.
#[inline]
fn tokens(line: &[u8]) -> impl Iterator<Item = &[u8]> {
    line.split(|&b| is_space(b)).filter(|t| !t.is_empty())
}

fn lossy(t: &[u8]) -> String {
    String::from_utf8_lossy(t).into_owned()
}

#[inline]
fn parse_f64(t: &[u8]) -> Option<f64> {
    std::str::from_utf8(t).ok()?.parse::<f64>().ok()
}

/// Parses an optionally signed decimal integer.
#[inline]
fn parse_i64(t: &[u8]) -> Option<i64> {
    let (neg, digits) = match t.first()? {
        b'-' => (true, &t[1..]),
        b'+' => (false, &t[1..]),
        _ => (false, t),
    };
    if digits.is_empty() || digits.len() > 18 {
        return None;
    }
    let mut v: i64 = 0;
    for &d in digits {
        if !d.is_ascii_digit() {
            return None;
        }
        v = v * 10 + (d - b'0') as i64;
    }
    Some(if neg { -v } else { v })
}

/// A face corner whose (positive) index points past the vertices read so far; checked
/// against the final vertex count at the end of the file.
struct ForwardRef {
    line: usize,
    corner: usize,
    index: i64,
}

fn parse_obj(bytes: &[u8], path: &Path) -> Result<Mesh> {
    let file = path.display();
    let mut positions: Vec<DVec3> = Vec::with_capacity(bytes.len() / 64);
    let mut faces: Vec<[u32; 3]> = Vec::with_capacity(bytes.len() / 32);
    let mut groups: Vec<FaceGroup> = Vec::new();
    let mut group_ids: HashMap<String, usize> = HashMap::new();
    let mut current: Vec<usize> = Vec::new();
    let mut forward: Vec<ForwardRef> = Vec::new();
    let mut corners: Vec<u32> = Vec::with_capacity(16);

    for (ln, line) in lines(bytes) {
        let mut toks = tokens(line);
        let Some(key) = toks.next() else { continue };
        match key {
            b"v" => {
                let mut c = [0.0f64; 3];
                for (k, ck) in c.iter_mut().enumerate() {
                    let Some(t) = toks.next() else {
                        return Err(Error::bad(format!(
                            "{file} line {ln}: vertex has {k} coordinates, expected 3"
                        )));
                    };
                    *ck = parse_f64(t).ok_or_else(|| {
                        Error::bad(format!(
                            "{file} line {ln}: cannot parse vertex coordinate '{}' as a number",
                            lossy(t)
                        ))
                    })?;
                }
                positions.push(DVec3::new(c[0], c[1], c[2]));
            }
            b"f" => {
                corners.clear();
                let nv = positions.len() as i64;
                for (k, t) in toks.enumerate() {
                    let pos = t.split(|&b| b == b'/').next().unwrap_or(t);
                    let idx = parse_i64(pos).ok_or_else(|| {
                        Error::bad(format!(
                            "{file} line {ln}: cannot parse face corner {} '{}' as a vertex index",
                            k + 1,
                            lossy(t)
                        ))
                    })?;
                    let resolved = if idx > 0 {
                        if idx > nv {
                            forward.push(ForwardRef {
                                line: ln,
                                corner: k + 1,
                                index: idx,
                            });
                        }
                        idx - 1
                    } else if idx < 0 {
                        let r = nv + idx;
                        if r < 0 {
                            return Err(Error::bad(format!(
                                "{file} line {ln}: face corner {} has relative index {idx} but only \
                                 {nv} vertices are defined before this line",
                                k + 1
                            )));
                        }
                        r
                    } else {
                        return Err(Error::bad(format!(
                            "{file} line {ln}: face corner {} has vertex index 0 (OBJ indices \
                             start at 1)",
                            k + 1
                        )));
                    };
                    if resolved > u32::MAX as i64 - 1 {
                        return Err(Error::bad(format!(
                            "{file} line {ln}: face corner {} refers to vertex {idx}, which is too \
                             large",
                            k + 1
                        )));
                    }
                    corners.push(resolved as u32);
                }
                if corners.len() < 3 {
                    return Err(Error::bad(format!(
                        "{file} line {ln}: face has {} corners, at least 3 are needed",
                        corners.len()
                    )));
                }
                let first = faces.len();
                for i in 1..corners.len() - 1 {
                    faces.push([corners[0], corners[i], corners[i + 1]]);
                }
                for &g in &current {
                    groups[g].faces.extend(first..faces.len());
                }
            }
            b"g" | b"o" => {
                let names: Vec<String> = if key == b"o" {
                    // The object name is the rest of the line.
                    let start = line
                        .iter()
                        .position(|&b| !is_space(b))
                        .map_or(line.len(), |p| p + 1);
                    let rest = String::from_utf8_lossy(&line[start..]).trim().to_string();
                    if rest.is_empty() {
                        vec![]
                    } else {
                        vec![rest]
                    }
                } else {
                    toks.map(lossy).collect()
                };
                current.clear();
                for name in names {
                    let id = *group_ids.entry(name.clone()).or_insert_with(|| {
                        groups.push(FaceGroup {
                            name,
                            faces: Vec::new(),
                        });
                        groups.len() - 1
                    });
                    if !current.contains(&id) {
                        current.push(id);
                    }
                }
            }
            // vt, vn, vp, s, usemtl, mtllib, l, p, comments and anything else.
            _ => {}
        }
    }

    let nv = positions.len() as i64;
    if let Some(bad) = forward.iter().find(|r| r.index > nv) {
        return Err(Error::bad(format!(
            "{file} line {}: face corner {} refers to vertex {} but the file has {nv} vertices",
            bad.line, bad.corner, bad.index
        )));
    }
    Ok(Mesh {
        positions,
        faces,
        groups,
    })
}

// ---------------------------------------------------------------------------------------
// PLY
// ---------------------------------------------------------------------------------------

mod ply_elems {
    use ply_rs_bw::ply::{Property, PropertyAccess, PropertyAccessResult};

    fn scalar(p: &Property) -> Option<f64> {
        Some(match *p {
            Property::Char(v) => v as f64,
            Property::UChar(v) => v as f64,
            Property::Short(v) => v as f64,
            Property::UShort(v) => v as f64,
            Property::Int(v) => v as f64,
            Property::UInt(v) => v as f64,
            Property::Float(v) => v as f64,
            Property::Double(v) => v,
            _ => return None,
        })
    }

    #[derive(Default)]
    pub struct Vertex(pub [f64; 3]);

    impl PropertyAccess for Vertex {
        fn new() -> Self {
            Self::default()
        }
        fn set_float(&mut self, name: &str, value: f32) -> PropertyAccessResult {
            self.set_double(name, value as f64)
        }
        fn set_double(&mut self, name: &str, value: f64) -> PropertyAccessResult {
            let k = match name {
                "x" => 0,
                "y" => 1,
                "z" => 2,
                _ => return PropertyAccessResult::Ignored,
            };
            self.0[k] = value;
            PropertyAccessResult::Set
        }
        fn set_property(&mut self, name: &str, p: Property) -> PropertyAccessResult {
            match scalar(&p) {
                Some(v) => self.set_double(name, v),
                None => PropertyAccessResult::Ignored,
            }
        }
    }

    #[derive(Default)]
    pub struct Face(pub Vec<i64>);

    fn conv<T: Copy + Into<i64>>(v: &[T]) -> Vec<i64> {
        v.iter().map(|&x| x.into()).collect()
    }

    impl PropertyAccess for Face {
        fn new() -> Self {
            Self::default()
        }
        fn set_property(&mut self, name: &str, p: Property) -> PropertyAccessResult {
            if name != "vertex_indices" && name != "vertex_index" {
                return PropertyAccessResult::Ignored;
            }
            self.0 = match p {
                Property::ListChar(v) => conv(&v),
                Property::ListUChar(v) => conv(&v),
                Property::ListShort(v) => conv(&v),
                Property::ListUShort(v) => conv(&v),
                Property::ListInt(v) => conv(&v),
                Property::ListUInt(v) => conv(&v),
                _ => return PropertyAccessResult::UnsupportedType,
            };
            PropertyAccessResult::Set
        }
    }

    /// Any other element: read and dropped.
    pub struct Skip;

    impl PropertyAccess for Skip {
        fn new() -> Self {
            Skip
        }
    }
}

fn parse_ply(bytes: &[u8], path: &Path) -> Result<Mesh> {
    use ply_rs_bw::parser::{Parser, Reader};
    let file = path.display();
    let perr =
        |e: ply_rs_bw::parser::ParseError| Error::bad(format!("{file}: cannot parse PLY: {e}"));
    let bytes = ply_line_ends(bytes);
    let mut reader = Reader::new(&bytes[..]);
    let vparser = Parser::<ply_elems::Vertex>::new();
    let fparser = Parser::<ply_elems::Face>::new();
    let sparser = Parser::<ply_elems::Skip>::new();
    let header = vparser.read_header(&mut reader).map_err(perr)?;

    let Some(vdef) = header.elements.get("vertex") else {
        return Err(Error::bad(format!(
            "{file}: PLY file has no 'vertex' element"
        )));
    };
    for p in ["x", "y", "z"] {
        if !vdef.properties.contains_key(p) {
            return Err(Error::bad(format!(
                "{file}: PLY 'vertex' element has no property '{p}'"
            )));
        }
    }
    if let Some(fdef) = header.elements.get("face") {
        if !fdef.properties.contains_key("vertex_indices")
            && !fdef.properties.contains_key("vertex_index")
        {
            return Err(Error::bad(format!(
                "{file}: PLY 'face' element has no 'vertex_indices' or 'vertex_index' list"
            )));
        }
    }

    let mut verts = Vec::new();
    let mut polys = Vec::new();
    for (name, def) in &header.elements {
        match name.as_str() {
            "vertex" => {
                verts = vparser
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(perr)?
            }
            "face" => {
                polys = fparser
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(perr)?
            }
            // A binary element without properties holds no bytes: reading its
            // `count` (up to 2^64 - 1) empty records would loop for ever.
            _ if def.properties.is_empty()
                && header.encoding != ply_rs_bw::ply::Encoding::Ascii => {}
            _ => {
                sparser
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(perr)?;
            }
        }
    }

    let positions: Vec<DVec3> = verts.iter().map(|v| DVec3::from_array(v.0)).collect();
    let nv = positions.len() as i64;
    let mut faces = Vec::with_capacity(polys.len());
    for (fi, poly) in polys.iter().enumerate() {
        let idx = &poly.0;
        if idx.len() < 3 {
            return Err(Error::bad(format!(
                "{file}: face {fi} (0-based) has {} corners, at least 3 are needed",
                idx.len()
            )));
        }
        if let Some((k, &bad)) = idx.iter().enumerate().find(|(_, &v)| v < 0 || v >= nv) {
            return Err(Error::bad(format!(
                "{file}: face {fi} (0-based) corner {} refers to vertex {bad} but the file has \
                 {nv} vertices (0-based indices)",
                k + 1
            )));
        }
        for i in 1..idx.len() - 1 {
            faces.push([idx[0] as u32, idx[i] as u32, idx[i + 1] as u32]);
        }
    }
    Ok(Mesh {
        positions,
        faces,
        groups: Vec::new(),
    })
}

// ---------------------------------------------------------------------------------------
// STL
// ---------------------------------------------------------------------------------------

/// Reads the triangles (corner positions only) of an ASCII or binary STL file.
fn stl_triangles(bytes: &[u8], path: &Path) -> Result<Vec<[[f32; 3]; 3]>> {
    // Binary files whose 80-byte header starts with "solid " are common; recognise binary
    // files by their exact size first, so that they are not mistaken for ASCII.
    if bytes.len() >= 84 {
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        if bytes.len() - 84 == 50 * n {
            let f =
                |o: usize| f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
            return Ok((0..n)
                .map(|t| {
                    let o = 84 + 50 * t + 12;
                    [
                        [f(o), f(o + 4), f(o + 8)],
                        [f(o + 12), f(o + 16), f(o + 20)],
                        [f(o + 24), f(o + 28), f(o + 32)],
                    ]
                })
                .collect());
        }
    }
    // ASCII STL with lone-CR line ends (old Mac files).
    let bytes = lone_cr_to_lf(bytes);
    let mut cursor = std::io::Cursor::new(&bytes[..]);
    let bad = |e: std::io::Error| Error::bad(format!("{}: cannot parse STL: {e}", path.display()));
    let reader = stl_io::create_stl_reader(&mut cursor).map_err(bad)?;
    reader
        .map(|t| t.map(|t| t.vertices.map(|v| v.0)).map_err(bad))
        .collect()
}

fn parse_stl(bytes: &[u8], path: &Path) -> Result<Mesh> {
    let tris = stl_triangles(bytes, path)?;
    let mut positions = Vec::new();
    let mut faces = Vec::with_capacity(tris.len());
    // Fx hashing, as Topology::build's: lookups only, no order decided.
    let mut ids: rustc_hash::FxHashMap<[u32; 3], u32> =
        rustc_hash::FxHashMap::with_capacity_and_hasher(tris.len() / 2 + 16, Default::default());
    for t in &tris {
        let mut face = [0u32; 3];
        for (k, p) in t.iter().enumerate() {
            // -0.0 and 0.0 are the same position; everything else merges bit for bit.
            let key = p.map(|c| if c == 0.0 { 0u32 } else { c.to_bits() });
            face[k] = *ids.entry(key).or_insert_with(|| {
                positions.push(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
                (positions.len() - 1) as u32
            });
        }
        faces.push(face);
    }
    Ok(Mesh {
        positions,
        faces,
        groups: Vec::new(),
    })
}

// ---------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------

/// Writes `mesh` with the vertex positions `positions` to `path`, in the format given by
/// the extension (`.obj`, `.ply`, `.stl`).
///
/// * OBJ with `source = Some(file.obj)`: the source text is copied line by line, with the
///   three coordinates of the i-th `v` line replaced by `positions[i]`; every other byte
///   (faces, groups, `vt`, `vn`, comments, extra vertex columns, line endings) is kept.
/// * OBJ otherwise: `v x y z` lines, then `f a b c` lines (1-based), with `g` lines so that
///   reading the file back gives the same groups.
/// * PLY: `binary_little_endian`, `double` x/y/z, `list uchar int vertex_indices`
///   ([`encode_mesh_with`] adds `double` vertex and face properties).
/// * STL: binary (f32 coordinates), one triangle per face with its unit normal.
///
/// Text formats print `f64` with `Display` (shortest round trip), so positions read back
/// bit-identical. The write is atomic ([`crate::output::write_atomic`]): a temporary
/// file `.<name>.tmp-<pid>-<n>` in the target directory is written, fsynced and renamed
/// over `path`; on error it is removed. Writing to the path of `source` is rejected
/// ([`Error::BadInput`]).
pub fn write_mesh(
    path: &Path,
    mesh: &Mesh,
    positions: &[DVec3],
    source: Option<&Path>,
) -> Result<()> {
    let data = encode_mesh(path, mesh, positions, source)?;
    crate::output::write_atomic(path, &data)
}

/// The bytes [`write_mesh`] writes to `path` (format from its extension), for a
/// caller that writes them together with other files ([`crate::output::stage`]).
pub fn encode_mesh(
    path: &Path,
    mesh: &Mesh,
    positions: &[DVec3],
    source: Option<&Path>,
) -> Result<Vec<u8>> {
    encode_mesh_with(path, mesh, positions, source, None)
}

/// Extra `double` properties of a PLY file: per vertex (after `x y z`) and per
/// face (after `vertex_indices`), each a name and one value per vertex / face.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyAttributes {
    pub vertex: Vec<(String, Vec<f64>)>,
    pub face: Vec<(String, Vec<f64>)>,
}

impl PlyAttributes {
    /// The attributes of a deformed mesh (contract: "PLY output carries face
    /// properties `scale` and `distortion` and vertex properties `dx dy dz`"):
    /// per face [`crate::distortion::face_scales`] and
    /// [`crate::distortion::face_distortions`] from `input` to `output`, per
    /// vertex `output - input`.
    pub fn deformation(mesh: &Mesh, input: &[DVec3], output: &[DVec3]) -> PlyAttributes {
        let d: Vec<DVec3> = input.iter().zip(output).map(|(a, b)| *b - *a).collect();
        PlyAttributes {
            vertex: vec![
                ("dx".into(), d.iter().map(|v| v.x).collect()),
                ("dy".into(), d.iter().map(|v| v.y).collect()),
                ("dz".into(), d.iter().map(|v| v.z).collect()),
            ],
            face: vec![
                (
                    "scale".into(),
                    crate::distortion::face_scales(mesh, input, output),
                ),
                (
                    "distortion".into(),
                    crate::distortion::face_distortions(mesh, input, output),
                ),
            ],
        }
    }

    /// Every column has one value per vertex / face, every name is one PLY token.
    fn check(&self, nv: usize, nf: usize) -> Result<()> {
        let cols = self
            .vertex
            .iter()
            .map(|c| (c, nv, "vertex"))
            .chain(self.face.iter().map(|c| (c, nf, "face")));
        for ((name, values), n, element) in cols {
            let token = !name.is_empty()
                && name.bytes().all(|b| b.is_ascii_graphic())
                && !["x", "y", "z", "vertex_indices"].contains(&name.as_str());
            if !token || values.len() != n {
                return Err(Error::Internal(format!(
                    "PLY {element} property '{name}': {} values for {n} elements \
                     (or a name that is not one new PLY token)",
                    values.len()
                )));
            }
        }
        Ok(())
    }
}

/// [`encode_mesh`], and for a `.ply` path the extra properties `attributes`
/// (ignored for OBJ and STL, which stay plain geometry).
pub fn encode_mesh_with(
    path: &Path,
    mesh: &Mesh,
    positions: &[DVec3],
    source: Option<&Path>,
    attributes: Option<&PlyAttributes>,
) -> Result<Vec<u8>> {
    let format = format_of(path)?;
    if positions.len() != mesh.positions.len() {
        return Err(Error::Internal(format!(
            "write_mesh: {} positions given for a mesh with {} vertices",
            positions.len(),
            mesh.positions.len()
        )));
    }
    if let Some(src) = source {
        if crate::output::same_file(path, src) {
            return Err(Error::bad(format!(
                "{}: output path equals the input mesh {}",
                path.display(),
                src.display()
            )));
        }
    }
    let obj_source = source.filter(|s| {
        format == Format::Obj
            && s.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| e.eq_ignore_ascii_case("obj"))
    });

    // Produce the contents first so that nothing touches the disk on a content error.
    let data = match format {
        Format::Obj => match obj_source {
            Some(src) => obj_from_source(src, positions)?,
            None => obj_plain(mesh, positions),
        },
        Format::Ply => {
            let none = PlyAttributes::default();
            let attributes = attributes.unwrap_or(&none);
            attributes.check(positions.len(), mesh.faces.len())?;
            ply_binary(mesh, positions, attributes)
        }
        Format::Stl => stl_binary(mesh, positions, path)?,
    };
    Ok(data)
}

fn push_vertex(out: &mut String, p: DVec3) {
    let _ = write!(out, "{} {} {}", p.x, p.y, p.z);
}

/// Copies the source OBJ, replacing the coordinates of the i-th `v` line by `positions[i]`.
fn obj_from_source(src: &Path, positions: &[DVec3]) -> Result<Vec<u8>> {
    let bytes = fs::read(src).map_err(|e| io_err(src, e))?;
    let mut out: Vec<u8> = Vec::with_capacity(bytes.len() + bytes.len() / 4);
    let mut coords = String::with_capacity(80);
    let mut vi = 0usize;
    let mut rest = &bytes[..];
    let mut ln = 0usize;
    while !rest.is_empty() {
        ln += 1;
        // The line with its terminator: `\n`, `\r\n` or a lone `\r` (old Mac
        // files, as the reader's `lines`), kept byte for byte.
        let end = rest
            .iter()
            .enumerate()
            .position(|(i, &b)| b == b'\n' || (b == b'\r' && rest.get(i + 1) != Some(&b'\n')))
            .map_or(rest.len(), |p| p + 1);
        let (line, tail) = rest.split_at(end);
        rest = tail;
        // Token spans within `line`.
        let mut spans = [(0usize, 0usize); 4];
        let mut ns = 0;
        let mut i = 0;
        while i < line.len() && ns < 4 {
            while i < line.len() && (is_space(line[i]) || line[i] == b'\n') {
                i += 1;
            }
            let s = i;
            while i < line.len() && !(is_space(line[i]) || line[i] == b'\n') {
                i += 1;
            }
            if i > s {
                spans[ns] = (s, i);
                ns += 1;
            }
        }
        let is_v = ns > 0 && &line[spans[0].0..spans[0].1] == b"v";
        if !is_v {
            out.extend_from_slice(line);
            continue;
        }
        if ns < 4 {
            return Err(Error::bad(format!(
                "{} line {ln}: vertex has {} coordinates, expected 3",
                src.display(),
                ns - 1
            )));
        }
        let Some(p) = positions.get(vi) else {
            return Err(Error::bad(format!(
                "{}: has more than the {} vertices of the mesh being written",
                src.display(),
                positions.len()
            )));
        };
        coords.clear();
        push_vertex(&mut coords, *p);
        out.extend_from_slice(&line[..spans[1].0]);
        out.extend_from_slice(coords.as_bytes());
        out.extend_from_slice(&line[spans[3].1..]);
        vi += 1;
    }
    if vi != positions.len() {
        return Err(Error::bad(format!(
            "{}: has {vi} vertices but the mesh being written has {}",
            src.display(),
            positions.len()
        )));
    }
    Ok(out)
}

fn obj_plain(mesh: &Mesh, positions: &[DVec3]) -> Vec<u8> {
    let mut s = String::with_capacity(positions.len() * 48 + mesh.faces.len() * 24);
    s.push_str("# written by metricdeform\n");
    for &p in positions {
        s.push_str("v ");
        push_vertex(&mut s, p);
        s.push('\n');
    }
    // Group membership per face, so that `g` lines can be emitted where it changes.
    let mut member: Vec<Vec<usize>> = Vec::new();
    if !mesh.groups.is_empty() {
        member = vec![Vec::new(); mesh.faces.len()];
        for (g, grp) in mesh.groups.iter().enumerate() {
            for &f in &grp.faces {
                if let Some(m) = member.get_mut(f) {
                    if !m.contains(&g) {
                        m.push(g);
                    }
                }
            }
        }
    }
    let none: Vec<usize> = Vec::new();
    let mut cur: &Vec<usize> = &none;
    for (f, t) in mesh.faces.iter().enumerate() {
        if let Some(m) = member.get(f) {
            if m != cur {
                s.push('g');
                for &g in m {
                    s.push(' ');
                    s.push_str(&mesh.groups[g].name);
                }
                s.push('\n');
                cur = m;
            }
        }
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s.into_bytes()
}

fn ply_binary(mesh: &Mesh, positions: &[DVec3], attributes: &PlyAttributes) -> Vec<u8> {
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by metricdeform\n\
         element vertex {}\nproperty double x\nproperty double y\nproperty double z\n",
        positions.len()
    );
    for (name, _) in &attributes.vertex {
        let _ = writeln!(header, "property double {name}");
    }
    let _ = write!(
        header,
        "element face {}\nproperty list uchar int vertex_indices\n",
        mesh.faces.len()
    );
    for (name, _) in &attributes.face {
        let _ = writeln!(header, "property double {name}");
    }
    header.push_str("end_header\n");
    let (nva, nfa) = (attributes.vertex.len(), attributes.face.len());
    let mut out = Vec::with_capacity(
        header.len() + positions.len() * (24 + 8 * nva) + mesh.faces.len() * (13 + 8 * nfa),
    );
    out.extend_from_slice(header.as_bytes());
    for (i, p) in positions.iter().enumerate() {
        for c in p.to_array() {
            out.extend_from_slice(&c.to_le_bytes());
        }
        for (_, values) in &attributes.vertex {
            out.extend_from_slice(&values[i].to_le_bytes());
        }
    }
    for (f, t) in mesh.faces.iter().enumerate() {
        out.push(3u8);
        for &v in t {
            out.extend_from_slice(&(v as i32).to_le_bytes());
        }
        for (_, values) in &attributes.face {
            out.extend_from_slice(&values[f].to_le_bytes());
        }
    }
    out
}

fn stl_binary(mesh: &Mesh, positions: &[DVec3], path: &Path) -> Result<Vec<u8>> {
    let tris: Vec<stl_io::Triangle> = mesh
        .faces
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|v| positions[v as usize]);
            let n = (b - a).cross(c - a).normalize_or_zero();
            let f = |p: DVec3| stl_io::Vector::new([p.x as f32, p.y as f32, p.z as f32]);
            stl_io::Triangle {
                normal: f(n),
                vertices: [f(a), f(b), f(c)],
            }
        })
        .collect();
    let mut out = Vec::with_capacity(84 + 50 * tris.len());
    stl_io::write_stl(&mut out, tris.iter()).map_err(|e| io_err(path, e))?;
    Ok(out)
}
