//! Input mesh checks: what the method cannot work with is rejected with a message that
//! names the file and the offending elements; what it can live with is counted.
//!
//! Rejected ([`Error::BadInput`]): no faces, face corners out of range, non-finite
//! coordinates on vertices used by faces, and non-manifold edges (more than two
//! faces; duplicate and collapsed faces not counted).
//!
//! Accepted and counted ([`MeshCheck`]): boundary edges, connected components. Accepted
//! and named in [`MeshCheck::warnings`] (the command line prints them as warnings):
//! zero-area (a repeated corner index included), needle and cap faces
//! ([`Mesh::degenerate_faces`]: they get no shape weight), duplicate faces (left out of
//! the adjacency, see [`Topology`]), unreferenced vertices and non-manifold vertices
//! (two fans of faces meeting in one vertex).
//!
//! A volume constraint needs more ([`require_volume`]): a closed, consistently oriented
//! mesh.
//!
//! Vertex and face indices in messages are 0-based (faces are triangles after fan
//! triangulation, numbered in file order).

use crate::error::{Error, Result};
use crate::mesh::topology::{Topology, UnionFind};
use crate::mesh::Mesh;
use std::path::Path;

/// Most offenders listed by name in an error message.
const MAX_LISTED: usize = 5;

/// Summary of an accepted mesh.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct MeshCheck {
    /// Edges with exactly one face.
    pub boundary_edges: usize,
    /// Edges with more than two faces (always 0 for a mesh that passed [`validate`]).
    pub non_manifold_edges: usize,
    /// Vertices no face uses.
    pub unreferenced_vertices: usize,
    /// Connected components of faces (faces sharing a vertex are connected).
    pub components: usize,
    /// Every edge has exactly two faces.
    pub closed: bool,
    /// Zero-area, needle and cap faces ([`Mesh::degenerate_faces`]): accepted, they
    /// get no shape weight.
    pub zero_area_faces: Vec<usize>,
    /// Duplicate faces `(f, g)`: face f repeats the vertices of the earlier face g.
    pub duplicate_faces: Vec<(usize, usize)>,
    /// One line per tolerated defect worth telling the user (also logged with
    /// the command line), without a `warning:` prefix.
    pub warnings: Vec<String>,
}

/// "`what`: a, b, c, d, e and 7 more"
fn listing(items: &[String]) -> String {
    let mut s = items
        .iter()
        .take(MAX_LISTED)
        .cloned()
        .collect::<Vec<_>>()
        .join("; ");
    if items.len() > MAX_LISTED {
        s.push_str(&format!(" and {} more", items.len() - MAX_LISTED));
    }
    s
}

/// Most indices listed in a warning.
const MAX_INDICES: usize = 10;

/// "a, b, c" with at most [`MAX_INDICES`] items, then "and N more".
fn index_listing(items: impl Iterator<Item = String>) -> String {
    let all: Vec<String> = items.collect();
    let mut s = all
        .iter()
        .take(MAX_INDICES)
        .cloned()
        .collect::<Vec<_>>()
        .join(", ");
    if all.len() > MAX_INDICES {
        s.push_str(&format!(" and {} more", all.len() - MAX_INDICES));
    }
    s
}

fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// At least one face, every corner index names a vertex. `file` is named in
/// the message.
fn check_indices(mesh: &Mesh, file: &Path) -> Result<()> {
    let file_s = file.display();
    let nv = mesh.positions.len();
    let nf = mesh.faces.len();
    if nf == 0 {
        return Err(Error::bad(format!(
            "{file_s}: the mesh has no faces ({})",
            plural(nv, "vertex", "vertices")
        )));
    }

    // Corner indices in range (the readers already check; be defensive).
    let out_of_range: Vec<String> = mesh
        .faces
        .iter()
        .enumerate()
        .flat_map(|(f, t)| {
            t.iter()
                .enumerate()
                .filter(|&(_, &v)| (v as usize) >= nv)
                .map(move |(k, &v)| format!("face {f} corner {k} refers to vertex {v}"))
        })
        .collect();
    if !out_of_range.is_empty() {
        return Err(Error::bad(format!(
            "{file_s}: {} out of range (the mesh has {}): {}",
            plural(out_of_range.len(), "face corner is", "face corners are"),
            plural(nv, "vertex", "vertices"),
            listing(&out_of_range)
        )));
    }
    Ok(())
}

