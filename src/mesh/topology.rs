//! Edge and adjacency structure of a triangle mesh.

use crate::mesh::Mesh;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// Undirected edges, the faces around them, and face-face adjacency.
#[derive(Clone, Debug, Default)]
pub struct Topology {
    /// Unique undirected edges `[a, b]` with `a < b`.
    pub edges: Vec<[u32; 2]>,
    /// Faces of each edge, CSR (1 = boundary, 2 = interior, >2 = non-manifold):
    /// read them with [`Topology::edge_faces`]. Flat, not a `Vec` per edge: at a
    /// million faces that is ~70 MB less.
    edge_face_start: Vec<usize>,
    edge_face_index: Vec<u32>,
    /// For each face, the edge index of each side: side k joins corners k and k+1.
    pub face_edges: Vec<[u32; 3]>,
    /// Pairs of faces sharing a manifold interior edge (the set Q of Eq. 2).
    pub face_pairs: Vec<[u32; 2]>,
    /// Edges with exactly one face.
    pub boundary_edges: Vec<usize>,
    /// Edges with more than two faces.
    pub non_manifold_edges: Vec<usize>,
    /// Faces around each vertex, CSR: faces of v are `vf_index[vf_start[v]..vf_start[v+1]]`.
    /// Duplicate and collapsed faces (`ignored`) are left out.
    pub vf_start: Vec<usize>,
    pub vf_index: Vec<u32>,
    /// Duplicate faces `(f, g)`: face `f` has the same three vertices as the earlier
    /// face `g` (in any order or orientation), in face order. A duplicate keeps its
    /// index and its `face_edges`, but is left out of `edge_faces` and
    /// `vertex_faces`, so it makes no edge non-manifold; `face_pairs` ties it to
    /// `g` instead.
    pub duplicate_faces: Vec<(u32, u32)>,
    /// Per face: true when it duplicates an earlier face.
    pub is_duplicate: Vec<bool>,
    /// Faces with a repeated corner index (`[a, a, b]`, e.g. an STL triangle with two
    /// equal corners): zero area, no triangle. Like duplicates they keep their
    /// index and `face_edges` (a side `(a, a)` is an edge with no faces), but are
    /// left out of `edge_faces` and `vertex_faces`; `face_pairs` ties each to a face
    /// of one of its sides when there is one.
    pub collapsed_faces: Vec<u32>,
    /// Per face: a duplicate or collapsed face, left out of the adjacency.
    pub ignored: Vec<bool>,
    /// Each vertex's connected component through the faces, and their
    /// number: [`vertex_components`].
    pub vertex_component: Vec<u32>,
    pub components: usize,
}

/// The edges of `faces` (each face's sides `(t[k], t[k + 1])`, as the
/// pair `(min, max)`), numbered in the order they first appear, face after
/// face; and each face's three edge numbers. Where every corner is one of
/// the `nv` vertices, each side is looked up among the sides already seen
/// at its smaller end (a few each: a linear search in that vertex's slots),
/// else in a hash map: the same numbering either way. At homer 1.2M the
/// hash map (Fx) took 0.148 s of `Topology::build`'s 0.26 s on the
/// development machine.
fn number_edges(faces: &[[u32; 3]], nv: usize) -> (Vec<[u32; 2]>, Vec<[u32; 3]>) {
    let sides = |t: &[u32; 3]| {
        let t = *t;
        (0..3).map(move |k| {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            (a.min(b), a.max(b))
        })
    };
    let mut edges = Vec::with_capacity(faces.len() * 3 / 2 + 16);
    let mut face_edges = Vec::with_capacity(faces.len());
    if faces.iter().flatten().any(|&v| v as usize >= nv) {
        let mut map: FxHashMap<(u32, u32), u32> =
            FxHashMap::with_capacity_and_hasher(faces.len() * 3 / 2 + 16, Default::default());
        for t in faces {
            let mut fe = [0u32; 3];
            for (k, key) in sides(t).enumerate() {
                fe[k] = *map.entry(key).or_insert_with(|| {
                    edges.push([key.0, key.1]);
                    (edges.len() - 1) as u32
                });
            }
            face_edges.push(fe);
        }
        return (edges, face_edges);
    }
    // Each vertex's slots for the sides whose smaller end it is: the
    // larger end and the edge's number.
    let mut start = vec![0usize; nv + 1];
    for t in faces {
        for (lo, _) in sides(t) {
            start[lo as usize + 1] += 1;
        }
    }
    for v in 0..nv {
        start[v + 1] += start[v];
    }
    let mut filled = start[..nv].to_vec();
    let mut slots = vec![(0u32, 0u32); start[nv]];
    for t in faces {
        let mut fe = [0u32; 3];
        for (k, (lo, hi)) in sides(t).enumerate() {
            let v = lo as usize;
            let seen = slots[start[v]..filled[v]].iter().find(|s| s.0 == hi);
            fe[k] = match seen {
                Some(&(_, e)) => e,
                None => {
                    let e = edges.len() as u32;
                    edges.push([lo, hi]);
                    slots[filled[v]] = (hi, e);
                    filled[v] += 1;
                    e
                }
            };
        }
        face_edges.push(fe);
    }
    (edges, face_edges)
}

