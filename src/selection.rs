//! Selections: what a constraint, handle or curvature region picks on the
//! INPUT mesh (contract: "Curves", "Regions"), as typed values ([`Curve`],
//! [`Region`]) and as their resolutions on a mesh ([`SurfaceCurve`],
//! [`FaceSet`]).
//!
//! A [`Curve`] or [`Region`] is checked in one place: [`Curve::validate`] and
//! [`Region::validate`] for what needs no mesh (the job file front end calls
//! them when it reads a job, to fail before the mesh is read), then
//! [`build_curve`] and [`build_region`] on the mesh.
//!
//! Curves are polylines of surface points: each segment lies in one face and stores
//! its ends as barycentric coordinates of that face (paper Sec. 3.1), so the curve
//! follows the mesh when it deforms. Everything here runs in (near) linear time.

use crate::error::{Error, Result};
use crate::mesh::topology::{compressed_rows, Topology};
use crate::mesh::Mesh;
use glam::DVec3;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// A curve on the input surface, as a caller gives it.
#[derive(Clone, Debug, PartialEq)]
pub enum Curve {
    /// The section of the mesh by the plane through `origin` with normal
    /// `normal` (any non-zero length); where the plane cuts several pieces,
    /// the piece with a crossing point closest to `origin`.
    Plane { origin: [f64; 3], normal: [f64; 3] },
    /// The shortest edge path through these vertices, in order (at least 2);
    /// `closed` returns to the first.
    Path { vertices: Vec<usize>, closed: bool },
    /// The polyline through these surface points (at least 2); consecutive
    /// points must share a face.
    Points(Vec<FacePoint>),
}

/// A surface point as a caller gives it: barycentric coordinates (>= 0,
/// summing to 1) in face `face`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FacePoint {
    pub face: usize,
    pub bary: [f64; 3],
}

/// A set of faces of the input mesh, as a caller gives it.
#[derive(Clone, Debug, PartialEq)]
pub enum Region {
    /// These faces (0-based indices).
    Faces(Vec<usize>),
    /// The faces whose centroid lies within `radius` of `center`.
    Sphere { center: [f64; 3], radius: f64 },
    /// The faces whose centroid lies inside the axis-aligned box.
    Box { min: [f64; 3], max: [f64; 3] },
    /// The faces of every OBJ group (`g` or `o`) of this name.
    Group(String),
    /// These vertices (0-based): for handles only.
    Vertices(Vec<usize>),
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

impl Curve {
    /// The checks that need no mesh: finite numbers, a non-zero normal, at
    /// least 2 vertices or points. `what` names the owner in the message.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        match self {
            Curve::Plane { origin, normal } => {
                if !finite3(origin) || !finite3(normal) {
                    return Err(format!("{what}: plane origin and normal must be finite"));
                }
                if normal.iter().all(|&x| x == 0.0) {
                    return Err(format!("{what}: plane normal is zero"));
                }
            }
            Curve::Path { vertices, .. } if vertices.len() < 2 => {
                return Err(format!(
                    "{what}: a path needs at least 2 vertices (got {})",
                    vertices.len()
                ));
            }
            Curve::Points(points) if points.len() < 2 => {
                return Err(format!(
                    "{what}: a curve needs at least 2 points (got {})",
                    points.len()
                ));
            }
            _ => {}
        }
        Ok(())
    }
}

impl Region {
    /// The field name of the job file schema for this kind of region.
    pub fn kind(&self) -> &'static str {
        match self {
            Region::Faces(_) => "faces",
            Region::Sphere { .. } => "sphere",
            Region::Box { .. } => "box",
            Region::Group(_) => "group",
            Region::Vertices(_) => "vertices",
        }
    }

    /// The checks that need no mesh: `Vertices` only where `allow_vertices`
    /// (handles), finite numbers, a positive radius, `min <= max`.
    pub fn validate(&self, what: &str, allow_vertices: bool) -> Result<(), String> {
        match self {
            Region::Vertices(_) if !allow_vertices => {
                return Err(format!(
                    "{what}: region `vertices` is only allowed for handles; \
                     use one of faces, faces_file, sphere, box or group"
                ))
            }
            Region::Sphere { center, radius } => {
                if !finite3(center) {
                    return Err(format!("{what}: sphere center must be finite"));
                }
                if !(radius.is_finite() && *radius > 0.0) {
                    return Err(format!(
                        "{what}: sphere radius must be a finite number > 0 (got {radius})"
                    ));
                }
            }
            Region::Box { min, max } => {
                if !finite3(min) || !finite3(max) {
                    return Err(format!("{what}: box min and max must be finite"));
                }
                if (0..3).any(|k| min[k] > max[k]) {
                    return Err(format!(
                        "{what}: box min {min:?} exceeds max {max:?} in some coordinate"
                    ));
                }
            }
            _ => {}
        }
        Ok(())
    }
}