/// Checks `mesh` (with its topology `topo`) for use by the solver; `file` is named in the
/// messages. Returns the counts of tolerated defects, or [`Error::BadInput`] listing at
/// most five offenders of the first failed check.
pub fn validate(mesh: &Mesh, topo: &Topology, file: &Path) -> Result<MeshCheck> {
    check_indices(mesh, file)?;
    let file_s = file.display();
    let nv = mesh.positions.len();

    let mut used = vec![false; nv];
    for t in &mesh.faces {
        for &v in t {
            used[v as usize] = true;
        }
    }

    // Finite coordinates on used vertices.
    let non_finite: Vec<String> = mesh
        .positions
        .iter()
        .enumerate()
        .filter(|&(v, p)| used[v] && !p.is_finite())
        .map(|(v, p)| format!("vertex {v} = ({}, {}, {})", p.x, p.y, p.z))
        .collect();
    if !non_finite.is_empty() {
        return Err(Error::bad(format!(
            "{file_s}: {} used by faces {} non-finite coordinates (0-based indices): {}",
            plural(non_finite.len(), "vertex", "vertices"),
            if non_finite.len() == 1 { "has" } else { "have" },
            listing(&non_finite)
        )));
    }

    let x = &mesh.positions;

    // Tolerated: zero-area (a repeated corner index included), needle and cap faces,
    // and duplicate faces.
    let mut warnings = Vec::new();
    let zero_area_faces: Vec<usize> = mesh
        .degenerate_faces(x)
        .iter()
        .enumerate()
        .filter(|&(_, &d)| d)
        .map(|(f, _)| f)
        .collect();
    if !zero_area_faces.is_empty() {
        let diag = mesh.bbox_diagonal(x);
        let all_zero = zero_area_faces
            .iter()
            .all(|&f| 2.0 * mesh.face_area(x, f) <= crate::mesh::DEGENERATE_AREA * diag * diag);
        warnings.push(format!(
            "mesh {file_s}: {} (0-based: {}) get no shape weight",
            plural(
                zero_area_faces.len(),
                if all_zero {
                    "zero-area face"
                } else {
                    "zero-area or needle face"
                },
                if all_zero {
                    "zero-area faces"
                } else {
                    "zero-area or needle faces"
                }
            ),
            index_listing(zero_area_faces.iter().map(|f| f.to_string()))
        ));
    }
    let duplicate_faces: Vec<(usize, usize)> = topo
        .duplicate_faces
        .iter()
        .map(|&(f, g)| (f as usize, g as usize))
        .collect();
    if !duplicate_faces.is_empty() {
        warnings.push(format!(
            "mesh {file_s}: {} (0-based: {}) ignored for adjacency and shape weight \
             (same three vertices as an earlier face)",
            plural(duplicate_faces.len(), "duplicate face", "duplicate faces"),
            index_listing(
                duplicate_faces
                    .iter()
                    .map(|(f, g)| format!("{f} repeats {g}"))
            )
        ));
    }
    // Non-manifold edges.
    if !topo.non_manifold_edges.is_empty() {
        let items: Vec<String> = topo
            .non_manifold_edges
            .iter()
            .map(|&e| {
                let [a, b] = topo.edges[e];
                format!("edge ({a}, {b}) has {} faces", topo.edge_faces(e).len())
            })
            .collect();
        return Err(Error::bad(format!(
            "{file_s}: the mesh has {} (edges with more than two faces; the method needs a \
             manifold mesh; 0-based vertex indices): {}",
            plural(items.len(), "non-manifold edge", "non-manifold edges"),
            listing(&items)
        )));
    }

    // Tolerated: unreferenced vertices.
    let unreferenced = used.iter().filter(|&&u| !u).count();
    if unreferenced > 0 {
        let first: Vec<String> = used
            .iter()
            .enumerate()
            .filter(|(_, &u)| !u)
            .map(|(v, _)| v.to_string())
            .collect();
        warnings.push(format!(
            "mesh {file_s}: {} not used by any face (ignored; 0-based: {})",
            plural(unreferenced, "vertex is", "vertices are"),
            index_listing(first.into_iter())
        ));
    }

    // Tolerated: non-manifold vertices (the faces around a vertex form several fans).
    let nm_vertices = non_manifold_vertices(mesh, topo);
    if !nm_vertices.is_empty() {
        warnings.push(format!(
            "mesh {file_s}: {} where separate fans of faces meet (0-based: {})",
            plural(
                nm_vertices.len(),
                "non-manifold vertex",
                "non-manifold vertices"
            ),
            index_listing(nm_vertices.iter().map(|v| v.to_string()))
        ));
    }
    for w in &warnings {
        log::debug!("mesh check: {w}");
    }

    // Connected components of faces via shared vertices.
    let label = &topo.vertex_component;
    let mut seen = vec![false; topo.components];
    for v in 0..nv {
        if used[v] {
            seen[label[v] as usize] = true;
        }
    }
    let components = seen.iter().filter(|&&r| r).count();

    let check = MeshCheck {
        boundary_edges: topo.boundary_edges.len(),
        non_manifold_edges: topo.non_manifold_edges.len(),
        unreferenced_vertices: unreferenced,
        components,
        closed: topo.boundary_edges.is_empty() && topo.non_manifold_edges.is_empty(),
        zero_area_faces,
        duplicate_faces,
        warnings,
    };
    log::debug!("{file_s}: {check:?}");
    Ok(check)
}