impl Topology {
    pub fn build(mesh: &Mesh) -> Topology {
        let nf = mesh.faces.len();
        let nv = mesh.positions.len();
        // The components beside the edges' numbering: both walk the faces
        // once, one after the other (homer 4.3M on the development machine:
        // 0.11-0.16 s and 0.09 s).
        let ((edges, face_edges), (vertex_component, components)) =
            rayon::join(|| number_edges(&mesh.faces, nv), || vertex_components(mesh));
        // Duplicate faces: the same vertex set as an earlier face, found
        // among the faces of their smallest edge (faces with the same
        // vertices have the same edges). Without a map over the faces'
        // vertex sets (0.069 s at homer 1.2M on the development machine,
        // Fx-hashed).
        let key = |f: usize| {
            let mut key = mesh.faces[f];
            key.sort_unstable();
            key
        };
        // Faces with a repeated corner, sorted once (the adjacency and the
        // duplicates below both ask).
        let collapsed: Vec<bool> = (0..nf)
            .into_par_iter()
            .map(|f| {
                let k = key(f);
                k[0] == k[1] || k[1] == k[2]
            })
            .collect();
        let smallest_edge = |f: usize| *face_edges[f].iter().min().unwrap() as usize;
        let ne = edges.len();
        // The faces of each edge and of each vertex (at once), leaving out
        // `ignored`'s; made first with the collapsed faces alone left out,
        // and made again only where there are duplicates.
        let adjacency = |ignored: &[bool]| {
            rayon::join(
                || {
                    compressed_rows(ne, |add| {
                        for (f, fe) in face_edges.iter().enumerate() {
                            if !ignored[f] {
                                fe.iter().for_each(|&e| add(e as usize, f as u32));
                            }
                        }
                    })
                },
                || {
                    compressed_rows(nv, |add| {
                        for (f, t) in mesh.faces.iter().enumerate() {
                            if !ignored[f] {
                                t.iter()
                                    .filter(|&&v| (v as usize) < nv)
                                    .for_each(|&v| add(v as usize, f as u32));
                            }
                        }
                    })
                },
            )
        };
        let mut made = adjacency(&collapsed);
        // Each face's first earlier face with its vertices (among the faces
        // of its smallest edge, which every such face has), on rayon's
        // threads; the lists in face order after.
        let first: Vec<Option<u32>> = {
            let (start, by_edge) = &made.0;
            (0..nf)
                .into_par_iter()
                .map(|f| {
                    if collapsed[f] {
                        return None;
                    }
                    let e = smallest_edge(f);
                    let kf = key(f);
                    by_edge[start[e]..start[e + 1]]
                        .iter()
                        .take_while(|&&g| (g as usize) < f)
                        .find(|&&g| key(g as usize) == kf)
                        .copied()
                })
                .collect()
        };
        let mut duplicate_faces = Vec::new();
        let mut is_duplicate = vec![false; nf];
        let mut collapsed_faces = Vec::new();
        let mut ignored = vec![false; nf];
        for f in 0..nf {
            if collapsed[f] {
                collapsed_faces.push(f as u32);
                ignored[f] = true;
            } else if let Some(g) = first[f] {
                duplicate_faces.push((f as u32, g));
                is_duplicate[f] = true;
                ignored[f] = true;
            }
        }
        drop(first);
        if !duplicate_faces.is_empty() {
            drop(made);
            made = adjacency(&ignored);
        }
        let ((edge_face_start, edge_face_index), (vf_start, vf_index)) = made;
        let mut face_pairs = Vec::new();
        let mut boundary_edges = Vec::new();
        let mut non_manifold_edges = Vec::new();
        for e in 0..ne {
            let fs = &edge_face_index[edge_face_start[e]..edge_face_start[e + 1]];
            match fs.len() {
                1 => boundary_edges.push(e),
                2 => {
                    if fs[0] != fs[1] {
                        face_pairs.push([fs[0], fs[1]])
                    }
                }
                0 => {}
                _ => non_manifold_edges.push(e),
            }
        }
        face_pairs.extend(duplicate_faces.iter().map(|&(f, g)| [g, f]));
        for &f in &collapsed_faces {
            let partner = face_edges[f as usize].iter().find_map(|&e| {
                let e = e as usize;
                (edge_face_start[e + 1] > edge_face_start[e])
                    .then(|| edge_face_index[edge_face_start[e]])
            });
            if let Some(g) = partner {
                face_pairs.push([g, f]);
            }
        }
        Topology {
            edges,
            edge_face_start,
            edge_face_index,
            face_edges,
            face_pairs,
            boundary_edges,
            non_manifold_edges,
            vf_start,
            vf_index,
            duplicate_faces,
            is_duplicate,
            collapsed_faces,
            ignored,
            vertex_component,
            components,
        }
    }