/// A point on the surface: barycentric coordinates in one face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub face: u32,
    pub bary: [f64; 3],
}

impl SurfacePoint {
    /// Position for vertex positions `x`.
    pub fn position(&self, mesh: &Mesh, x: &[DVec3]) -> DVec3 {
        bary_point(mesh, x, self.face, &self.bary)
    }
}

/// A curve segment lying in one face; its ends as barycentric coordinates of that
/// face (paper Sec. 3.1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub face: u32,
    pub a: [f64; 3],
    pub b: [f64; 3],
}

impl Segment {
    /// The two end points for vertex positions `x`.
    pub fn ends(&self, mesh: &Mesh, x: &[DVec3]) -> (DVec3, DVec3) {
        (
            bary_point(mesh, x, self.face, &self.a),
            bary_point(mesh, x, self.face, &self.b),
        )
    }

    /// Length for vertex positions `x`.
    pub fn length(&self, mesh: &Mesh, x: &[DVec3]) -> f64 {
        let (p, q) = self.ends(mesh, x);
        (q - p).length()
    }
}

/// A polyline on the surface. Consecutive segments meet (segment i's `b` is at the
/// same surface point as segment i+1's `a`); `closed` when the last meets the first.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfaceCurve {
    pub segments: Vec<Segment>,
    pub closed: bool,
    /// For a curve cut by a plane: how many pieces the plane cut and which one
    /// this curve is. `None` for paths and explicit points.
    pub plane_cut: Option<PlaneCut>,
}

/// What a plane section found on the input mesh.
///
/// The pieces are numbered from 1 in the order of the smallest index of the
/// faces each one crosses (the piece through the lowest-numbered crossed face
/// is piece 1). A piece where the plane only touches the mesh at a vertex (no
/// segment of positive length) is not counted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlaneCut {
    /// Connected pieces (closed loops, or open arcs on an open mesh) the plane
    /// cut from the mesh.
    pub loops: usize,
    /// 1-based number of the piece chosen (the one with a crossing point
    /// closest to the plane's origin), in the order above.
    pub chosen: usize,
}

impl SurfaceCurve {
    /// Sum of the segment lengths for vertex positions `x`.
    pub fn length(&self, mesh: &Mesh, x: &[DVec3]) -> f64 {
        self.segments.iter().map(|s| s.length(mesh, x)).sum()
    }

    /// Points of the polyline: the segments' ends, each shared end counted once
    /// (segments + 1 for an open curve, segments for a closed one).
    pub fn num_points(&self) -> usize {
        if self.segments.is_empty() {
            0
        } else if self.closed {
            self.segments.len()
        } else {
            self.segments.len() + 1
        }
    }
}

/// A set of faces: sorted, unique, non-empty.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct FaceSet {
    pub faces: Vec<u32>,
}

impl FaceSet {
    /// Total area for vertex positions `x`.
    pub fn area(&self, mesh: &Mesh, x: &[DVec3]) -> f64 {
        self.faces
            .iter()
            .map(|&f| mesh.face_area(x, f as usize))
            .sum()
    }

    /// The vertices of the region's faces, sorted and unique.
    pub fn vertices(&self, mesh: &Mesh) -> Vec<u32> {
        let mut v: Vec<u32> = self
            .faces
            .iter()
            .flat_map(|&f| mesh.faces[f as usize])
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    }
}

