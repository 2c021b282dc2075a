//! Indexed triangle mesh, exactly as in the input file (contract: "Indices").
//!
//! Vertex `i` is the i-th vertex of the file, face `f` the f-th triangle after fan
//! triangulation in file order. Nothing is ever re-ordered, merged or split.

use glam::DVec3;

/// A named set of faces (OBJ `g`/`o` statement).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FaceGroup {
    pub name: String,
    pub faces: Vec<usize>,
}

/// Triangle mesh with positions in f64.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub positions: Vec<DVec3>,
    pub faces: Vec<[u32; 3]>,
    /// OBJ groups/objects (empty for PLY/STL). A face may be in several groups.
    pub groups: Vec<FaceGroup>,
}

impl Mesh {
    pub fn num_vertices(&self) -> usize {
        self.positions.len()
    }
    pub fn num_faces(&self) -> usize {
        self.faces.len()
    }

    /// The three corner positions of face `f` in the given position array.
    #[inline]
    pub fn corners(&self, x: &[DVec3], f: usize) -> [DVec3; 3] {
        let [a, b, c] = self.faces[f];
        [x[a as usize], x[b as usize], x[c as usize]]
    }

    /// Area of face `f` for positions `x`.
    #[inline]
    pub fn face_area(&self, x: &[DVec3], f: usize) -> f64 {
        let [a, b, c] = self.corners(x, f);
        0.5 * (b - a).cross(c - a).length()
    }

    /// Areas of all faces for positions `x`.
    pub fn face_areas(&self, x: &[DVec3]) -> Vec<f64> {
        (0..self.faces.len())
            .map(|f| self.face_area(x, f))
            .collect()
    }

    /// Signed volume (sum of signed tetrahedra to the origin) for positions `x`.
    pub fn signed_volume(&self, x: &[DVec3]) -> f64 {
        (0..self.faces.len())
            .map(|f| {
                let [a, b, c] = self.corners(x, f);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    /// Axis-aligned bounding box diagonal length of the vertices that faces use.
    pub fn bbox_diagonal(&self, x: &[DVec3]) -> f64 {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for t in &self.faces {
            for &v in t {
                lo = lo.min(x[v as usize]);
                hi = hi.max(x[v as usize]);
            }
        }
        if lo.x > hi.x {
            return 0.0;
        }
        (hi - lo).length()
    }

    /// Face centroid for positions `x`.
    #[inline]
    pub fn centroid(&self, x: &[DVec3], f: usize) -> DVec3 {
        let [a, b, c] = self.corners(x, f);
        (a + b + c) / 3.0
    }
}

impl Mesh {
    /// 1-to-4 midpoint subdivision (for benchmarks at larger sizes). Groups are dropped.
    pub fn subdivide_midpoint(&self) -> Mesh {
        use std::collections::HashMap;
        let mut positions = self.positions.clone();
        let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(self.faces.len() * 2);
        let mut faces = Vec::with_capacity(self.faces.len() * 4);
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<DVec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                positions.push(0.5 * (positions[a as usize] + positions[b as usize]));
                (positions.len() - 1) as u32
            })
        };
        for &[a, b, c] in &self.faces {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            faces.extend_from_slice(&[[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        Mesh {
            positions,
            faces,
            groups: Vec::new(),
        }
    }
}