    /// Faces using edge `e`, in face order.
    #[inline]
    pub fn edge_faces(&self, e: usize) -> &[u32] {
        &self.edge_face_index[self.edge_face_start[e]..self.edge_face_start[e + 1]]
    }

    /// Faces around vertex `v`.
    #[inline]
    pub fn vertex_faces(&self, v: usize) -> &[u32] {
        &self.vf_index[self.vf_start[v]..self.vf_start[v + 1]]
    }

    /// True when every edge has exactly two faces.
    pub fn is_closed(&self) -> bool {
        self.boundary_edges.is_empty() && self.non_manifold_edges.is_empty()
    }
}

/// Compressed rows: `entries` calls its argument `add(row, item)` for every
/// item (the same items in the same order each time it is called: it is
/// called twice, to count and to fill); row r's items are
/// `items[start[r]..start[r + 1]]`, in the order added.
pub fn compressed_rows<T: Copy + Default>(
    rows: usize,
    entries: impl Fn(&mut dyn FnMut(usize, T)),
) -> (Vec<usize>, Vec<T>) {
    let mut start = vec![0usize; rows + 1];
    entries(&mut |r, _| start[r + 1] += 1);
    for r in 0..rows {
        start[r + 1] += start[r];
    }
    let mut fill = start.clone();
    let mut items = vec![T::default(); start[rows]];
    entries(&mut |r, item| {
        items[fill[r]] = item;
        fill[r] += 1;
    });
    (start, items)
}

/// Disjoint sets of `0..n` (union by smaller root, path halving).
pub struct UnionFind(Vec<u32>);

impl UnionFind {
    pub fn new(n: usize) -> UnionFind {
        UnionFind((0..n as u32).collect())
    }

    /// The set's root; roots are the smallest member of their set.
    pub fn find(&mut self, mut x: u32) -> u32 {
        let p = &mut self.0;
        while p[x as usize] != x {
            p[x as usize] = p[p[x as usize] as usize];
            x = p[x as usize];
        }
        x
    }

    /// Joins the sets of `a` and `b`.
    pub fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.0[ra.max(rb) as usize] = ra.min(rb);
        }
    }
}