#[inline]
fn bary_point(mesh: &Mesh, x: &[DVec3], face: u32, w: &[f64; 3]) -> DVec3 {
    let [i, j, k] = mesh.faces[face as usize];
    x[i as usize] * w[0] + x[j as usize] * w[1] + x[k as usize] * w[2]
}

fn v3(a: &[f64; 3]) -> DVec3 {
    DVec3::new(a[0], a[1], a[2])
}

// ---------------------------------------------------------------------------
// Curves
// ---------------------------------------------------------------------------

/// Build the curve of a length constraint on the input mesh. `what` names the
/// constraint in messages.
pub fn build_curve(
    curve: &Curve,
    mesh: &Mesh,
    topo: &Topology,
    what: &str,
) -> Result<SurfaceCurve> {
    curve.validate(what).map_err(Error::bad)?;
    match curve {
        Curve::Plane { origin, normal } => plane_section(origin, normal, mesh, topo, what),
        Curve::Path { vertices, closed } => edge_path(vertices, *closed, mesh, topo, what),
        Curve::Points(points) => point_curve(points, mesh, topo, what),
    }
}

/// Plane section: see the module docs and the contract. One pass over the faces;
/// crossing points are computed per edge so that neighbouring faces agree exactly.
fn plane_section(
    origin_given: &[f64; 3],
    normal_given: &[f64; 3],
    mesh: &Mesh,
    topo: &Topology,
    what: &str,
) -> Result<SurfaceCurve> {
    let origin = v3(origin_given);
    let normal = v3(normal_given);
    let x = &mesh.positions;
    let d: Vec<f64> = {
        use rayon::prelude::*;
        x.par_iter().map(|&p| (p - origin).dot(normal)).collect()
    };
    let pos = |v: u32| d[v as usize] >= 0.0;

    // Parameter of the crossing on edge e, measured from its lower vertex.
    let edge_t = |e: u32| -> f64 {
        let [lo, hi] = topo.edges[e as usize];
        let (dl, dh) = (d[lo as usize], d[hi as usize]);
        dl / (dl - dh)
    };
    let edge_point = |e: u32| -> DVec3 {
        let [lo, hi] = topo.edges[e as usize];
        let t = edge_t(e);
        x[lo as usize] * (1.0 - t) + x[hi as usize] * t
    };
    // Crossing point of face f's side k (edge e) in f's barycentric coordinates.
    let side_bary = |f: u32, k: usize| -> [f64; 3] {
        let e = topo.face_edges[f as usize][k];
        let lo = topo.edges[e as usize][0];
        let t = edge_t(e);
        let k1 = (k + 1) % 3;
        let mut w = [0.0; 3];
        if mesh.faces[f as usize][k] == lo {
            w[k] = 1.0 - t;
            w[k1] = t;
        } else {
            w[k] = t;
            w[k1] = 1.0 - t;
        }
        w
    };
    // The two crossed sides of face f, or None when f is not crossed.
    let crossed_sides = |f: usize| -> Option<[usize; 2]> {
        let t = mesh.faces[f];
        let s = [pos(t[0]), pos(t[1]), pos(t[2])];
        if s[0] == s[1] && s[1] == s[2] {
            return None;
        }
        let mut out = [0usize; 2];
        let mut n = 0;
        for k in 0..3 {
            if s[k] != s[(k + 1) % 3] {
                out[n] = k;
                n += 1;
            }
        }
        debug_assert_eq!(n, 2);
        Some(out)
    };
    // Next face across edge e from face f; None at a boundary.
    let across = |f: u32, e: u32| -> Result<Option<u32>> {
        let fs = topo.edge_faces(e as usize);
        match fs.len() {
            0 | 1 => Ok(None),
            2 => Ok(Some(if fs[0] == f { fs[1] } else { fs[0] })),
            _ => {
                let [a, b] = topo.edges[e as usize];
                Err(Error::bad(format!(
                    "{what}: the plane section branches at non-manifold edge ({a}, {b}); \
                     choose another plane or give the curve as a path or points"
                )))
            }
        }
    };

    let nf = mesh.faces.len();
    // The crossed faces of the surface (duplicate and collapsed faces are
    // not part of its adjacency), in face order, found on rayon's threads:
    // the walks below start from them alone.
    let crossed: Vec<u32> = {
        use rayon::prelude::*;
        (0..nf)
            .into_par_iter()
            .filter(|&f| {
                !topo.ignored.get(f).copied().unwrap_or(false) && crossed_sides(f).is_some()
            })
            .map(|f| f as u32)
            .collect()
    };
    let mut visited = vec![false; nf];
    // Best piece so far: (distance of its nearest crossing to origin, segments,
    // closed, 1-based piece number).
    let mut best: Option<(f64, Vec<Segment>, bool, usize)> = None;
    // Pieces found so far (those with at least one segment).
    let mut pieces = 0usize;
    for &f0 in &crossed {
        if visited[f0 as usize] {
            continue;
        }
        let Some(sides0) = crossed_sides(f0 as usize) else {
            continue;
        };
        visited[f0 as usize] = true;
        let e_of = |f: u32, k: usize| topo.face_edges[f as usize][k];
        // Walk forward from f0 leaving through its second crossed side. Each step
        // records (face, entry side, exit side).
        let mut forward: Vec<(u32, usize, usize)> = vec![(f0, sides0[0], sides0[1])];
        let mut closed = false;
        let mut cur = f0;
        let mut exit_edge = e_of(f0, sides0[1]);
        while let Some(g) = across(cur, exit_edge)? {
            if g == f0 {
                closed = true;
                break;
            }
            if visited[g as usize] {
                return Err(Error::Internal(format!(
                    "{what}: plane section revisits face {g}"
                )));
            }
            visited[g as usize] = true;
            let sides = crossed_sides(g as usize).ok_or_else(|| {
                Error::Internal(format!("{what}: plane section reached uncrossed face {g}"))
            })?;
            let (entry, exit) = if e_of(g, sides[0]) == exit_edge {
                (sides[0], sides[1])
            } else {
                (sides[1], sides[0])
            };
            forward.push((g, entry, exit));
            cur = g;
            exit_edge = e_of(g, exit);
        }
        let mut chain: Vec<(u32, usize, usize)> = Vec::new();
        if !closed {
            // Open piece: also walk backward from f0 through its first crossed side.
            let mut backward: Vec<(u32, usize, usize)> = Vec::new();
            let mut cur = f0;
            let mut edge = e_of(f0, sides0[0]);
            while let Some(g) = across(cur, edge)? {
                if visited[g as usize] {
                    return Err(Error::Internal(format!(
                        "{what}: plane section revisits face {g}"
                    )));
                }
                visited[g as usize] = true;
                let sides = crossed_sides(g as usize).ok_or_else(|| {
                    Error::Internal(format!("{what}: plane section reached uncrossed face {g}"))
                })?;
                // Walking backward we enter g through `edge`; in curve order that
                // side is g's exit.
                let (entry, exit) = if e_of(g, sides[0]) == edge {
                    (sides[1], sides[0])
                } else {
                    (sides[0], sides[1])
                };
                backward.push((g, entry, exit));
                cur = g;
                edge = e_of(g, entry);
            }
            backward.reverse();
            chain.extend(backward);
        }
        chain.extend(forward);

        // Nearest crossing point to the origin, and the segments (dropping the
        // degenerate ones where both ends are the same mesh vertex).
        let mut dist = f64::INFINITY;
        let mut segments = Vec::with_capacity(chain.len());
        for &(f, entry, exit) in &chain {
            for k in [entry, exit] {
                let p = edge_point(e_of(f, k));
                dist = dist.min((p - origin).length());
            }
            let a = side_bary(f, entry);
            let b = side_bary(f, exit);
            if a != b {
                segments.push(Segment { face: f, a, b });
            }
        }
        if segments.is_empty() {
            continue; // the plane only touches the mesh at a vertex here
        }
        // Pieces are found in order of their lowest-numbered crossed face: f0
        // is the first crossed face not on an earlier piece.
        pieces += 1;
        if best.as_ref().is_none_or(|(bd, _, _, _)| dist < *bd) {
            best = Some((dist, segments, closed, pieces));
        }
    }
    match best {
        Some((_, segments, closed, chosen)) => Ok(SurfaceCurve {
            segments,
            closed,
            plane_cut: Some(PlaneCut {
                loops: pieces,
                chosen,
            }),
        }),
        None => {
            // Extent of the mesh along the unit normal, measured from the origin.
            let nh = normal.normalize();
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for t in &mesh.faces {
                for &v in t {
                    let h = (x[v as usize] - origin).dot(nh);
                    lo = lo.min(h);
                    hi = hi.max(h);
                }
            }
            Err(Error::bad(format!(
                "{what}: the plane (origin {:?}, normal {:?}) misses the mesh: the mesh \
                 spans {} to {} along the unit normal from the origin (dot(x - origin, \
                 n/|n|)); move the origin by a distance in that range along the unit \
                 normal",
                origin_given,
                normal_given,
                short(lo),
                short(hi)
            )))
        }
    }
}

