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
use crate::mesh::topology::{vertex_components, Topology, UnionFind};
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
    let (label, count) = vertex_components(mesh);
    let mut seen = vec![false; count];
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
/// rayon's threads, listed in vertex order.
fn non_manifold_vertices(mesh: &Mesh, topo: &Topology) -> Vec<usize> {
    use rayon::prelude::*;
    let more_than_one_fan = |v: usize| -> bool {
        let fs = topo.vertex_faces(v);
        if fs.len() < 2 {
            return false;
        }
        // Union-find over the faces around v (indices into fs).
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
    };
    (0..mesh.positions.len())
        .into_par_iter()
        .filter(|&v| more_than_one_fan(v))
        .collect()
}

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
    let mut bad: Vec<String> = Vec::new();
    let mut count = 0usize;
    for (e, &[a, b]) in topo.edges.iter().enumerate() {
        let fs = topo.edge_faces(e);
        if fs.len() != 2 {
            continue;
        }
        if runs_forward(fs[0], a, b) == runs_forward(fs[1], a, b) {
            count += 1;
            if bad.len() < MAX_LISTED {
                bad.push(format!(
                    "edge ({a}, {b}) runs the same way in faces {} and {}",
                    fs[0], fs[1]
                ));
            }
        }
    }
    if count > 0 {
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