/// Connected components of the vertices through the faces: each vertex's
/// component label (0-based, numbered in vertex order; a vertex in no face
/// is its own component) and the number of components. A face with a
/// corner out of range joins nothing (`validate` refuses such a mesh).
pub fn vertex_components(mesh: &Mesh) -> (Vec<u32>, usize) {
    let n = mesh.num_vertices();
    let mut sets = UnionFind::new(n);
    for t in &mesh.faces {
        if t.iter().all(|&v| (v as usize) < n) {
            sets.union(t[0], t[1]);
            sets.union(t[0], t[2]);
        }
    }
    let mut label = vec![u32::MAX; n];
    let mut count = 0usize;
    let mut out = vec![0u32; n];
    for v in 0..n {
        let r = sets.find(v as u32) as usize;
        if label[r] == u32::MAX {
            label[r] = count as u32;
            count += 1;
        }
        out[v] = label[r];
    }
    (out, count)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Duplicate and collapsed faces are those a map over the faces'
    /// sorted vertex sets finds: each duplicate paired with the first face
    /// of its set, in face order (rotated, reversed and triple copies, and a
    /// collapsed face's copy, among them).
    #[test]
    fn duplicates_are_those_a_map_of_vertex_sets_finds() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes/spot.obj");
        let mut mesh = crate::mesh::io::read_mesh(&path).unwrap();
        let t = mesh.faces[100];
        mesh.faces.extend([
            [t[1], t[2], t[0]],
            [t[2], t[1], t[0]],
            [5, 5, 9],
            [9, 5, 5],
            t,
        ]);
        let u = mesh.faces[2000];
        mesh.faces.insert(1500, [u[2], u[0], u[1]]);
        let topo = Topology::build(&mesh);
        let mut first = std::collections::HashMap::new();
        let (mut duplicates, mut collapsed) = (Vec::new(), Vec::new());
        for (f, t) in mesh.faces.iter().enumerate() {
            let mut key = *t;
            key.sort_unstable();
            if key[0] == key[1] || key[1] == key[2] {
                collapsed.push(f as u32);
                continue;
            }
            match first.get(&key) {
                Some(&g) => duplicates.push((f as u32, g)),
                None => {
                    first.insert(key, f as u32);
                }
            }
        }
        assert_eq!(duplicates.len(), 4, "{duplicates:?}");
        assert_eq!(topo.duplicate_faces, duplicates);
        assert_eq!(topo.collapsed_faces, collapsed);
        for (f, &d) in topo.is_duplicate.iter().enumerate() {
            assert_eq!(
                d,
                duplicates.iter().any(|&(g, _)| g as usize == f),
                "face {f}"
            );
        }
        adjacency_leaves_out_the_ignored_faces(&mesh, &topo);
        let spot = crate::mesh::io::read_mesh(&path).unwrap();
        adjacency_leaves_out_the_ignored_faces(&spot, &Topology::build(&spot));
    }

    /// Each edge's and each vertex's faces are the faces with it, the
    /// ignored (duplicate and collapsed) ones left out, in face order.
    fn adjacency_leaves_out_the_ignored_faces(mesh: &Mesh, topo: &Topology) {
        let kept = |f: &usize| !topo.ignored[*f];
        for (e, &[a, b]) in topo.edges.iter().enumerate() {
            let want: Vec<u32> = (0..mesh.faces.len())
                .filter(kept)
                .filter(|&f| topo.face_edges[f].contains(&(e as u32)))
                .map(|f| f as u32)
                .collect();
            assert_eq!(topo.edge_faces(e), want, "edge ({a}, {b})");
        }
        let mut want = vec![Vec::new(); mesh.positions.len()];
        for f in (0..mesh.faces.len()).filter(kept) {
            for &v in &mesh.faces[f] {
                want[v as usize].push(f as u32);
            }
        }
        for (v, want) in want.iter().enumerate() {
            assert_eq!(topo.vertex_faces(v), want, "vertex {v}");
        }
    }

    /// The slots' numbering is the hash map's (taken where a corner is out
    /// of range; here forced with no vertices), on spot and on spot with a
    /// collapsed face, a repeated face and a face reversed added.
    #[test]
    fn edges_are_numbered_alike_by_slots_and_by_the_hash_map() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes/spot.obj");
        let mut mesh = crate::mesh::io::read_mesh(&path).unwrap();
        let nv = mesh.positions.len();
        for extra in [
            vec![],
            vec![[3u32, 3, 7], [10, 11, 12], [12, 11, 10], [10, 11, 12]],
        ] {
            mesh.faces.extend(extra);
            let (slots, by_map) = (number_edges(&mesh.faces, nv), number_edges(&mesh.faces, 0));
            assert!(slots.0.len() > nv, "{} edges", slots.0.len());
            assert_eq!(slots, by_map);
            // Each face's edges are its sides.
            for (t, fe) in mesh.faces.iter().zip(&slots.1) {
                for k in 0..3 {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    assert_eq!(slots.0[fe[k] as usize], [a.min(b), a.max(b)]);
                }
            }
        }
    }

    /// The components made with the topology: numbered in vertex order, a
    /// vertex in no face its own; a face with a corner out of range joins
    /// nothing (and builds no panic: `validate` refuses the mesh after).
    #[test]
    fn components_are_numbered_in_vertex_order_and_skip_faces_out_of_range() {
        let mesh = Mesh {
            positions: vec![glam::DVec3::ZERO; 8],
            faces: vec![[4, 5, 6], [0, 1, 2], [2, 3, 1], [6, 7, 99]],
            groups: Vec::new(),
        };
        let topo = Topology::build(&mesh);
        assert_eq!(topo.vertex_component, vec![0, 0, 0, 0, 1, 1, 1, 2]);
        assert_eq!(topo.components, 3);
    }
}