/// A number for messages: about 6 significant digits.
fn short(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 || (1e-3..1e6).contains(&a) {
        let s = format!("{v:.6}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        if s == "-0" {
            "0".into()
        } else {
            s.into()
        }
    } else {
        format!("{v:.5e}")
    }
}

/// `min [..] max [..]` of the vertices that faces use, for messages.
fn bbox_text(mesh: &Mesh) -> String {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for t in &mesh.faces {
        for &v in t {
            lo = lo.min(mesh.positions[v as usize]);
            hi = hi.max(mesh.positions[v as usize]);
        }
    }
    let f = |p: DVec3| format!("[{}, {}, {}]", short(p.x), short(p.y), short(p.z));
    format!("min {} max {}", f(lo), f(hi))
}

/// Vertex-vertex adjacency (CSR) with the connecting edge index.
struct Adjacency {
    start: Vec<usize>,
    nbr: Vec<(u32, u32)>, // (neighbour, edge)
}

impl Adjacency {
    fn build(nv: usize, topo: &Topology) -> Adjacency {
        // Edges without faces (sides of collapsed faces only) are no path.
        let usable = |e: usize| {
            let [a, b] = topo.edges[e];
            a != b && !topo.edge_faces(e).is_empty()
        };
        let (start, nbr) = compressed_rows(nv, |add| {
            for (e, &[a, b]) in topo.edges.iter().enumerate() {
                if usable(e) {
                    add(a as usize, (b, e as u32));
                    add(b as usize, (a, e as u32));
                }
            }
        });
        Adjacency { start, nbr }
    }
    fn of(&self, v: u32) -> &[(u32, u32)] {
        &self.nbr[self.start[v as usize]..self.start[v as usize + 1]]
    }
}