/// Vertices whose incident faces form more than one fan (faces connected through edges
/// incident to the vertex). Assumes no non-manifold edges. Each vertex on
/// rayon's threads, listed in vertex order: its faces' corners compared
/// ([`one_fan`]), or where there are many, a union-find over its faces
/// through the edges ([`several_fans`]).
fn non_manifold_vertices(mesh: &Mesh, topo: &Topology) -> Vec<usize> {
    use rayon::prelude::*;
    let more_than_one_fan = |v: usize| -> bool {
        let fs = topo.vertex_faces(v);
        if fs.len() < 2 {
            return false;
        }
        match one_fan(mesh, v, fs) {
            Some(one) => !one,
            None => several_fans(mesh, topo, v, fs),
        }
    };
    (0..mesh.positions.len())
        .into_par_iter()
        .filter(|&v| more_than_one_fan(v))
        .collect()
}

/// Whether the faces `fs` around `v` form more than one fan: a union-find
/// over them, joining two that share a side at `v`.
fn several_fans(mesh: &Mesh, topo: &Topology, v: usize, fs: &[u32]) -> bool {
    let mut local = UnionFind::new(fs.len());
    for (i, &f) in fs.iter().enumerate() {
        let t = mesh.faces[f as usize];
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if a as usize != v && b as usize != v {
                continue;
            }
            let e = topo.face_edges[f as usize][k] as usize;
            for &g in topo.edge_faces(e) {
                if g != f {
                    if let Some(j) = fs.iter().position(|&h| h == g) {
                        local.union(i as u32, j as u32);
                    }
                }
            }
        }
    }
    let root = local.find(0);
    (1..fs.len() as u32).any(|i| local.find(i) != root)
}

