//! Quasi-conformal distortion (paper Fig. 17): per face, the ratio of the larger to
//! the smaller singular value of the affine map from the input triangle to the
//! output triangle; 1.0 is a similarity (uniform scale and rotation).

use crate::Mesh;
use glam::DVec3;
use serde::Serialize;

/// How far the vertices moved from the input to the output, each vertex's
/// `|output - input|` as a percentage of a length (the input's bbox diagonal,
/// [`Mesh::bbox_diagonal`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct DisplacementStats {
    pub max_percent: f64,
    /// Mean over all vertices.
    pub mean_percent: f64,
    /// The 99th percentile by the nearest-rank definition: with the n values
    /// sorted ascending, the ceil(0.99 n)-th (1-based).
    pub p99_percent: f64,
}

/// Per-vertex displacement `|output[i] - input[i]|` as a percentage of
/// `diagonal`: max, mean over every vertex and nearest-rank 99th percentile
/// ([`DisplacementStats`]). All zero when there are no vertices or `diagonal`
/// is not a positive finite number (nothing to measure against).
pub fn displacement_percent(input: &[DVec3], output: &[DVec3], diagonal: f64) -> DisplacementStats {
    let n = input.len().min(output.len());
    if n == 0 || !(diagonal.is_finite() && diagonal > 0.0) {
        return DisplacementStats::default();
    }
    let mut d = vertex_displacements(input, output, diagonal);
    let mean = d.iter().sum::<f64>() / n as f64;
    d.sort_unstable_by(f64::total_cmp);
    // Nearest rank: the smallest value with at least 99 % of the values <= it.
    let rank = ((0.99 * n as f64).ceil() as usize).clamp(1, n);
    DisplacementStats {
        max_percent: d[n - 1],
        mean_percent: mean,
        p99_percent: d[rank - 1],
    }
}

/// Per vertex, `|output - input|` as a % of `diagonal`.
pub fn vertex_displacements(input: &[DVec3], output: &[DVec3], diagonal: f64) -> Vec<f64> {
    input
        .iter()
        .zip(output)
        .map(|(a, b)| (*b - *a).length() / diagonal * 100.0)
        .collect()
}

/// Distortion of one face: sigma_max / sigma_min (infinity for a collapsed face).
pub fn face_ratio(a: [DVec3; 3], b: [DVec3; 3]) -> f64 {
    // Input triangle in its own orthonormal 2D frame.
    let e1 = a[1] - a[0];
    let e2 = a[2] - a[0];
    let u = e1.normalize();
    let nrm = e1.cross(e2);
    let w = nrm.normalize().cross(u);
    let (x1, x2, y2) = (e1.length(), e2.dot(u), e2.dot(w));
    let det = x1 * y2;
    if det == 0.0 || !det.is_finite() {
        return f64::INFINITY;
    }
    // J = [f1 f2] * inv([[x1, x2], [0, y2]]) with f the output edges (3x2 map).
    let f1 = b[1] - b[0];
    let f2 = b[2] - b[0];
    let j1 = f1 / x1;
    let j2 = (f2 - j1 * x2) / y2;
    // Singular values from the 2x2 Gram matrix.
    let (p, q, r) = (j1.dot(j1), j1.dot(j2), j2.dot(j2));
    let tr = p + r;
    let disc = ((p - r) * (p - r) + 4.0 * q * q).sqrt();
    let l1 = 0.5 * (tr + disc);
    let l2 = (0.5 * (tr - disc)).max(0.0);
    if l2 <= 0.0 {
        return f64::INFINITY;
    }
    (l1 / l2).sqrt()
}

/// Per face, [`face_ratio`] from `input` to `output`; faces degenerate in the
/// input ([`Mesh::degenerate_faces`]: zero area, needles) have no meaningful
/// ratio and get 1.0.
pub fn face_distortions(mesh: &Mesh, input: &[DVec3], output: &[DVec3]) -> Vec<f64> {
    distortions_but(mesh, input, output, &mesh.degenerate_faces(input))
}

/// [`face_distortions`] with the input's degenerate faces given.
fn distortions_but(
    mesh: &Mesh,
    input: &[DVec3],
    output: &[DVec3],
    degenerate: &[bool],
) -> Vec<f64> {
    (0..mesh.num_faces())
        .map(|f| {
            if degenerate[f] {
                1.0
            } else {
                face_ratio(mesh.corners(input, f), mesh.corners(output, f))
            }
        })
        .collect()
}

/// Per face, the scale factor the result realised: `sqrt(area out / area in)`
/// (paper Eq. 3's `s`); 1.0 for faces of zero input area.
pub fn face_scales(mesh: &Mesh, input: &[DVec3], output: &[DVec3]) -> Vec<f64> {
    (0..mesh.num_faces())
        .map(|f| {
            let a = mesh.face_area(input, f);
            if a > 0.0 {
                (mesh.face_area(output, f) / a).sqrt()
            } else {
                1.0
            }
        })
        .collect()
}

/// (area-weighted mean over faces with input area as weight, max). Faces
/// degenerate in the input ([`Mesh::degenerate_faces`]: zero area, needles)
/// have no meaningful ratio and get no shape weight: they are left out.
pub fn quasi_conformal(mesh: &Mesh, input: &[DVec3], output: &[DVec3]) -> (f64, f64) {
    distortion_summary(mesh, input, &face_distortions(mesh, input, output))
}