#[derive(PartialEq)]
struct HeapItem(f64, u32);
impl Eq for HeapItem {}
impl Ord for HeapItem {
    fn cmp(&self, o: &Self) -> Ordering {
        // Min-heap on distance, ties by vertex index.
        o.0.total_cmp(&self.0).then_with(|| o.1.cmp(&self.1))
    }
}
impl PartialOrd for HeapItem {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// Shortest edge path (Dijkstra on input edge lengths) through `path`, in order.
fn edge_path(
    path: &[usize],
    closed: bool,
    mesh: &Mesh,
    topo: &Topology,
    what: &str,
) -> Result<SurfaceCurve> {
    let nv = mesh.positions.len();
    if path.len() < 2 {
        return Err(Error::bad(format!(
            "{what}: a path needs at least 2 vertices (got {})",
            path.len()
        )));
    }
    for (i, &v) in path.iter().enumerate() {
        if v >= nv {
            return Err(Error::bad(format!(
                "{what}: path vertex {v} (entry {i}) is out of range (mesh has {nv} vertices)"
            )));
        }
    }
    let x = &mesh.positions;
    let adj = Adjacency::build(nv, topo);
    let mut dist = vec![f64::INFINITY; nv];
    let mut prev: Vec<(u32, u32)> = vec![(u32::MAX, u32::MAX); nv]; // (vertex, edge)
    let mut touched: Vec<u32> = Vec::new();
    let mut heap = BinaryHeap::new();

    let mut stops: Vec<usize> = path.to_vec();
    if closed && stops.first() != stops.last() {
        stops.push(stops[0]);
    }
    let mut segments = Vec::new();
    for leg in stops.windows(2) {
        let (s, t) = (leg[0] as u32, leg[1] as u32);
        if s == t {
            continue;
        }
        for &v in &touched {
            dist[v as usize] = f64::INFINITY;
            prev[v as usize] = (u32::MAX, u32::MAX);
        }
        touched.clear();
        heap.clear();
        dist[s as usize] = 0.0;
        touched.push(s);
        heap.push(HeapItem(0.0, s));
        let mut found = false;
        while let Some(HeapItem(dv, v)) = heap.pop() {
            if dv > dist[v as usize] {
                continue;
            }
            if v == t {
                found = true;
                break;
            }
            for &(w, e) in adj.of(v) {
                let nd = dv + (x[w as usize] - x[v as usize]).length();
                if nd < dist[w as usize] {
                    if dist[w as usize] == f64::INFINITY {
                        touched.push(w);
                    }
                    dist[w as usize] = nd;
                    prev[w as usize] = (v, e);
                    heap.push(HeapItem(nd, w));
                }
            }
        }
        if !found {
            return Err(Error::bad(format!(
                "{what}: path vertex {t} cannot be reached from vertex {s} \
                 along mesh edges (not in the same connected component)"
            )));
        }
        // Reconstruct t -> s, then emit in s -> t order.
        let mut steps: Vec<(u32, u32, u32)> = Vec::new(); // (from, to, edge)
        let mut v = t;
        while v != s {
            let (p, e) = prev[v as usize];
            steps.push((p, v, e));
            v = p;
        }
        for &(a, b, e) in steps.iter().rev() {
            let face = topo.edge_faces(e as usize)[0];
            let tri = mesh.faces[face as usize];
            let mut wa = [0.0; 3];
            let mut wb = [0.0; 3];
            for k in 0..3 {
                if tri[k] == a {
                    wa[k] = 1.0;
                }
                if tri[k] == b {
                    wb[k] = 1.0;
                }
            }
            segments.push(Segment { face, a: wa, b: wb });
        }
    }
    if segments.is_empty() {
        return Err(Error::bad(format!(
            "{what}: the path has zero length (all its vertices are the same)"
        )));
    }
    let closed = closed || path.first() == path.last();
    Ok(SurfaceCurve {
        segments,
        closed,
        plane_cut: None,
    })
}

/// A validated surface point: face and normalised barycentrics (tiny ones snapped to 0).
struct VertexWeights {
    face: u32,
    bary: [f64; 3],
}

impl VertexWeights {
    /// Faces that contain this point: its own face, or every face around the edge
    /// or vertex it lies on.
    fn support(&self, mesh: &Mesh, topo: &Topology) -> Vec<u32> {
        let tri = mesh.faces[self.face as usize];
        let nz: Vec<usize> = (0..3).filter(|&k| self.bary[k] != 0.0).collect();
        match nz.len() {
            1 => topo.vertex_faces(tri[nz[0]] as usize).to_vec(),
            2 => {
                // Side k joins corners k and k+1.
                let k = if nz == [0, 1] {
                    0
                } else if nz == [1, 2] {
                    1
                } else {
                    2
                };
                let e = topo.face_edges[self.face as usize][k];
                topo.edge_faces(e as usize).to_vec()
            }
            _ => vec![self.face],
        }
    }