/// Whether the faces `fs` around `v` form one fan, from their corners
/// alone: two faces around `v` share a side at `v` exactly where they share
/// a corner other than `v` (each has three distinct corners, since
/// `Topology` leaves the others out of `vertex_faces`, so each pair of its
/// corners is a side, and a side's faces are all of the faces holding both
/// its ends). A union-find over at most [`FAN_LIMIT`] faces in a stack
/// array; `None` where there are more, or a face lacks `v` ([`several_fans`]
/// decides then).
fn one_fan(mesh: &Mesh, v: usize, fs: &[u32]) -> Option<bool> {
    let k = fs.len();
    if k > FAN_LIMIT {
        return None;
    }
    let mut others = [[u32::MAX; 2]; FAN_LIMIT];
    for (o, &f) in others.iter_mut().zip(fs) {
        let t = mesh.faces[f as usize];
        let c = t.iter().position(|&x| x as usize == v)?;
        *o = [t[(c + 1) % 3], t[(c + 2) % 3]];
    }
    let mut parent = [0u8; FAN_LIMIT];
    for (i, p) in parent.iter_mut().enumerate() {
        *p = i as u8;
    }
    let find = |parent: &[u8; FAN_LIMIT], mut x: u8| {
        while parent[x as usize] != x {
            x = parent[x as usize];
        }
        x
    };
    let mut sets = k;
    for i in 0..k {
        for j in i + 1..k {
            let ([a, b], [c, d]) = (others[i], others[j]);
            if a == c || a == d || b == c || b == d {
                let (ri, rj) = (find(&parent, i as u8), find(&parent, j as u8));
                if ri != rj {
                    parent[ri.max(rj) as usize] = ri.min(rj);
                    sets -= 1;
                }
            }
        }
    }
    Some(sets == 1)
}

/// The most faces around a vertex [`one_fan`] takes.
const FAN_LIMIT: usize = 32;

/// Fails unless the mesh is closed: `what` names the requirement, e.g.
/// `volume constraint 'body'`, giving
/// `<file>: volume constraint 'body' needs a closed mesh, but it has 223 boundary edges
/// (...): fill the holes ... or drop the volume constraint`.
pub fn require_closed(check: &MeshCheck, file: &Path, what: &str) -> Result<()> {
    if check.closed {
        return Ok(());
    }
    Err(Error::bad(closed_message(check, file, what, None)))
}

fn closed_message(check: &MeshCheck, file: &Path, what: &str, seams: Option<&Seams>) -> String {
    let mut msg = format!(
        "{}: {what} needs a closed mesh, but it has {}",
        file.display(),
        plural(check.boundary_edges, "boundary edge", "boundary edges")
    );
    if let Some(s) = seams {
        if !s.examples.is_empty() {
            msg.push_str(&format!(" (0-based vertices: {}", s.examples.join("; ")));
            if check.boundary_edges > s.examples.len() {
                msg.push_str(&format!(
                    " and {} more",
                    check.boundary_edges - s.examples.len()
                ));
            }
            msg.push(')');
        }
    }
    if check.non_manifold_edges > 0 {
        msg.push_str(&format!(
            " and {}",
            plural(
                check.non_manifold_edges,
                "non-manifold edge",
                "non-manifold edges"
            )
        ));
    }
    match seams {
        Some(s) if s.paired > 0 && s.paired == check.boundary_edges => msg.push_str(
            ": the mesh is open only because its seams are split (every boundary edge \
             coincides in position with another, as after a UV or normal export): weld \
             vertices at equal positions (e.g. MeshLab's Merge Close Vertices, trimesh's \
             merge_vertices), or drop the volume constraint",
        ),
        Some(s) if s.paired > 0 => msg.push_str(&format!(
            ": {} of them coincide in position with another (split seams: weld vertices \
             at equal positions); fill the remaining holes (e.g. MeshLab's Close Holes) or \
             drop the volume constraint",
            s.paired
        )),
        _ if check.boundary_edges > 0 => msg.push_str(
            ": fill the holes (e.g. MeshLab's Close Holes) or drop the volume constraint",
        ),
        _ => {
            msg.push_str(": make every edge have exactly two faces, or drop the volume constraint")
        }
    }
    msg
}