/// The area-weighted mean and the max of per-face distortions `ratios` (as
/// [`face_distortions`] gives them), the input's degenerate faces left out.
pub fn distortion_summary(mesh: &Mesh, input: &[DVec3], ratios: &[f64]) -> (f64, f64) {
    let degenerate = mesh.degenerate_faces(input);
    let mut sum = 0.0;
    let mut wsum = 0.0;
    let mut max = 1.0f64;
    for (f, &r) in ratios.iter().enumerate() {
        if degenerate[f] {
            continue;
        }
        let a = mesh.face_area(input, f);
        if r.is_finite() {
            sum += a * r;
            wsum += a;
        }
        max = max.max(r);
    }
    (if wsum > 0.0 { sum / wsum } else { 1.0 }, max)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A zero-area input face does not make the maximum infinite; a face that
    /// collapses in the output still does.
    #[test]
    fn degenerate_input_faces_are_left_out() {
        let x = vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(2.0, 0.0, 0.0)];
        // Face 1 is (0, 1, 3): collinear, zero area.
        let mesh = Mesh {
            positions: x.clone(),
            faces: vec![[0, 1, 2], [0, 1, 3]],
            groups: Vec::new(),
        };
        let (mean, max) = quasi_conformal(&mesh, &x, &x);
        assert_eq!((mean, max), (1.0, 1.0));
        let mut y = x.clone();
        y[2] = DVec3::new(0.5, 0.0, 0.0);
        assert_eq!(quasi_conformal(&mesh, &x, &y).1, f64::INFINITY);
    }
    /// A face scaled by 2 in both directions has scale 2 and distortion 1;
    /// one stretched by 3 in one direction has scale sqrt(3) and distortion 3.
    #[test]
    fn per_face_fields_follow_the_map() {
        let x = vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(1.0, 1.0, 0.0)];
        let mesh = Mesh {
            positions: x.clone(),
            faces: vec![[0, 1, 2], [1, 3, 2]],
            groups: Vec::new(),
        };
        let y: Vec<DVec3> = x.iter().map(|p| 2.0 * *p).collect();
        for s in face_scales(&mesh, &x, &y) {
            assert!((s - 2.0).abs() < 1e-12);
        }
        for d in face_distortions(&mesh, &x, &y) {
            assert!((d - 1.0).abs() < 1e-12);
        }
        let z: Vec<DVec3> = x.iter().map(|p| DVec3::new(3.0 * p.x, p.y, p.z)).collect();
        for s in face_scales(&mesh, &x, &z) {
            assert!((s - 3f64.sqrt()).abs() < 1e-12);
        }
        for d in face_distortions(&mesh, &x, &z) {
            assert!((d - 3.0).abs() < 1e-12);
        }
    }
    /// 200 vertices, vertex i moved by i/1000 along a fixed direction, against
    /// a diagonal of 4: max 199/1000/4 = 4.975 %, mean (199/2)/1000/4 = 2.4875 %,
    /// p99 the 198th smallest (nearest rank: ceil(0.99 * 200) = 198) = 197/1000/4
    /// = 4.925 %.
    #[test]
    fn displacement_of_a_known_field() {
        let x: Vec<DVec3> = (0..200).map(|i| DVec3::new(i as f64, 0.5, -1.0)).collect();
        let dir = DVec3::new(2.0, -1.0, 2.0) / 3.0; // unit length
        let y: Vec<DVec3> = x
            .iter()
            .enumerate()
            .map(|(i, p)| *p + dir * (i as f64 / 1000.0))
            .collect();
        let s = displacement_percent(&x, &y, 4.0);
        assert!((s.max_percent - 4.975).abs() < 1e-12, "{s:?}");
        assert!((s.mean_percent - 2.4875).abs() < 1e-12, "{s:?}");
        assert!((s.p99_percent - 4.925).abs() < 1e-12, "{s:?}");
        // The order of the vertices does not matter; no motion is all zero.
        let (xr, yr): (Vec<DVec3>, Vec<DVec3>) = x.iter().rev().zip(y.iter().rev()).unzip();
        assert_eq!(displacement_percent(&xr, &yr, 4.0), s);
        assert_eq!(
            displacement_percent(&x, &x, 4.0),
            DisplacementStats::default()
        );
        // Nearest rank on few values: with 3 values p99 is the largest.
        let z = [DVec3::ZERO; 3];
        let w = [DVec3::X, DVec3::ZERO, 2.0 * DVec3::Y];
        assert_eq!(displacement_percent(&z, &w, 100.0).p99_percent, 2.0);
    }
    #[test]
    fn similarity_is_one_and_shear_is_not() {
        let a = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let rot = glam::DQuat::from_rotation_z(0.7);
        let b = a.map(|p| 2.5 * (rot * p) + DVec3::new(1.0, 2.0, 3.0));
        assert!((face_ratio(a, b) - 1.0).abs() < 1e-12);
        let c = a.map(|p| DVec3::new(3.0 * p.x, p.y, 0.0));
        assert!((face_ratio(a, c) - 3.0).abs() < 1e-12);
    }
}
