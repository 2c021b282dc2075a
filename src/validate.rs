//! Input mesh checks: what the method cannot work with is rejected with a message that
//! names the file and the offending elements; what it can live with is counted.
//!
//! Rejected ([`Error::BadInput`]): no faces, face corners out of range, non-finite
//! coordinates on vertices used by faces, degenerate faces (a repeated vertex or zero area,
//! `area <= 1e-14 * bbox_diagonal^2`) and non-manifold edges (more than two faces).
//!
//! Accepted and counted ([`MeshCheck`]): boundary edges, unreferenced vertices (logged with
//! `log::warn!`), connected components. Non-manifold vertices (two fans of faces meeting in
//! one vertex) are logged with `log::warn!` but not rejected.
//!
//! Vertex and face indices in messages are 0-based (faces are triangles after fan
//! triangulation, numbered in file order).

use crate::error::{Error, Result};
use crate::mesh::Mesh;
use crate::topology::Topology;
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

fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

fn find(parent: &mut [u32], mut x: u32) -> u32 {
    while parent[x as usize] != x {
        let p = parent[x as usize];
        parent[x as usize] = parent[p as usize];
        x = p;
    }
    x
}

fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    if ra != rb {
        parent[ra.max(rb) as usize] = ra.min(rb);
    }
}

/// Checks `mesh` (with its topology `topo`) for use by the solver; `file` is named in the
/// messages. Returns the counts of tolerated defects, or [`Error::BadInput`] listing at
/// most five offenders of the first failed check.
pub fn validate(mesh: &Mesh, topo: &Topology, file: &Path) -> Result<MeshCheck> {
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

    // Degenerate faces.
    let x = &mesh.positions;
    let diag = mesh.bbox_diagonal(x);
    let tol = 1e-14 * diag * diag;
    let degenerate: Vec<String> = mesh
        .faces
        .iter()
        .enumerate()
        .filter_map(|(f, t)| {
            let [a, b, c] = *t;
            if a == b || b == c || a == c {
                Some(format!("face {f} ({a}, {b}, {c}) repeats a vertex"))
            } else {
                let area = mesh.face_area(x, f);
                (area <= tol).then(|| format!("face {f} ({a}, {b}, {c}) has area {area:e}"))
            }
        })
        .collect();
    if !degenerate.is_empty() {
        return Err(Error::bad(format!(
            "{file_s}: {} (0-based triangle index (vertices), zero area means <= {tol:e} = \
             1e-14 * bbox diagonal^2): {}",
            plural(degenerate.len(), "degenerate face", "degenerate faces"),
            listing(&degenerate)
        )));
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
        log::warn!(
            "{file_s}: {} not used by any face (ignored; 0-based): {}",
            plural(unreferenced, "vertex is", "vertices are"),
            listing(&first)
        );
    }

    // Tolerated: non-manifold vertices (the faces around a vertex form several fans).
    let nm_vertices = non_manifold_vertices(mesh, topo);
    if !nm_vertices.is_empty() {
        let items: Vec<String> = nm_vertices.iter().map(|v| v.to_string()).collect();
        log::warn!(
            "{file_s}: {} where separate fans of faces meet (0-based): {}",
            plural(items.len(), "non-manifold vertex", "non-manifold vertices"),
            listing(&items)
        );
    }

    // Connected components of faces via shared vertices.
    let mut parent: Vec<u32> = (0..nv as u32).collect();
    for t in &mesh.faces {
        union(&mut parent, t[0], t[1]);
        union(&mut parent, t[0], t[2]);
    }
    let mut is_root = vec![false; nv];
    for v in 0..nv {
        if used[v] {
            is_root[find(&mut parent, v as u32) as usize] = true;
        }
    }
    let components = is_root.iter().filter(|&&r| r).count();

    let check = MeshCheck {
        boundary_edges: topo.boundary_edges.len(),
        non_manifold_edges: topo.non_manifold_edges.len(),
        unreferenced_vertices: unreferenced,
        components,
        closed: topo.boundary_edges.is_empty() && topo.non_manifold_edges.is_empty(),
    };
    log::debug!("{file_s}: {check:?}");
    Ok(check)
}

/// Vertices whose incident faces form more than one fan (faces connected through edges
/// incident to the vertex). Assumes no non-manifold edges.
fn non_manifold_vertices(mesh: &Mesh, topo: &Topology) -> Vec<usize> {
    let mut out = Vec::new();
    let mut local: Vec<u32> = Vec::new();
    for v in 0..mesh.positions.len() {
        let fs = topo.vertex_faces(v);
        if fs.len() < 2 {
            continue;
        }
        // Union-find over the faces around v (indices into fs).
        local.clear();
        local.extend(0..fs.len() as u32);
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
                            union(&mut local, i as u32, j as u32);
                        }
                    }
                }
            }
        }
        let root = find(&mut local, 0);
        if (1..fs.len() as u32).any(|i| find(&mut local, i) != root) {
            out.push(v);
        }
    }
    out
}

/// Fails unless the mesh is closed: `what` names the requirement, e.g.
/// `volume constraint 'body'`, giving
/// "<file>: volume constraint 'body' needs a closed mesh, but it has 223 boundary edges".
pub fn require_closed(check: &MeshCheck, file: &Path, what: &str) -> Result<()> {
    if check.closed {
        return Ok(());
    }
    let mut msg = format!(
        "{}: {what} needs a closed mesh, but it has {}",
        file.display(),
        plural(check.boundary_edges, "boundary edge", "boundary edges")
    );
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
    Err(Error::bad(msg))
}