/// Boundary edges that coincide in position with another boundary edge.
struct Seams {
    paired: usize,
    /// A few boundary edges, as "(a, b)", for the message.
    examples: Vec<String>,
}

fn seams(mesh: &Mesh, topo: &Topology) -> Seams {
    use std::collections::HashMap;
    // Positions equal bit for bit (-0.0 = 0.0), else equal on a grid of 1e-9 times
    // the bbox diagonal (exporters that print seam copies with other rounding).
    let count_paired = |key: &dyn Fn(u32) -> [u64; 3]| -> usize {
        let keys: Vec<([u64; 3], [u64; 3])> = topo
            .boundary_edges
            .iter()
            .map(|&e| {
                let [a, b] = topo.edges[e];
                let (ka, kb) = (key(a), key(b));
                if ka <= kb {
                    (ka, kb)
                } else {
                    (kb, ka)
                }
            })
            .collect();
        let mut count: HashMap<([u64; 3], [u64; 3]), usize> = HashMap::new();
        for k in &keys {
            *count.entry(*k).or_default() += 1;
        }
        keys.iter().filter(|k| count[*k] >= 2).count()
    };
    let exact = |v: u32| -> [u64; 3] {
        mesh.positions[v as usize]
            .to_array()
            .map(|c| if c == 0.0 { 0 } else { c.to_bits() })
    };
    let mut paired = count_paired(&exact);
    let grid = 1e-9 * mesh.bbox_diagonal(&mesh.positions);
    if paired < topo.boundary_edges.len() && grid > 0.0 {
        let snapped = |v: u32| -> [u64; 3] {
            mesh.positions[v as usize]
                .to_array()
                .map(|c| (c / grid).round() as i64 as u64)
        };
        paired = paired.max(count_paired(&snapped));
    }
    let examples = topo
        .boundary_edges
        .iter()
        .take(MAX_LISTED)
        .map(|&e| format!("({}, {})", topo.edges[e][0], topo.edges[e][1]))
        .collect();
    Seams { paired, examples }
}