    /// Barycentric coordinates in face `g`, which must contain the point.
    fn in_face(&self, mesh: &Mesh, g: u32) -> [f64; 3] {
        let tri = mesh.faces[self.face as usize];
        let tg = mesh.faces[g as usize];
        let mut w = [0.0; 3];
        for (k, &v) in tri.iter().enumerate() {
            if self.bary[k] != 0.0 {
                let j = (0..3).find(|&j| tg[j] == v).expect("support face");
                w[j] += self.bary[k];
            }
        }
        w
    }

    fn same_point(&self, mesh: &Mesh, o: &VertexWeights) -> bool {
        let mut a: Vec<(u32, f64)> = (0..3)
            .filter(|&k| self.bary[k] != 0.0)
            .map(|k| (mesh.faces[self.face as usize][k], self.bary[k]))
            .collect();
        let mut b: Vec<(u32, f64)> = (0..3)
            .filter(|&k| o.bary[k] != 0.0)
            .map(|k| (mesh.faces[o.face as usize][k], o.bary[k]))
            .collect();
        a.sort_by_key(|p| p.0);
        b.sort_by_key(|p| p.0);
        a == b
    }
}

fn check_point(p: &FacePoint, i: usize, mesh: &Mesh, what: &str) -> Result<VertexWeights> {
    let nf = mesh.faces.len();
    if p.face >= nf {
        return Err(Error::bad(format!(
            "{what}: point {i}: face {} is out of range (mesh has {nf} faces)",
            p.face
        )));
    }
    let w = p.bary;
    if w.iter().any(|c| !c.is_finite() || *c < -1e-9) {
        return Err(Error::bad(format!(
            "{what}: point {i}: barycentric coordinates {w:?} must be finite and >= 0"
        )));
    }
    let sum: f64 = w.iter().sum();
    if (sum - 1.0).abs() > 1e-6 {
        return Err(Error::bad(format!(
            "{what}: point {i}: barycentric coordinates {w:?} must sum to 1 (sum is {sum})"
        )));
    }
    // Snap tiny coordinates to zero (so points on edges/vertices are recognised),
    // then normalise.
    let mut b = w.map(|c| if c < 1e-9 { 0.0 } else { c });
    let s: f64 = b.iter().sum();
    for c in &mut b {
        *c /= s;
    }
    Ok(VertexWeights {
        face: p.face as u32,
        bary: b,
    })
}

/// Curve through explicit surface points; consecutive points must share a face.
fn point_curve(
    points: &[FacePoint],
    mesh: &Mesh,
    topo: &Topology,
    what: &str,
) -> Result<SurfaceCurve> {
    if points.len() < 2 {
        return Err(Error::bad(format!(
            "{what}: a curve needs at least 2 points (got {})",
            points.len()
        )));
    }
    let pts: Vec<VertexWeights> = points
        .iter()
        .enumerate()
        .map(|(i, p)| check_point(p, i, mesh, what))
        .collect::<Result<_>>()?;
    let mut segments = Vec::with_capacity(pts.len() - 1);
    for i in 0..pts.len() - 1 {
        let (p, q) = (&pts[i], &pts[i + 1]);
        if p.same_point(mesh, q) {
            continue;
        }
        let sp = p.support(mesh, topo);
        let sq = q.support(mesh, topo);
        let face = if sq.contains(&p.face) {
            Some(p.face)
        } else if sp.contains(&q.face) {
            Some(q.face)
        } else {
            sp.iter().copied().filter(|f| sq.contains(f)).min()
        };
        let Some(face) = face else {
            return Err(Error::bad(format!(
                "{what}: points {i} (face {}) and {} (face {}) share no face; \
                 consecutive points must lie in a common face",
                p.face,
                i + 1,
                q.face
            )));
        };
        segments.push(Segment {
            face,
            a: p.in_face(mesh, face),
            b: q.in_face(mesh, face),
        });
    }
    if segments.is_empty() {
        return Err(Error::bad(format!(
            "{what}: the curve has zero length (all its points are the same)"
        )));
    }
    let closed = pts.len() > 2 && pts[0].same_point(mesh, &pts[pts.len() - 1]);
    Ok(SurfaceCurve {
        segments,
        closed,
        plane_cut: None,
    })
}

// ---------------------------------------------------------------------------
// Regions and handles
// ---------------------------------------------------------------------------

/// Build a region (a set of faces of the input mesh). `what` names the constraint,
/// handle or curvature entry in messages. `Vertices` is rejected here (handles use
/// [`build_handle_vertices`]).
pub fn build_region(region: &Region, mesh: &Mesh, what: &str) -> Result<FaceSet> {
    region.validate(what, false).map_err(Error::bad)?;
    let nf = mesh.faces.len();
    let x = &mesh.positions;
    let mut faces: Vec<u32> = match region {
        Region::Faces(list) => {
            check_faces(list, nf, what, "region face index")?;
            list.iter().map(|&f| f as u32).collect()
        }
        Region::Sphere { center, radius } => {
            let c = v3(center);
            let r2 = radius * radius;
            (0..nf)
                .filter(|&f| (mesh.centroid(x, f) - c).length_squared() <= r2)
                .map(|f| f as u32)
                .collect()
        }
        Region::Box { min, max } => {
            let (lo, hi) = (v3(min), v3(max));
            (0..nf)
                .filter(|&f| {
                    let c = mesh.centroid(x, f);
                    c.cmpge(lo).all() && c.cmple(hi).all()
                })
                .map(|f| f as u32)
                .collect()
        }
        Region::Group(name) => group_faces(name, mesh, what)?,
        Region::Vertices(_) => unreachable!("rejected by Region::validate"),
    };
    faces.sort_unstable();
    faces.dedup();
    if faces.is_empty() {
        let hint = match region {
            Region::Sphere {
                center: c,
                radius: r,
            } => format!(
                ": no face centroid lies within the sphere (center {:?}, radius {r}, \
                 extent [{}, {}, {}] to [{}, {}, {}]); the mesh's bounding box is {}: \
                 move the center or enlarge the radius",
                c,
                short(c[0] - r),
                short(c[1] - r),
                short(c[2] - r),
                short(c[0] + r),
                short(c[1] + r),
                short(c[2] + r),
                bbox_text(mesh)
            ),
            Region::Box { min, max } => format!(
                ": no face centroid lies inside the box (min {:?} max {:?}); the mesh's \
                 bounding box is {}: move or enlarge the box",
                min,
                max,
                bbox_text(mesh)
            ),
            _ => ": the list is empty; give at least one face index".to_string(),
        };
        return Err(Error::bad(format!(
            "{what}: region selects no faces ({}){hint}",
            region.kind()
        )));
    }
    Ok(FaceSet { faces })
}

/// The faces of every group named `name`.
fn group_faces(name: &str, mesh: &Mesh, what: &str) -> Result<Vec<u32>> {
    let nf = mesh.faces.len();
    let matching: Vec<_> = mesh.groups.iter().filter(|g| g.name == name).collect();
    if matching.is_empty() {
        if mesh.groups.is_empty() {
            return Err(Error::bad(format!(
                "{what}: group '{name}' not found: the mesh has no groups \
                 (only OBJ files have `g`/`o` groups)"
            )));
        }
        let mut names: Vec<&str> = mesh.groups.iter().map(|g| g.name.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        let shown = if names.len() > 30 {
            format!("{}, ... ({} in all)", names[..30].join(", "), names.len())
        } else {
            names.join(", ")
        };
        return Err(Error::bad(format!(
            "{what}: group '{name}' not found; the mesh has groups: {shown}"
        )));
    }
    let mut list = Vec::new();
    for g in matching {
        check_faces(&g.faces, nf, what, &format!("face index of group '{name}'"))?;
        list.extend(g.faces.iter().map(|&f| f as u32));
    }
    Ok(list)
}

/// Every index of `list` below `nf`; `ctx` says what the indices are.
pub fn check_faces(list: &[usize], nf: usize, what: &str, ctx: &str) -> Result<()> {
    if let Some(&f) = list.iter().find(|&&f| f >= nf) {
        return Err(Error::bad(format!(
            "{what}: {ctx} {f} is out of range (mesh has {nf} faces)"
        )));
    }
    Ok(())
}

fn check_vertices(list: &[usize], nv: usize, what: &str) -> Result<Vec<u32>> {
    if let Some(&v) = list.iter().find(|&&v| v >= nv) {
        return Err(Error::bad(format!(
            "{what}: vertex index {v} is out of range (mesh has {nv} vertices)"
        )));
    }
    let mut out: Vec<u32> = list.iter().map(|&v| v as u32).collect();
    out.sort_unstable();
    out.dedup();
    if out.is_empty() {
        return Err(Error::bad(format!("{what}: selects no vertices")));
    }
    Ok(out)
}

/// The vertices a handle moves: its `Vertices`, or all vertices of its
/// region's faces; sorted and unique, non-empty.
pub fn build_handle_vertices(region: &Region, mesh: &Mesh, what: &str) -> Result<Vec<u32>> {
    region.validate(what, true).map_err(Error::bad)?;
    match region {
        Region::Vertices(list) => check_vertices(list, mesh.positions.len(), what),
        _ => Ok(build_region(region, mesh, what)?.vertices(mesh)),
    }
}