/// Everything a volume constraint needs (contract: "Volume"): a closed mesh (every
/// edge has two faces; when the mesh is open only because its seams are split, the
/// message says to weld vertices) whose faces are consistently oriented (each
/// interior edge runs one way in one face and the other way in the other; an
/// inward-oriented mesh is fine). `what` names the constraint.
pub fn require_volume(
    mesh: &Mesh,
    topo: &Topology,
    check: &MeshCheck,
    file: &Path,
    what: &str,
) -> Result<()> {
    if !check.closed {
        let s = seams(mesh, topo);
        return Err(Error::bad(closed_message(check, file, what, Some(&s))));
    }
    let runs_forward = |f: u32, a: u32, b: u32| -> bool {
        let t = mesh.faces[f as usize];
        (0..3).any(|k| t[k] == a && t[(k + 1) % 3] == b)
    };
    // The edges whose two faces run them the same way: counted on rayon's
    // threads; the first few listed, in edge order, only where there are any.
    let disagree = |e: usize| -> Option<(u32, u32)> {
        let [a, b] = topo.edges[e];
        match *topo.edge_faces(e) {
            [f, g] if runs_forward(f, a, b) == runs_forward(g, a, b) => Some((f, g)),
            _ => None,
        }
    };
    let count = {
        use rayon::prelude::*;
        (0..topo.edges.len())
            .into_par_iter()
            .filter(|&e| disagree(e).is_some())
            .count()
    };
    if count > 0 {
        let bad: Vec<String> = (0..topo.edges.len())
            .filter_map(|e| {
                let [a, b] = topo.edges[e];
                disagree(e)
                    .map(|(f, g)| format!("edge ({a}, {b}) runs the same way in faces {f} and {g}"))
            })
            .take(MAX_LISTED)
            .collect();
        return Err(Error::bad(format!(
            "{}: {what} needs a consistently oriented mesh, but {} (0-based; the two \
             faces of an edge must list it in opposite orders): {}{}: re-orient the faces \
             consistently (e.g. MeshLab's Re-Orient all faces coherently, libigl's \
             bfs_orient, trimesh's fix_winding), or drop the volume constraint",
            file.display(),
            plural(
                count,
                "edge has two faces that disagree on orientation",
                "edges have two faces that disagree on orientation"
            ),
            bad.join("; "),
            if count > bad.len() {
                format!(" and {} more", count - bad.len())
            } else {
                String::new()
            }
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh(positions: usize, faces: &[[u32; 3]]) -> Mesh {
        Mesh {
            positions: (0..positions)
                .map(|i| glam::DVec3::new(i as f64, (i * i % 7) as f64, (i % 3) as f64))
                .collect(),
            faces: faces.to_vec(),
            groups: Vec::new(),
        }
    }

    /// A closed cone: apex `a`, ring `r` (three vertices), its cap.
    fn cone(a: u32, r: [u32; 3]) -> [[u32; 3]; 4] {
        [
            [a, r[0], r[1]],
            [a, r[1], r[2]],
            [a, r[2], r[0]],
            [r[0], r[2], r[1]],
        ]
    }

    /// Every vertex's verdict from its faces' corners ([`one_fan`]) equals
    /// the union-find's through the edges ([`several_fans`]), where it has
    /// one; the vertices it decided.
    fn corners_agree(m: &Mesh, topo: &Topology) -> usize {
        let mut decided = 0;
        for v in 0..m.num_vertices() {
            let fs = topo.vertex_faces(v);
            if fs.len() < 2 {
                continue;
            }
            if let Some(one) = one_fan(m, v, fs) {
                assert_eq!(!one, several_fans(m, topo, v, fs), "vertex {v}");
                decided += 1;
            }
        }
        decided
    }

    /// Two triangles touching at a corner (a bowtie) and two closed cones
    /// touching at their apex (an hourglass: two closed fans, which counting
    /// a vertex's interior and boundary sides does not tell from one) both
    /// pinch their shared vertex, and only it.
    #[test]
    fn pinched_vertices_are_found_from_the_corners() {
        let bowtie = mesh(5, &[[0, 1, 2], [0, 3, 4]]);
        let topo = Topology::build(&bowtie);
        assert_eq!(non_manifold_vertices(&bowtie, &topo), vec![0]);
        assert_eq!(corners_agree(&bowtie, &topo), 1);

        let faces: Vec<[u32; 3]> = cone(0, [1, 2, 3])
            .into_iter()
            .chain(cone(0, [4, 5, 6]))
            .collect();
        let hourglass = mesh(7, &faces);
        let topo = Topology::build(&hourglass);
        assert!(topo.is_closed());
        assert_eq!(non_manifold_vertices(&hourglass, &topo), vec![0]);
        assert_eq!(corners_agree(&hourglass, &topo), 7);
    }

    /// A closed mesh, an open disk (a fan with two boundary sides) and a
    /// mesh with duplicate and collapsed faces (left out of the vertices'
    /// faces) have no pinched vertex; the corners decide every vertex.
    #[test]
    fn manifold_vertices_are_not_listed() {
        let octahedron = mesh(
            6,
            &[
                [0, 2, 4],
                [2, 1, 4],
                [1, 3, 4],
                [3, 0, 4],
                [2, 0, 5],
                [1, 2, 5],
                [3, 1, 5],
                [0, 3, 5],
            ],
        );
        let topo = Topology::build(&octahedron);
        assert!(non_manifold_vertices(&octahedron, &topo).is_empty());
        assert_eq!(corners_agree(&octahedron, &topo), 6);

        let disk = mesh(6, &[[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]]);
        let topo = Topology::build(&disk);
        assert!(non_manifold_vertices(&disk, &topo).is_empty());
        assert_eq!(corners_agree(&disk, &topo), 4);

        let mut faces = octahedron.faces.clone();
        faces.extend([[4, 0, 2], [1, 1, 3]]);
        let odd = mesh(6, &faces);
        let topo = Topology::build(&odd);
        assert_eq!(topo.duplicate_faces.len(), 1);
        assert_eq!(topo.collapsed_faces.len(), 1);
        assert!(non_manifold_vertices(&odd, &topo).is_empty());
        assert_eq!(corners_agree(&odd, &topo), 6);
    }

    /// On a real mesh with pinches added (a bowtie's wing glued to a vertex
    /// of it, and a second cone's apex at another), the corners and the
    /// union-find agree on every vertex, and the pinched ones are listed.
    #[test]
    fn the_corners_agree_with_the_union_find_on_spot() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes/spot.obj");
        let mut m = crate::mesh::io::read_mesh(&path).unwrap();
        let n = m.num_vertices() as u32;
        for i in 0..5 {
            m.positions
                .push(glam::DVec3::new(3.0 + i as f64, 0.5 * i as f64, 1.0));
        }
        m.faces.push([7, n, n + 1]);
        m.faces.extend(cone(100, [n + 2, n + 3, n + 4]));
        let topo = Topology::build(&m);
        assert_eq!(non_manifold_vertices(&m, &topo), vec![7, 100]);
        // All but the wing's two corners of one face.
        assert_eq!(corners_agree(&m, &topo), m.num_vertices() - 2);
    }

    /// A volume job on a closed mesh with faces flipped lists the first
    /// edges whose two faces run them the same way, in edge order, and
    /// counts the rest.
    #[test]
    fn flipped_faces_are_listed_in_edge_order_and_counted() {
        let mut faces: Vec<[u32; 3]> = cone(0, [1, 2, 3]).to_vec();
        faces.extend(cone(4, [5, 6, 7]));
        // Two faces of the first cone (sharing an edge, which they still
        // run opposite ways) and one of the second flipped: four edges of the
        // first, three of the second.
        for f in [0, 3, 5] {
            faces[f].swap(1, 2);
        }
        let m = mesh(8, &faces);
        let topo = Topology::build(&m);
        let file = Path::new("two-cones.obj");
        let check = validate(&m, &topo, file).unwrap();
        let msg = require_volume(&m, &topo, &check, file, "constraint 1 (volume)")
            .unwrap_err()
            .to_string();
        let disagreeing: Vec<usize> = (0..topo.edges.len())
            .filter(|&e| {
                let fs = topo.edge_faces(e);
                let [a, b] = topo.edges[e];
                let forward = |f: u32| {
                    let t = m.faces[f as usize];
                    (0..3).any(|k| t[k] == a && t[(k + 1) % 3] == b)
                };
                forward(fs[0]) == forward(fs[1])
            })
            .collect();
        assert_eq!(disagreeing.len(), 7);
        assert!(
            msg.contains("7 edges have two faces that disagree"),
            "{msg}"
        );
        assert!(msg.contains(" and 2 more"), "{msg}");
        let listed: Vec<String> = disagreeing[..MAX_LISTED]
            .iter()
            .map(|&e| format!("edge ({}, {})", topo.edges[e][0], topo.edges[e][1]))
            .collect();
        let mut at = 0;
        for edge in &listed {
            let found = msg[at..]
                .find(edge.as_str())
                .unwrap_or_else(|| panic!("{edge} in {msg}"));
            at += found + edge.len();
        }
        assert!(!msg[at..].contains("edge ("), "{msg}");
    }
}
