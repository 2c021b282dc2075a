//! Shape optimisation (paper Sec. 2.3, Eqs. 4-7, with handles Eq. 19 and curvature
//! scaling Eq. 21).
//!
//! Unknowns are vertex positions, dof `3 v + r`; the system matrix couples the
//! vertex pairs of the 2-ring. It is kept as `K (x) I3 + sum_i L_i^T C_i L_i`
//! ([`IsoRingSym3`]): every term's Hessian is isotropic except E_l's, whose
//! anisotropic part is one traceless 3x3 `C_i` per mean-value Laplacian row `L_i`.
//! Terms (all dimensionless, so the weights
//! do not depend on the model's size or resolution):
//!
//! * `E_f` (Eq. 4) in the deformation-transfer form `||V (V^c)^-1 - s I||_F^2` that
//!   the paper says it approximates. The fourth frame vertex (Sec. 2.1) enters one
//!   face only and is eliminated in closed form: what remains is
//!   `w_f ||D_f P_f - s_f P_f||_F^2`, the deviation of the face's deformation
//!   gradient (restricted to its current tangent plane `P_f`) from `s_f` times the
//!   identity, with `w_f = A_f^o / sum A^o`. Its Hessian per face is
//!   `2 w_f (G_k . G_l) I3` with `G_k` the gradient of corner k's hat function.
//! * `E_m` (Eqs. 5, 21): `sum_i ||delta_i(x) - c_i delta_i(x^c)||^2 / (4 A_i^o)`,
//!   `delta` the cotangent Laplacian of the input; `c_i` is the area-weighted mean
//!   scale factor around vertex i (pitfall (b)) times the curvature factor of Eq. 21.
//! * `E_l` (Eq. 6): `sum_i a_i ||L(v_i) x L(v_i^c)||^2 / (rms|L(v^c)|^2 h^2)`, mean-value
//!   Laplacian `L` of the input, `a_i = A_i^o / sum A^o`, `h` the mean input edge length.
//! * `E_p` (Eq. 19): `sum_p ||v_p - v_p^t||^2 / (h^2 |P|)`.
//!
//! The energy is translation-invariant on every connected component without
//! handles: one vertex of each such component is held (its increment is zero) and
//! the component is re-centred after each step.

use crate::mesh::topology::Topology;
use crate::mesh::{triangle_area_gradient, Mesh, COT_CAP};
use crate::{Error, Result};
use glam::DVec3;
use rayon::prelude::*;
use solver_cpu::{BlockPcgSolver, IsoRingSym3, ShapeOperatorModel, SparseRows, SpdSolver, SymCsc};
use std::sync::Arc;

/// Faces per thread from which the assembly's sums into `K` and the
/// gradient run on several threads ([`vertex_ranges`]).
const FACES_PER_RANGE: usize = 16_384;

/// Bounds `0 = b_0 < b_1 < ... = n` of the vertex ranges the assembly's
/// sums are cut into: one per rayon thread, or fewer on a small mesh
/// (one range: one thread, as before).
fn vertex_ranges(n: usize, faces: usize) -> Vec<usize> {
    let ranges = rayon::current_num_threads()
        .min(faces / FACES_PER_RANGE)
        .clamp(1, n.max(1));
    (0..=ranges).map(|r| r * n / ranges).collect()
}

/// `data` cut at the ascending offsets `at` (the first 0, the last its
/// length): one slice per range between two offsets.
fn split_at_bounds<T>(data: &mut [T], at: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    let mut parts = Vec::new();
    let mut rest = data;
    let mut done = 0;
    for (i, b) in at.enumerate() {
        if i == 0 {
            continue;
        }
        let (part, tail) = std::mem::take(&mut rest).split_at_mut(b - done);
        parts.push(part);
        rest = tail;
        done = b;
    }
    parts
}

/// Weights of Eq. 7 / Eq. 19.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShapeWeights {
    pub k_f: f64,
    pub k_m: f64,
    pub k_l: f64,
    pub k_p: f64,
}

/// Sparse rows `delta_i = diag_i x_i - sum_j w_ij x_j`.
pub type Laplacian = SparseRows;

/// Cotangent Laplacian (weights `(cot a + cot b) / 2`) of positions `x`. Zero-area,
/// needle and cap faces ([`Mesh::degenerate_faces`]) contribute zero weights.
pub fn cotangent_laplacian(mesh: &Mesh, x: &[DVec3]) -> Laplacian {
    cotangent_laplacian_masked(mesh, x, &mesh.degenerate_faces(x))
}

/// [`cotangent_laplacian`] with the faces flagged in `skip` contributing zero
/// weights (their vertex pairs stay in the pattern). Cotangents are clamped to
/// `[-COT_CAP, COT_CAP]` (libigl's `cot = (l1^2 + l2^2 - l0^2) / (4 area)` is
/// unbounded on needles).
pub fn cotangent_laplacian_masked(mesh: &Mesh, x: &[DVec3], skip: &[bool]) -> Laplacian {
    let (start, faces) = vertex_faces(x.len(), &mesh.faces);
    laplacian_by_corners(mesh, (&start, &faces), false, cotangent_corner(x, skip))
}

/// What one corner of one face adds to a Laplacian ([`laplacian_by_corners`]):
/// `corner(face, corners, k, out)` pushes onto `out` the `(column, weight)`
/// entries corner k's row gets from the face.
trait FaceCorner: Fn(usize, [u32; 3], usize, &mut Vec<(u32, f64)>) + Sync {}

impl<F: Fn(usize, [u32; 3], usize, &mut Vec<(u32, f64)>) + Sync> FaceCorner for F {}

/// A face's corner in [`cotangent_laplacian_masked`].
fn cotangent_corner<'a>(x: &'a [DVec3], skip: &'a [bool]) -> impl FaceCorner + 'a {
    move |fi, f, k, out| {
        let skipped = skip.get(fi).copied().unwrap_or(false);
        // Side m, (f[m], f[m + 1]): half the cotangent of the angle across
        // it, both ways; `None` where a skipped face has no such side.
        let side = |m: usize| {
            let (a, b, c) = (f[m], f[(m + 1) % 3], f[(m + 2) % 3]);
            if skipped && a == b {
                return None; // a collapsed face's side (a, a): nothing to keep
            }
            let cot = if skipped {
                0.0
            } else {
                let e1 = x[a as usize] - x[c as usize];
                let e2 = x[b as usize] - x[c as usize];
                let cr = e1.cross(e2).length();
                if cr > 0.0 {
                    (e1.dot(e2) / cr).clamp(-COT_CAP, COT_CAP)
                } else {
                    0.0
                }
            };
            Some(0.5 * cot)
        };
        // Corner k's row: the sides from it and to it.
        let (next, prev) = ((k + 1) % 3, (k + 2) % 3);
        out.extend(side(k).map(|v| (f[next], v)));
        out.extend(side(prev).map(|v| (f[prev], v)));
    }
}

/// Each vertex's faces, CSR `(start, faces)`, in face order: a face once
/// for each of its distinct corners below `n`. Every face, unlike
/// [`Topology::vertex_faces`] (which leaves duplicate and collapsed faces
/// out, where the Laplacians keep their vertex pairs), and from the faces
/// alone ([`shape_pattern`] has no topology).
fn vertex_faces(n: usize, faces: &[[u32; 3]]) -> (Vec<usize>, Vec<u32>) {
    crate::mesh::topology::compressed_rows(n, |add| {
        for (fi, f) in faces.iter().enumerate() {
            for k in 0..3 {
                if (f[k] as usize) < n && !f[..k].contains(&f[k]) {
                    add(f[k] as usize, fi as u32);
                }
            }
        }
    })
}

/// The Laplacian ([`SparseRows::from_rows`]) of the vertices of
/// `faces_of` ([`vertex_faces`] of `mesh`) whose row i holds what `corner`
/// pushes for each corner at i of each of i's faces, rows on rayon's
/// threads: the same bits on any thread count.
fn laplacian_by_corners(
    mesh: &Mesh,
    (start, faces): (&[usize], &[u32]),
    normalise: bool,
    corner: impl FaceCorner,
) -> Laplacian {
    let n = start.len() - 1;
    let row = |i: usize, out: &mut Vec<(u32, f64)>| {
        for &fi in &faces[start[i]..start[i + 1]] {
            let f = mesh.faces[fi as usize];
            for k in (0..3).filter(|&k| f[k] as usize == i) {
                corner(fi as usize, f, k, out);
            }
        }
    };
    SparseRows::from_rows(n, row, normalise)
}

/// Mean-value Laplacian (Floater), rows normalised to sum 1. Zero-area, needle and
/// cap faces ([`Mesh::degenerate_faces`]) contribute zero weights.
pub fn mean_value_laplacian(mesh: &Mesh, x: &[DVec3]) -> Laplacian {
    mean_value_laplacian_masked(mesh, x, &mesh.degenerate_faces(x))
}

/// [`mean_value_laplacian`] with the faces flagged in `skip` contributing zero
/// weights (their vertex pairs stay in the pattern).
pub fn mean_value_laplacian_masked(mesh: &Mesh, x: &[DVec3], skip: &[bool]) -> Laplacian {
    let (start, faces) = vertex_faces(x.len(), &mesh.faces);
    laplacian_by_corners(mesh, (&start, &faces), true, mean_value_corner(x, skip))
}

/// A face's corner in [`mean_value_laplacian_masked`].
fn mean_value_corner<'a>(x: &'a [DVec3], skip: &'a [bool]) -> impl FaceCorner + 'a {
    move |fi, f, k, out| {
        let skipped = skip.get(fi).copied().unwrap_or(false);
        let (a, b, c) = (f[k], f[(k + 1) % 3], f[(k + 2) % 3]);
        if skipped {
            if a != b {
                out.push((b, 0.0));
            }
            if a != c {
                out.push((c, 0.0));
            }
            return;
        }
        let e1 = x[b as usize] - x[a as usize];
        let e2 = x[c as usize] - x[a as usize];
        let (l1, l2) = (e1.length(), e2.length());
        let denom = l1 * l2 + e1.dot(e2);
        let tan_half = if denom > 0.0 {
            e1.cross(e2).length() / denom
        } else {
            1e6
        };
        if l1 > 0.0 {
            out.push((b, tan_half / l1));
        }
        if l2 > 0.0 {
            out.push((c, tan_half / l2));
        }
    }
}

/// Barycentric vertex areas.
pub fn vertex_areas(mesh: &Mesh, x: &[DVec3]) -> Vec<f64> {
    vertex_areas_of(mesh, x.len(), &mesh.face_areas(x))
}

/// Barycentric vertex areas of `n` vertices, from the face areas `areas`
/// (computed on rayon's threads; the sums in face order, as ever).
fn vertex_areas_of(mesh: &Mesh, n: usize, areas: &[f64]) -> Vec<f64> {
    let mut a = vec![0.0; n];
    for (f, &area) in mesh.faces.iter().zip(areas) {
        let ar = area / 3.0;
        for &v in f {
            a[v as usize] += ar;
        }
    }
    a
}

/// Weight of the springs on the sides of faces without shape weight, relative to
/// a frame term `(k_f + k_m + k_l) / total area`: small enough to change nothing
/// measurable, large enough to keep the shape system positive definite.
pub const NO_WEIGHT_SPRING: f64 = 1e-6;

/// A positional handle vertex (Eq. 19).
#[derive(Debug, Clone, Copy)]
pub struct HandleTarget {
    pub vertex: u32,
    pub target: DVec3,
}

/// Everything about the input that the shape steps reuse, plus the factorization.
pub struct ShapeModel {
    pub n: usize,
    cot: Arc<Laplacian>,
    /// The operator model handed to the solver, and the weights `(k_f, k_m)`
    /// it was made for.
    operator_model: Option<((f64, f64), Arc<ShapeOperatorModel>)>,
    /// Mean-value Laplacian of the input: E_l's rows, shared with the matrix.
    mv: Arc<Laplacian>,
    vertex_area: Vec<f64>,
    face_weight: Vec<f64>,
    /// Faces with no shape weight: zero-area, needle or cap faces of the input
    /// ([`Mesh::degenerate_faces`]) and duplicate faces. They get no frame energy
    /// and no Laplacian weights; instead a spring of weight [`NO_WEIGHT_SPRING`]
    /// on each side keeps their vertices moving with the rest (without it, a
    /// vertex used only by such faces would make the system singular).
    no_weight: Vec<bool>,
    /// The faces without shape weight, ascending: the springs' faces, found
    /// once (every assembly adds their springs).
    spring_faces: Vec<u32>,
    total_area: f64,
    mean_edge: f64,
    /// Unscaled Hessian of E_m (constant: input cotangent weights), isotropic:
    /// one scalar per entry of `K`. Empty when the cotangent and mean-value rows
    /// have the same columns (every mesh without zero-length edges): then each
    /// assembly adds it through `mv_slots` instead of keeping a copy.
    hm: Vec<f64>,
    /// Working matrix (pattern of the 2-ring) while the model holds it; after
    /// an assembly the solver may keep it instead (see [`ShapeModel::matrix`]).
    h: Option<IsoRingSym3>,
    /// Block slots of each face's corner pairs (k, l), l <= k, in the order
    /// (0,0) (1,0) (1,1) (2,0) (2,1) (2,2) (E_f assembly without searching).
    face_slots: Vec<[u32; 6]>,
    /// Block slots of the pairs (p >= q) of each mean-value Laplacian row, in the
    /// order the E_l assembly visits them.
    mv_slot_ptr: Vec<usize>,
    mv_slots: Arc<[u32]>,
    /// For the vertex ranges last asked of [`Self::add_ring_pairs`] (their
    /// bounds), each range's rows of `mv` (ascending) with an entry in it:
    /// the cotangent rows have the same entries wherever `mv_slots` serve
    /// them (`hm` empty).
    rows_by_range: std::sync::Mutex<Option<RowsByRange>>,
    /// The same for the faces: each range's faces (ascending) with a corner
    /// in it, whose E_f terms add to the range's columns of `K`.
    faces_by_range: std::sync::Mutex<Option<RowsByRange>>,
    pub fixed: Vec<bool>,
    /// Components re-centred after each step (those without handles): vertex lists.
    free_components: Vec<Vec<u32>>,
    pub handles: Vec<HandleTarget>,
    solver: Box<dyn SpdSolver>,
    /// Gradient of the energy at the reference point of the last assembly.
    grad: Vec<f64>,
    /// Host seconds of the last assembly ([`Self::assemble`]).
    assembly_seconds: f64,
}

/// Per vertex range (`bounds`, as [`vertex_ranges`] gives them), the rows
/// of a ring matrix (ascending) with an entry in the range: the rows whose
/// pairs' slots may lie in the range's columns of `K` (a lower slot's
/// column is its pair's smaller vertex, an entry of the row).
struct RowsByRange {
    bounds: Vec<usize>,
    rows: Arc<Vec<Vec<u32>>>,
}

impl RowsByRange {
    fn new(rows: &SparseRows, bounds: &[usize]) -> RowsByRange {
        let ranges = bounds.len().saturating_sub(1);
        let range_of = |v: usize| bounds.partition_point(|&b| b <= v).saturating_sub(1);
        let mut by_range = vec![Vec::new(); ranges];
        let mut touched = Vec::new();
        for i in 0..rows.len() {
            touched.clear();
            touched.extend(rows.row(i).map(|(v, _)| range_of(v).min(ranges - 1)));
            touched.sort_unstable();
            touched.dedup();
            for &r in &touched {
                by_range[r].push(i as u32);
            }
        }
        RowsByRange {
            bounds: bounds.to_vec(),
            rows: Arc::new(by_range),
        }
    }

    /// Per range, the faces (ascending) with a corner in it; each range's
    /// list made on a thread of its own.
    fn of_faces(faces: &[[u32; 3]], bounds: &[usize]) -> RowsByRange {
        let by_range = bounds
            .par_windows(2)
            .map(|r| {
                let mine = |v: u32| (r[0]..r[1]).contains(&(v as usize));
                (0..faces.len() as u32)
                    .filter(|&f| faces[f as usize].iter().any(|&v| mine(v)))
                    .collect()
            })
            .collect();
        RowsByRange {
            bounds: bounds.to_vec(),
            rows: Arc::new(by_range),
        }
    }
}

/// `cache`'s lists where they were made for `bounds`, else `make(bounds)`'s,
/// kept in it.
fn cached_by_range(
    cache: &std::sync::Mutex<Option<RowsByRange>>,
    bounds: &[usize],
    make: impl FnOnce(&[usize]) -> RowsByRange,
) -> Arc<Vec<Vec<u32>>> {
    let mut cached = cache.lock().unwrap_or_else(|e| e.into_inner());
    match cached.as_ref() {
        Some(r) if r.bounds == bounds => r.rows.clone(),
        _ => {
            let r = make(bounds);
            let made = r.rows.clone();
            *cached = Some(r);
            made
        }
    }
}

/// Where [`ShapeModel::hessian_terms`] puts the terms.
struct Terms<'a> {
    /// `K`, on the 2-ring pattern: its values are overwritten.
    k: &'a mut SymCsc,
    /// E_l's whole term in the `C_i` (else its isotropic part in `K`).
    whole_ring: bool,
    /// E_m's constant Hessian is named to the solver, not summed into `K`.
    square_named: bool,
    /// E_l's `C_i`, one per vertex (overwritten); `None`: not made.
    ring_c: Option<&'a mut [[f64; 6]]>,
    /// The scale factors `s` (per face), the curvature targets `c` (per
    /// vertex) and the gradient to write (overwritten); `None`: not made.
    gradient: Option<(&'a [f64], &'a [f64], &'a mut [f64])>,
}

impl ShapeModel {
    pub fn new(mesh: &Mesh, topo: &Topology, handles: Vec<HandleTarget>) -> Result<Self> {
        Self::with_solver(mesh, topo, handles, Box::new(BlockPcgSolver::new()))
    }

    pub fn with_solver(
        mesh: &Mesh,
        topo: &Topology,
        handles: Vec<HandleTarget>,
        solver: Box<dyn SpdSolver>,
    ) -> Result<Self> {
        Self::with_solver_and_pattern(mesh, topo, handles, solver, None)
    }

    /// As [`ShapeModel::with_solver`], its 2-ring pattern taken from
    /// `pattern` where that holds one already: [`shape_pattern`] of the same
    /// mesh, made on another thread since the start (the pipeline's), not
    /// made again here. Where it holds none yet, the pattern is made here,
    /// and given up for the thread's should that come meanwhile (its `ready`
    /// set): not waited for, as that thread's pattern can sit behind other
    /// work in rayon's pool (homer 1.2M, 2 threads: a wait of 2.44 s, where
    /// making it takes 0.3-0.4 s).
    pub fn with_solver_and_pattern(
        mesh: &Mesh,
        topo: &Topology,
        handles: Vec<HandleTarget>,
        solver: Box<dyn SpdSolver>,
        pattern: Option<SharedPattern>,
    ) -> Result<Self> {
        let x = &mesh.positions;
        let n = x.len();
        let t_setup = std::time::Instant::now();
        let mut no_weight = mesh.degenerate_faces(x);
        for &(f, _) in &topo.duplicate_faces {
            no_weight[f as usize] = true;
        }
        // Both Laplacians from one list of each vertex's faces: the
        // topology's where it leaves no face out (then the same list), else
        // made here.
        let (cot, mv, pool_wait) = {
            let made;
            let faces_of: (&[usize], &[u32]) = if topo.collapsed_faces.is_empty()
                && topo.duplicate_faces.is_empty()
                && topo.vf_start.len() == n + 1
            {
                (&topo.vf_start, &topo.vf_index)
            } else {
                made = vertex_faces(n, &mesh.faces);
                (&made.0, &made.1)
            };
            crate::ordered::join_timed(
                || {
                    let corner = cotangent_corner(x, &no_weight);
                    Arc::new(laplacian_by_corners(mesh, faces_of, false, corner))
                },
                || {
                    let corner = mean_value_corner(x, &no_weight);
                    Arc::new(laplacian_by_corners(mesh, faces_of, true, corner))
                },
            )
        };
        let laplacians_seconds = t_setup.elapsed().as_secs_f64();
        let areas = mesh.face_areas(x);
        let vertex_area = vertex_areas_of(mesh, n, &areas);
        let total_area: f64 = areas.iter().sum();
        let face_weight: Vec<f64> = areas
            .iter()
            .zip(&no_weight)
            .map(|(a, &skip)| if skip { 0.0 } else { a / total_area })
            .collect();
        let mean_edge = if topo.edges.is_empty() {
            1.0
        } else {
            // The lengths on rayon's threads, their sum in edge order.
            topo.edges
                .par_iter()
                .map(|e| (x[e[0] as usize] - x[e[1] as usize]).length())
                .collect::<Vec<f64>>()
                .iter()
                .sum::<f64>()
                / topo.edges.len() as f64
        };

        let t_pattern = std::time::Instant::now();
        // The other thread's pattern where it has come, else this one's,
        // given up for the other's where that comes meanwhile.
        let fits = |p: &Arc<(Vec<usize>, Vec<usize>)>| {
            p.0.len() == n + 1 && p.0.last() == Some(&p.1.len())
        };
        let never = std::sync::atomic::AtomicBool::new(false);
        let (shared, own) = match &pattern {
            Some(share) => match share.pattern.try_recv() {
                Ok(p) => (Some(p), None),
                Err(_) => match two_ring_pattern(&cot.start, &cot.idx, &share.ready) {
                    Some(own) => (None, Some(own)),
                    None => (share.pattern.recv().ok(), None),
                },
            },
            None => (None, two_ring_pattern(&cot.start, &cot.idx, &never)),
        };
        let shared = shared.filter(fits);
        let from_thread = shared.is_some();
        let (col_ptr, row_idx) = match (shared, own) {
            (Some(p), _) => (p.0.clone(), p.1.clone()),
            (None, Some(own)) => own,
            // Given up for a pattern that did not fit (not the pipeline's).
            (None, None) => {
                two_ring_pattern(&cot.start, &cot.idx, &never).expect("a pattern not given up")
            }
        };
        let mut h = IsoRingSym3::new(n, col_ptr, row_idx, mv.clone());
        let pattern_seconds = t_pattern.elapsed().as_secs_f64();
        if from_thread {
            log::debug!(
                "shape model: its pattern from the shape pattern's thread (copied in \
                 {pattern_seconds:.3} s)"
            );
        }
        // E_m's Hessian is isotropic ((c c^T) (x) I3): one scalar per block slot.
        let same_rings = cot.start == mv.start && cot.idx == mv.idx;
        let hm = if same_rings {
            Vec::new()
        } else {
            em_hessian(&cot, &vertex_area, &h)
        };
        let t_slots = std::time::Instant::now();
        let slot = |a: u32, b: u32| -> u32 {
            h.iso
                .slot(a as usize, b as usize)
                .expect("pair inside the 2-ring pattern") as u32
        };
        let face_slots: Vec<[u32; 6]> = mesh
            .faces
            .par_iter()
            .map(|t| {
                [
                    slot(t[0], t[0]),
                    slot(t[1], t[0]),
                    slot(t[1], t[1]),
                    slot(t[2], t[0]),
                    slot(t[2], t[1]),
                    slot(t[2], t[2]),
                ]
            })
            .collect();
        // Row i's pairs (p, q), p >= q, in `mv.row(i)`'s order, made per
        // chunk of rows on rayon's threads.
        let mut mv_slot_ptr = Vec::with_capacity(n + 1);
        mv_slot_ptr.push(0);
        for i in 0..n {
            let d = mv.start[i + 1] - mv.start[i] + 1;
            mv_slot_ptr.push(mv_slot_ptr[i] + d * (d + 1) / 2);
        }
        // Written in place in their shared storage: a `Vec` turned into an
        // `Arc` is copied (0.66 s for homer 4.3M's 240 MB, 2 threads).
        // SAFETY: zeroed memory is a valid `u32`.
        let mut mv_slots: Arc<[u32]> =
            unsafe { Arc::new_zeroed_slice(mv_slot_ptr[n]).assume_init() };
        {
            use rayon::prelude::*;
            let slots = Arc::get_mut(&mut mv_slots).expect("the slots' new storage is not shared");
            let chunks = solver_cpu::row_groups_mut(slots, n, |i| mv_slot_ptr[i], 4096);
            chunks.into_par_iter().for_each(|(rows, chunk)| {
                let mut out = chunk.iter_mut();
                for i in rows {
                    for (p, _) in mv.row(i) {
                        for (q, _) in mv.row(i) {
                            if p >= q {
                                *out.next().unwrap() = slot(p as u32, q as u32);
                            }
                        }
                    }
                }
            });
        }
        // The same slots serve a solver that adds the rings' pairs itself.
        h.ring_slots = Some(mv_slots.clone());
        log::debug!(
            "shape model: {} vertices, {} blocks, set up in {:.3} s (its Laplacians {:.3} s, \
             {pool_wait:.3} s of it before rayon's threads took them up; pattern \
             {pattern_seconds:.3} s, slots {:.3} s), resident {:.0} MiB",
            n,
            h.iso.row_idx.len(),
            t_setup.elapsed().as_secs_f64(),
            laplacians_seconds,
            t_slots.elapsed().as_secs_f64(),
            crate::memory::resident_memory_mb()
        );

        // Held vertices: unreferenced ones, and one per component without handles.
        let t_held = std::time::Instant::now();
        let mut referenced = vec![false; n];
        for f in &mesh.faces {
            for &v in f {
                referenced[v as usize] = true;
            }
        }
        let mut fixed: Vec<bool> = referenced.iter().map(|r| !r).collect();
        let (label, count) = (&topo.vertex_component, topo.components);
        let mut has_handle = vec![false; count];
        for hd in &handles {
            has_handle[label[hd.vertex as usize] as usize] = true;
        }
        let mut free_components: Vec<Vec<u32>> = vec![Vec::new(); count];
        for v in 0..n {
            if referenced[v] {
                free_components[label[v] as usize].push(v as u32);
            }
        }
        let mut free = Vec::new();
        for (c, verts) in free_components.into_iter().enumerate() {
            if !has_handle[c] && !verts.is_empty() {
                fixed[verts[0] as usize] = true;
                free.push(verts);
            }
        }
        log::debug!(
            "shape model: held vertices and components in {:.3} s",
            t_held.elapsed().as_secs_f64()
        );
        let mut model = ShapeModel {
            n,
            cot,
            operator_model: None,
            mv,
            vertex_area,
            face_weight,
            spring_faces: (0..no_weight.len() as u32)
                .filter(|&f| no_weight[f as usize])
                .collect(),
            no_weight,
            total_area,
            mean_edge,
            hm,
            h: Some(h),
            face_slots,
            mv_slot_ptr,
            mv_slots,
            rows_by_range: Default::default(),
            faces_by_range: Default::default(),
            fixed,
            free_components: free,
            handles,
            solver,
            grad: vec![0.0; 3 * n],
            assembly_seconds: 0.0,
        };
        // Its matrices' pattern is known from now on: a solver may set up
        // what depends on it alone while the first values are made.
        if let Some(h) = model.h.as_ref() {
            model.solver.prepare_shape_pattern(h, &model.fixed);
        }
        Ok(model)
    }

    /// Mean input edge length.
    pub fn mean_edge(&self) -> f64 {
        self.mean_edge
    }

    /// Assemble the Hessian and the gradient at the reference positions `xc`
    /// for scale factors `s` (per face) and curvature targets `c` (per vertex),
    /// then factor the Hessian.
    pub fn assemble_and_factor(
        &mut self,
        mesh: &Mesh,
        xc: &[DVec3],
        s: &[f64],
        c: &[f64],
        w: &ShapeWeights,
    ) -> Result<()> {
        self.assemble(mesh, xc, s, c, w)?;
        self.hand_over(w)
    }

    /// The first half of [`Self::assemble_and_factor`]: the Hessian's terms
    /// and the gradient summed on the host and kept, for
    /// [`Self::hand_over`] to give the solver. Between the two the solver's
    /// state must not change what it reads apart (a factor made ahead may
    /// be adopted: the kind's set-up is at the hand-over).
    pub fn assemble(
        &mut self,
        mesh: &Mesh,
        xc: &[DVec3],
        s: &[f64],
        c: &[f64],
        w: &ShapeWeights,
    ) -> Result<()> {
        let t0 = std::time::Instant::now();
        let mut h_owned = match self.h.take() {
            Some(h) => h,
            None => self.solver.take_shape_matrix().ok_or_else(|| {
                Error::Internal("the shape matrix was not handed back by the solver".into())
            })?,
        };
        let h = &mut h_owned;
        // Where the solver no longer reads K apart (its preconditioner of this
        // kind is made), E_l's whole term goes into the rings' C_i (below),
        // and E_m's constant Hessian may be left to the solver, named by its
        // operator model instead of scattered into K (the same matrix).
        let whole_ring = !self.solver.wants_isotropic_part();
        h.laplacian_square = if whole_ring
            && w.k_m > 0.0
            && self.hm.is_empty()
            && self.solver.adds_laplacian_square()
        {
            self.operator_model(w)
        } else {
            None
        };
        let mut grad = std::mem::take(&mut self.grad);
        let square_named = h.laplacian_square.is_some();
        self.hessian_terms(
            mesh,
            xc,
            w,
            Terms {
                k: &mut h.iso,
                whole_ring,
                square_named,
                ring_c: Some(&mut h.ring_c),
                gradient: Some((s, c, &mut grad)),
            },
        );
        self.grad = grad;
        self.h = Some(h_owned);
        self.assembly_seconds = t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// The matrix [`Self::assemble`] made, given to the solver (which
    /// uploads or factors it): the second half of
    /// [`Self::assemble_and_factor`].
    pub fn hand_over(&mut self, w: &ShapeWeights) -> Result<()> {
        let t1 = std::time::Instant::now();
        let h_owned = self.h.take().ok_or_else(|| {
            Error::Internal("no assembled shape matrix to hand to the solver".into())
        })?;
        let model = self.operator_model(w);
        self.solver.set_shape_model(model);
        self.h = self.solver.prepare_shape_owned(h_owned, &self.fixed)?;
        log::debug!(
            "shape system: assembly {:.3} s, {} {:.3} s",
            self.assembly_seconds,
            self.solver.name(),
            t1.elapsed().as_secs_f64()
        );
        Ok(())
    }

    /// [`vertex_ranges`] for `faces`, and each range's rows of `mv` with an
    /// entry in it ([`RowsByRange`]), made once for those ranges.
    fn rows_by_range(&self, faces: usize) -> (Vec<usize>, Arc<Vec<Vec<u32>>>) {
        let bounds = vertex_ranges(self.n, faces);
        let rows = cached_by_range(&self.rows_by_range, &bounds, |b| {
            RowsByRange::new(&self.mv, b)
        });
        (bounds, rows)
    }

    /// [`vertex_mean_scale`] on rayon's threads, by the vertex ranges of
    /// the assembly's sums (`faces_by_range`): the same values to the bit.
    /// On one thread it took 0.03-0.14 s of each outer iteration at homer
    /// 4.3M (the H200's host and the development machine).
    pub fn vertex_mean_scale(&self, mesh: &Mesh, areas: &[f64], s: &[f64]) -> Vec<f64> {
        let (bounds, faces_of) = self.faces_by_range(&mesh.faces);
        let mut c = vec![0.0; self.n];
        split_at_bounds(&mut c, bounds.iter().copied())
            .into_par_iter()
            .zip(bounds.par_windows(2))
            .zip(faces_of.par_iter())
            .for_each(|((out, range), faces)| {
                vertex_mean_scale_of_range(mesh, areas, s, range[0], faces.iter().copied(), out)
            });
        c
    }

    /// [`vertex_ranges`] for `faces`, and each range's faces with a corner
    /// in it ([`RowsByRange::of_faces`]), made once for those ranges.
    fn faces_by_range(&self, faces: &[[u32; 3]]) -> (Vec<usize>, Arc<Vec<Vec<u32>>>) {
        let bounds = vertex_ranges(self.n, faces.len());
        let rows = cached_by_range(&self.faces_by_range, &bounds, |b| {
            RowsByRange::of_faces(faces, b)
        });
        (bounds, rows)
    }

    /// Adds `weight(i) R_ip R_iq` into `K`'s slot of each pair `p >= q` of
    /// each row `i` of `rows` (E_m's cotangent or E_l's mean-value rows: the
    /// pairs' slots are `mv_slots`), rows with weight 0 left out. On rayon's
    /// threads by the vertex ranges of the E_f sums ([`vertex_ranges`] for
    /// `faces`): each range's columns of `K` take their terms from the rows
    /// with an entry in the range, in row order, so every sum is the one
    /// a single thread makes. One after the other, the two such passes took
    /// about 0.3 s of every `K` assembled apart at homer 1.2M on an H200's
    /// host (inferred: the CPU backend's assemblies, 0.36-0.43 s, against
    /// the GPU path's 0.115 s without them).
    fn add_ring_pairs(
        &self,
        k: &mut SymCsc,
        rows: &SparseRows,
        faces: usize,
        weight: impl Fn(usize) -> f64 + Sync,
    ) {
        let (bounds, by_range) = self.rows_by_range(faces);
        let col_ptr = &k.col_ptr;
        let parts = split_at_bounds(&mut k.values, bounds.iter().map(|&b| col_ptr[b]));
        let (ptr, slots) = (&self.mv_slot_ptr, &self.mv_slots);
        parts
            .into_par_iter()
            .zip(bounds.par_windows(2))
            .zip(by_range.par_iter())
            .for_each(|((values, range), mine)| {
                let base = col_ptr[range[0]];
                for &i in mine {
                    let i = i as usize;
                    let m = weight(i);
                    if m == 0.0 {
                        continue;
                    }
                    let mut at = slots[ptr[i]..].iter();
                    for (p, cp) in rows.row(i) {
                        for (q, cq) in rows.row(i) {
                            if p >= q {
                                let s = *at.next().unwrap() as usize;
                                if let Some(v) = s.checked_sub(base).and_then(|s| values.get_mut(s))
                                {
                                    *v += m * cp * cq;
                                }
                            }
                        }
                    }
                }
            });
    }

    /// The Hessian's terms for the weights `w` at the reference positions
    /// `xc` (Eqs. 4-6, 19, and the springs of faces without shape weight),
    /// into `t` (see [`Terms`]): `K`'s values (overwritten), E_l's `C_i`
    /// and the gradient where asked for. One home for every term's sums, in
    /// one order, whether for a solve or for a factor made ahead.
    fn hessian_terms(&self, mesh: &Mesh, xc: &[DVec3], w: &ShapeWeights, t: Terms<'_>) {
        let n = self.n;
        let Terms {
            k,
            whole_ring,
            square_named,
            mut ring_c,
            mut gradient,
        } = t;
        if self.hm.is_empty() {
            k.values.par_iter_mut().for_each(|v| *v = 0.0);
            // E_m's Hessian sum_i 2 m_i delta_i^T delta_i, on mv's pair slots.
            if w.k_m > 0.0 && !square_named {
                let area = &self.vertex_area;
                let m = |i: usize| match area[i] > 0.0 {
                    true => 2.0 * w.k_m / (4.0 * area[i]),
                    false => 0.0,
                };
                self.add_ring_pairs(k, &self.cot, mesh.faces.len(), m);
            }
        } else {
            for (o, &m) in k.values.iter_mut().zip(&self.hm) {
                *o = w.k_m * m;
            }
        }
        if let Some(ring_c) = ring_c.as_deref_mut() {
            ring_c.par_iter_mut().for_each(|c| *c = [0.0; 6]);
        }
        if let Some((_, _, grad)) = gradient.as_mut() {
            grad.par_iter_mut().for_each(|g| *g = 0.0);
        }

        // Faces without shape weight: springs on their sides, zero gradient at xc.
        let spring = NO_WEIGHT_SPRING * 2.0 * (w.k_f + w.k_m + w.k_l).max(1e-300)
            / self.total_area.max(f64::MIN_POSITIVE);
        for &f in &self.spring_faces {
            let (t, slots) = (mesh.faces[f as usize], &self.face_slots[f as usize]);
            for (a, b) in [(1usize, 0usize), (2, 0), (2, 1)] {
                if t[a] == t[b] {
                    continue;
                }
                k.values[slots[a * (a + 1) / 2 + a] as usize] += spring;
                k.values[slots[b * (b + 1) / 2 + b] as usize] += spring;
                k.values[slots[a * (a + 1) / 2 + b] as usize] -= spring;
            }
        }

        // E_f (Eq. 4, fourth vertex eliminated), on rayon's threads: the
        // vertices are cut into ranges, and each range's columns of `K` and
        // entries of the gradient are added to by one thread, from the faces
        // with a corner in the range (`faces_by_range`), face after face, so
        // each sum is the same, in the same order, on any number of threads.
        // A face across ranges has its terms computed by each of them.
        let (no_weight, face_weight) = (&self.no_weight, &self.face_weight);
        let (bounds, faces_of) = self.faces_by_range(&mesh.faces);
        let parts = split_at_bounds(&mut k.values, bounds.iter().map(|&b| k.col_ptr[b]));
        let grad_parts = gradient
            .as_mut()
            .map(|(s, _, grad)| (*s, split_at_bounds(grad, bounds.iter().map(|&b| 3 * b))));
        let (s, grad_parts): (Option<&[f64]>, Vec<Option<&mut [f64]>>) = match grad_parts {
            Some((s, g)) => (Some(s), g.into_iter().map(Some).collect()),
            None => (None, (0..parts.len()).map(|_| None).collect()),
        };
        let face_slots = &self.face_slots;
        let col_ptr = &k.col_ptr;
        parts
            .into_par_iter()
            .zip(grad_parts)
            .zip(bounds.par_windows(2))
            .zip(faces_of.par_iter())
            .for_each(|(((values, mut grad), range), faces)| {
                let (lo, hi) = (range[0], range[1]);
                let base = col_ptr[lo];
                let mine = |v: u32| (lo..hi).contains(&(v as usize));
                for &f in faces {
                    let f = f as usize;
                    if no_weight[f] {
                        continue;
                    }
                    // The gradient of log(area): d area / d corner over the area.
                    let Some((a2, da)) = triangle_area_gradient(mesh.corners(xc, f)) else {
                        continue;
                    };
                    let (g, wf) = (da.map(|d| d * 2.0 / a2), 2.0 * w.k_f * face_weight[f]);
                    let t = mesh.faces[f];
                    let slots = &face_slots[f];
                    for kk in 0..3 {
                        for l in 0..=kk {
                            let (a, b) = (t[kk], t[l]);
                            // A lower slot's column is its smaller index.
                            if !mine(a.min(b)) {
                                continue;
                            }
                            let mut v = wf * g[kk].dot(g[l]);
                            if a == b && kk != l {
                                v *= 2.0;
                            }
                            values[slots[kk * (kk + 1) / 2 + l] as usize - base] += v;
                        }
                        if let (Some(s), Some(grad), true) = (s, grad.as_mut(), mine(t[kk])) {
                            let gk = wf * (1.0 - s[f]) * g[kk];
                            let i = 3 * (t[kk] as usize - lo);
                            grad[i] += gk.x;
                            grad[i + 1] += gk.y;
                            grad[i + 2] += gk.z;
                        }
                    }
                }
            });

        // E_m (Eqs. 5, 21): gradient at xc; the Hessian is the constant part
        // above (or the solver's).
        if let (true, Some((_, c, grad))) = (w.k_m > 0.0, gradient.as_mut()) {
            // Each vertex's residual on rayon's threads, added in vertex order.
            let (vertex_area, cot) = (&self.vertex_area, &self.cot);
            let residual: Vec<DVec3> = (0..n)
                .into_par_iter()
                .map(|i| {
                    if vertex_area[i] <= 0.0 {
                        DVec3::ZERO
                    } else {
                        (1.0 - c[i]) * cot.apply(xc, i)
                    }
                })
                .collect();
            // Added by vertex range on rayon's threads where the cotangent
            // rows have the mean-value rows' entries (`hm` empty: the rows
            // by range serve both), each entry's terms in row order as on one
            // thread; else one row after the other.
            let add = |grad: &mut [f64], lo: usize, rows: &mut dyn Iterator<Item = usize>| {
                for i in rows {
                    let r = residual[i];
                    if r == DVec3::ZERO {
                        continue;
                    }
                    let m = 1.0 / (4.0 * vertex_area[i]);
                    for (j, cj) in cot.row(i) {
                        let Some(j) = j.checked_sub(lo).filter(|&j| 3 * j < grad.len()) else {
                            continue;
                        };
                        let g = 2.0 * w.k_m * m * cj * r;
                        grad[3 * j] += g.x;
                        grad[3 * j + 1] += g.y;
                        grad[3 * j + 2] += g.z;
                    }
                }
            };
            if self.hm.is_empty() {
                let (bounds, by_range) = self.rows_by_range(mesh.faces.len());
                let parts = split_at_bounds(grad, bounds.iter().map(|&b| 3 * b));
                parts
                    .into_par_iter()
                    .zip(bounds.par_windows(2))
                    .zip(by_range.par_iter())
                    .for_each(|((part, range), mine)| {
                        add(part, range[0], &mut mine.iter().map(|&i| i as usize))
                    });
            } else {
                add(grad, 0, &mut (0..n));
            }
        }

        // E_l (Eq. 6): zero gradient at xc, Hessian sum_i 2 a_i L_i^T ([d]x^T [d]x) L_i
        // with [d]x^T [d]x = |d|^2 I - d d^T = (2/3)|d|^2 I + ((1/3)|d|^2 I - d d^T):
        // the isotropic part goes to K, the traceless rest is the ring's C_i.
        // With `whole_ring`, all of it is the ring's C_i: the same matrix,
        // without the scatter of every ring pair into K's slots.
        if w.k_l > 0.0 && (ring_c.is_some() || !whole_ring) {
            let d = self.mv.apply_all(xc);
            let ms: f64 = (0..n)
                .filter(|&i| self.vertex_area[i] > 0.0)
                .map(|i| d[i].length_squared())
                .sum::<f64>()
                / n.max(1) as f64;
            if ms > 0.0 {
                let norm = 2.0 * w.k_l / (self.total_area * ms * self.mean_edge * self.mean_edge);
                // The isotropic part, (2/3) a_i |d_i|^2 L_i^T L_i, into K.
                if !whole_ring {
                    let area = &self.vertex_area;
                    let iso = |i: usize| match area[i] * norm > 0.0 {
                        true => area[i] * norm * 2.0 * (d[i].length_squared() / 3.0),
                        false => 0.0,
                    };
                    self.add_ring_pairs(k, &self.mv, mesh.faces.len(), iso);
                }
                // Each ring's C_i, on rayon's threads (one value each).
                if let Some(ring_c) = ring_c {
                    let area = &self.vertex_area;
                    ring_c.par_iter_mut().enumerate().for_each(|(i, c)| {
                        let a = area[i] * norm;
                        if a <= 0.0 {
                            return;
                        }
                        let di = d[i];
                        let dd = di.length_squared();
                        // C_i's diagonal: all of |d|^2 in the ring, or its third.
                        let on_diag = if whole_ring { dd } else { dd / 3.0 };
                        *c = [
                            a * (on_diag - di.x * di.x),
                            a * (on_diag - di.y * di.y),
                            a * (on_diag - di.z * di.z),
                            -a * di.x * di.y,
                            -a * di.x * di.z,
                            -a * di.y * di.z,
                        ];
                    });
                }
            }
        }

        // E_p (Eq. 19).
        if !self.handles.is_empty() && w.k_p > 0.0 {
            let beta = 2.0 * w.k_p / (self.mean_edge * self.mean_edge * self.handles.len() as f64);
            for hd in &self.handles {
                let v = hd.vertex as usize;
                // The diagonal entry comes first in its column.
                k.values[k.col_ptr[v]] += beta;
                if let Some((_, _, grad)) = gradient.as_mut() {
                    let g = beta * (xc[v] - hd.target);
                    grad[3 * v] += g.x;
                    grad[3 * v + 1] += g.y;
                    grad[3 * v + 2] += g.z;
                }
            }
        }

        if let Some((_, _, grad)) = gradient.as_mut() {
            grad.par_chunks_mut(3)
                .zip(&self.fixed)
                .filter(|(_, &held)| held)
                .for_each(|(g, _)| g.fill(0.0));
        }
    }

    /// `K`, the isotropic part of the Hessian for the weights `w` at `xc`
    /// with every isotropic term in it and the held vertices' rows and
    /// columns made identity: the matrix a shape kind's Cholesky
    /// preconditioner factors, as that kind's first assembly at `xc` gives
    /// it to the solver ([`SpdSolver::isotropic_factorer`]).
    pub fn isotropic_part(&self, mesh: &Mesh, xc: &[DVec3], w: &ShapeWeights) -> SymCsc {
        let pattern = &self.matrix().iso;
        let mut k = SymCsc {
            n: pattern.n,
            col_ptr: pattern.col_ptr.clone(),
            row_idx: pattern.row_idx.clone(),
            values: vec![0.0; pattern.row_idx.len()],
        };
        let terms = Terms {
            k: &mut k,
            whole_ring: false,
            square_named: false,
            ring_c: None,
            gradient: None,
        };
        self.hessian_terms(mesh, xc, w, terms);
        k.set_held_identity(&self.fixed);
        k
    }

    /// The model `K ~ S Mt^-1 S + c S` of the Hessian's isotropic part for
    /// the weights `w` ([`ShapeOperatorModel`]; made once per pair `(k_f,
    /// k_m)`); `None` without E_m.
    fn operator_model(&mut self, w: &ShapeWeights) -> Option<Arc<ShapeOperatorModel>> {
        if w.k_m <= 0.0 || self.total_area <= 0.0 {
            return None;
        }
        let key = (w.k_f, w.k_m);
        if let Some((k, m)) = &self.operator_model {
            if *k == key {
                return Some(m.clone());
            }
        }
        let m = Arc::new(ShapeOperatorModel {
            laplacian: self.cot.clone(),
            mt: self.vertex_area.iter().map(|a| 2.0 * a / w.k_m).collect(),
            c: 2.0 * w.k_f.max(0.0) / self.total_area,
        });
        self.operator_model = Some((key, m.clone()));
        Some(m)
    }

    /// [`ShapeModel::assemble_and_factor`] at `x`; with `affine`, the solver
    /// is given the vertex positions for the factorization where it may read
    /// them ([`SpdSolver::wants_vertex_positions`]: an iterative backend's
    /// AMG then takes the vertices' affine motions as near-null space), and
    /// they are cleared after it.
    pub fn assemble_with_positions(
        &mut self,
        mesh: &Mesh,
        x: &[DVec3],
        s: &[f64],
        c: &[f64],
        w: &ShapeWeights,
        affine: bool,
    ) -> Result<()> {
        self.assemble(mesh, x, s, c, w)?;
        self.hand_over_with_positions(x, w, affine)
    }

    /// [`Self::hand_over`] of the matrix [`Self::assemble`] made at `x`,
    /// with the positions as [`Self::assemble_with_positions`] gives them.
    pub fn hand_over_with_positions(
        &mut self,
        x: &[DVec3],
        w: &ShapeWeights,
        affine: bool,
    ) -> Result<()> {
        if affine && self.solver.wants_vertex_positions() {
            let positions: Vec<[f64; 3]> = x.iter().map(|p| p.to_array()).collect();
            self.solver().set_vertex_positions(&positions);
        }
        let done = self.hand_over(w);
        self.solver().set_vertex_positions(&[]);
        done
    }

    /// The assembled Hessian of the last assembly and the held vertices (for
    /// benchmarks and solver tests on the real shape system).
    pub fn system(&self) -> (&IsoRingSym3, &[bool]) {
        (self.matrix(), &self.fixed)
    }

    /// The assembled Hessian, wherever it is kept.
    pub fn matrix(&self) -> &IsoRingSym3 {
        self.h
            .as_ref()
            .or_else(|| self.solver.shape_matrix())
            .expect("the shape matrix is held by the model or its solver")
    }

    /// Gradient of the energy at the reference positions of the last assembly.
    pub fn reference_gradient(&self) -> &[f64] {
        &self.grad
    }

    /// Energy (up to a constant) at `xref + dx`: `1/2 dx^T H dx + g0 . dx`,
    /// held dofs left out (`dx` is zero there). 0 at `dx = 0` with no
    /// product made; else `H`'s quadratic form on rayon's threads
    /// ([`IsoRingSym3::quadratic_form`]), the same on any number of them.
    pub fn energy(&self, dx: &[f64]) -> f64 {
        if dx.iter().all(|&v| v == 0.0) {
            return 0.0;
        }
        let held = |i: usize| self.fixed[i / 3];
        let held_moved = (0..self.n).any(|v| self.fixed[v] && dx[3 * v..3 * v + 3] != [0.0; 3]);
        let free: Vec<f64>;
        let dx_free = if held_moved {
            free = (0..dx.len())
                .map(|i| if held(i) { 0.0 } else { dx[i] })
                .collect();
            &free[..]
        } else {
            dx
        };
        let linear: f64 = dx_free.iter().zip(&self.grad).map(|(d, g)| g * d).sum();
        0.5 * self.matrix().quadratic_form(dx_free) + linear
    }

    /// Gradient at `xref + dx`: `H dx + g0` (held dofs zero); `g0` with no
    /// product made at `dx = 0` (the fine-tune's first step).
    pub fn gradient_at(&self, dx: &[f64]) -> Vec<f64> {
        let mut g = vec![0.0; dx.len()];
        if dx.iter().any(|&v| v != 0.0) {
            self.matrix().mul_vec(dx, &mut g);
        }
        let (fixed, grad) = (&self.fixed, &self.grad);
        g.par_iter_mut().enumerate().for_each(|(i, g)| {
            *g = if fixed[i / 3] { 0.0 } else { *g + grad[i] };
        });
        g
    }

    /// Unconstrained minimiser (Eq. 7 / 19): `xc + dx` with `H dx = -g0`, then
    /// each handle-free component re-centred on its previous centroid.
    pub fn solve_unconstrained(&mut self, xc: &[DVec3]) -> Result<Vec<DVec3>> {
        let mut rhs: Vec<f64> = self.grad.iter().map(|g| -g).collect();
        self.solver.solve_in_place(&mut rhs, 1)?;
        let mut x: Vec<DVec3> = (0..self.n)
            .map(|v| {
                if self.fixed[v] {
                    xc[v]
                } else {
                    xc[v] + DVec3::new(rhs[3 * v], rhs[3 * v + 1], rhs[3 * v + 2])
                }
            })
            .collect();
        self.recentre(xc, &mut x);
        Ok(x)
    }

    /// Translate each handle-free component so that its vertex centroid is unchanged.
    pub fn recentre(&self, before: &[DVec3], after: &mut [DVec3]) {
        for comp in &self.free_components {
            let mut d = DVec3::ZERO;
            for &v in comp {
                d += before[v as usize] - after[v as usize];
            }
            d /= comp.len() as f64;
            for &v in comp {
                after[v as usize] += d;
            }
        }
    }

    /// Access the prepared solver (for the constrained steps of Eq. 8).
    pub fn solver(&mut self) -> &mut dyn SpdSolver {
        self.solver.as_mut()
    }
}

/// E_m's unscaled Hessian `sum_i 2 delta_i^T delta_i / (4 A_i)`, one value per
/// entry of `h`'s `K`.
fn em_hessian(cot: &Laplacian, vertex_area: &[f64], h: &IsoRingSym3) -> Vec<f64> {
    let mut hm = vec![0.0; h.iso.row_idx.len()];
    for i in 0..cot.len() {
        if vertex_area[i] <= 0.0 {
            continue;
        }
        let m = 1.0 / (4.0 * vertex_area[i]);
        for (a, ca) in cot.row(i) {
            for (b, cb) in cot.row(i) {
                if a >= b {
                    let k = h.iso.slot(a, b).expect("pair inside the 2-ring pattern");
                    hm[k] += 2.0 * m * ca * cb;
                }
            }
        }
    }
    hm
}

/// A [`shape_pattern`] made on another thread, for
/// [`ShapeModel::with_solver_and_pattern`]: its `(col_ptr, row_idx)`, shared,
/// and a flag the thread sets once it has sent it.
pub struct SharedPattern {
    pub pattern: std::sync::mpsc::Receiver<Arc<(Vec<usize>, Vec<usize>)>>,
    pub ready: Arc<std::sync::atomic::AtomicBool>,
}

/// The shape systems' pattern (`K`'s and the shape matrices', Eqs. 7 and
/// 8; lower CSC, as [`ShapeModel::matrix`]'s) from a mesh's `n` vertices
/// and its faces alone,
/// before the model and its Laplacians exist: for the fill ordering of its
/// factors, made on another thread from the start. The 1-rings are the
/// faces' sides (each pair of a face's distinct corners), as the cotangent
/// Laplacian's pattern holds them.
pub fn shape_pattern(n: usize, faces: &[[u32; 3]]) -> (Vec<usize>, Vec<usize>) {
    let (start, by_vertex) = vertex_faces(n, faces);
    let never = std::sync::atomic::AtomicBool::new(false);
    // The 1-rings as a pattern alone (no weights made to be dropped).
    let (ring_start, ring_idx) = sorted_rows(
        n,
        &never,
        |i, out| {
            for &fi in &by_vertex[start[i]..start[i + 1]] {
                let others = faces[fi as usize].into_iter().filter(|&v| v as usize != i);
                out.extend(others.filter(|&v| (v as usize) < n));
            }
        },
        |v| v,
    )
    .expect("rows not given up");
    drop((start, by_vertex));
    two_ring_pattern(&ring_start, &ring_idx, &never).expect("a pattern not given up")
}

/// Lower-triangular pattern `(col_ptr, row_idx)` of the vertex pairs within two
/// rings of each other (every pair inside one closed 1-ring: a vertex and
/// its row of `(start, idx)`, which lists its 1-ring without itself),
/// diagonal first in every column; built column by column in parallel.
/// `None` where `stop` is set before its last columns are made (the caller
/// has the pattern from elsewhere).
fn two_ring_pattern(
    start: &[usize],
    idx: &[u32],
    stop: &std::sync::atomic::AtomicBool,
) -> Option<(Vec<usize>, Vec<usize>)> {
    let n = start.len() - 1;
    let row =
        |i: usize| std::iter::once(i as u32).chain(idx[start[i]..start[i + 1]].iter().copied());
    sorted_rows(
        n,
        stop,
        |j, column| {
            for p in row(j) {
                column.extend(row(p as usize).filter(|&q| q as usize >= j));
            }
        },
        |q| q as usize,
    )
}

/// Rows `0..n` of a pattern, CSR `(start, idx)`: row `i` what `row(i, out)`
/// pushes onto `out` (empty on the call), sorted, each entry once. Made in
/// chunks of rows on rayon's threads, each chunk's rows in one vector (not
/// one per row: 600k allocations at homer 1.2M), then copied into place.
/// `None` where `stop` is set before its last chunks are made. `to` turns
/// an entry into the index type stored.
fn sorted_rows<T: Copy + Default + Send + Sync>(
    n: usize,
    stop: &std::sync::atomic::AtomicBool,
    row: impl Fn(usize, &mut Vec<u32>) + Sync,
    to: fn(u32) -> T,
) -> Option<(Vec<usize>, Vec<T>)> {
    use rayon::prelude::*;
    const ROWS: usize = 4096;
    let chunks: Vec<(Vec<usize>, Vec<u32>)> = (0..n.div_ceil(ROWS))
        .into_par_iter()
        .map(|c| {
            let rows = c * ROWS..((c + 1) * ROWS).min(n);
            if stop.load(std::sync::atomic::Ordering::Acquire) {
                return (Vec::new(), Vec::new());
            }
            let mut lens = Vec::with_capacity(rows.len());
            let mut entries = Vec::new();
            let mut one = Vec::new();
            for i in rows {
                one.clear();
                row(i, &mut one);
                one.sort_unstable();
                one.dedup();
                lens.push(one.len());
                entries.extend_from_slice(&one);
            }
            (lens, entries)
        })
        .collect();
    if chunks.iter().map(|(lens, _)| lens.len()).sum::<usize>() < n {
        return None;
    }
    let mut start = Vec::with_capacity(n + 1);
    start.push(0);
    for len in chunks.iter().flat_map(|(lens, _)| lens) {
        start.push(start.last().unwrap() + len);
    }
    let mut idx = vec![T::default(); start[n]];
    solver_cpu::row_groups_mut(&mut idx, n, |i| start[i], ROWS)
        .into_par_iter()
        .zip(&chunks)
        .for_each(|((_, out), (_, entries))| {
            out.iter_mut().zip(entries).for_each(|(o, &q)| *o = to(q));
        });
    Some((start, idx))
}

// ---------------------------------------------------------------------------
// Eq. 21: the E_m targets c_i
// ---------------------------------------------------------------------------

/// How the E_m target of each vertex is scaled (Eq. 21).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CurvatureTarget {
    /// `c_i` = area-weighted mean scale factor around vertex i (pitfall (b); default).
    #[default]
    Scaled,
    /// `c_i` = 1 (Eq. 5 as printed), except in curvature regions.
    Literal,
}

/// The curvature targets `c_i` of Eq. 21: per vertex, the area-weighted
/// mean of its faces' scale factors `s` (1 for a vertex in no face), on
/// one thread ([`ShapeModel::vertex_mean_scale`] gives the same values on
/// rayon's threads).
pub fn vertex_mean_scale(mesh: &Mesh, areas: &[f64], s: &[f64]) -> Vec<f64> {
    let mut c = vec![0.0; mesh.num_vertices()];
    vertex_mean_scale_of_range(mesh, areas, s, 0, 0..mesh.num_faces() as u32, &mut c);
    c
}

/// [`vertex_mean_scale`] of the vertices `lo..lo + out.len()` into `out`,
/// from `faces` (ascending, every face with a corner among them): each
/// vertex's sums are added face after face, as one pass over all faces
/// adds them.
fn vertex_mean_scale_of_range(
    mesh: &Mesh,
    areas: &[f64],
    s: &[f64],
    lo: usize,
    faces: impl Iterator<Item = u32>,
    out: &mut [f64],
) {
    let mut den = vec![0.0; out.len()];
    out.iter_mut().for_each(|o| *o = 0.0);
    for f in faces {
        let f = f as usize;
        for &v in &mesh.faces[f] {
            let Some(i) = (v as usize).checked_sub(lo).filter(|&i| i < out.len()) else {
                continue;
            };
            out[i] += areas[f] * s[f];
            den[i] += areas[f];
        }
    }
    for (c, d) in out.iter_mut().zip(&den) {
        *c = if *d > 0.0 { *c / *d } else { 1.0 };
    }
}

/// A curvature region of Eq. 21 resolved on the mesh: its vertices and factor.
#[derive(Debug, Clone)]
pub struct CurvatureRegion {
    pub vertices: Vec<u32>,
    pub scale: f64,
}

/// Per vertex, the product of the factors of the curvature regions it is in
/// (Eq. 21; 1 outside them).
pub fn curvature_factors(n: usize, regions: &[CurvatureRegion]) -> Vec<f64> {
    let mut factor = vec![1.0; n];
    for r in regions {
        for &v in &r.vertices {
            factor[v as usize] *= r.scale;
        }
    }
    factor
}

/// The E_m targets `c_i` of Eq. 21 for face scale factors `s`: the vertex
/// mean scale ([`CurvatureTarget::Scaled`]) or 1, times `factors`
/// ([`curvature_factors`]) where given.
pub fn curvature_targets(
    model: &ShapeModel,
    mesh: &Mesh,
    areas: &[f64],
    s: &[f64],
    target: CurvatureTarget,
    factors: Option<&[f64]>,
) -> Vec<f64> {
    let mut c = match target {
        CurvatureTarget::Scaled => model.vertex_mean_scale(mesh, areas, s),
        CurvatureTarget::Literal => vec![1.0; mesh.num_vertices()],
    };
    if let Some(f) = factors {
        c.iter_mut().zip(f).for_each(|(c, f)| *c *= f);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    /// spot (in the repository) and its shape model.
    fn spot_model() -> (Mesh, ShapeModel) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes/spot.obj");
        let mesh = crate::mesh::io::read_mesh(&path).unwrap();
        let topo = Topology::build(&mesh);
        let model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
        (mesh, model)
    }

    /// The matrix hands a solver the slot of each ring pair in its pattern,
    /// in the rings' pair order: each pair's entry, as a search finds it.
    #[test]
    fn the_matrix_carries_its_ring_pairs_slots() {
        let (_, model) = spot_model();
        let h = model.matrix();
        let slots = h.ring_slots.as_ref().expect("the model's slots");
        let (col_ptr, row_idx) = (&h.iso.col_ptr, &h.iso.row_idx);
        let searched: Vec<u32> = (0..h.rings.len())
            .flat_map(|i| {
                h.rings.pairs(i).map(|(p, q, _)| {
                    (col_ptr[q]..col_ptr[q + 1])
                        .find(|&k| row_idx[k] == p)
                        .expect("pair in the pattern") as u32
                })
            })
            .collect();
        assert_eq!(&**slots, &searched[..]);
    }

    /// The assembly's sums into `K`, the rings' `C_i` and the gradient are
    /// the same to the bit on 1, 3 and 4 threads: the vertex ranges
    /// (`vertex_ranges`, 4 of them on 4 threads here) add each face's terms
    /// in face order, as one thread does.
    #[test]
    fn the_assembly_is_the_same_on_any_number_of_threads() {
        let (mut mesh, _) = spot_model();
        mesh = mesh.subdivide_midpoint().subdivide_midpoint();
        let nf = mesh.faces.len();
        assert!(nf >= 4 * FACES_PER_RANGE, "{nf} faces: one range only");
        let topo = Topology::build(&mesh);
        let x = perturbed(&mesh, 0.05);
        let (s, c, w) = varied_job(nf, mesh.num_vertices());
        let on = |threads: usize| {
            crate::ordered::on_threads(threads, || {
                assert_eq!(vertex_ranges(mesh.num_vertices(), nf).len() - 1, threads);
                let mut model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
                model
                    .assemble_with_positions(&mesh, &x, &s, &c, &w, false)
                    .unwrap();
                let m = model.matrix();
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
                let rings: Vec<f64> = m.ring_c.iter().flatten().copied().collect();
                let grad = model.gradient_at(&vec![0.0; 3 * mesh.num_vertices()]);
                (bits(&m.iso.values), bits(&rings), bits(&grad))
            })
        };
        let one = on(1);
        assert!(one.2.iter().any(|&g| g != 0), "a gradient to compare");
        assert!(one == on(3), "3 threads");
        assert!(one == on(4), "4 threads");
    }

    /// The model's vertex mean scale on 4 threads (4 vertex ranges) is the
    /// one-thread `vertex_mean_scale` to the bit, with a collapsed face
    /// (one vertex twice) across two ranges and a vertex in no face.
    #[test]
    fn the_vertex_mean_scale_by_ranges_is_the_one_threads() {
        let (mut mesh, _) = spot_model();
        mesh = mesh.subdivide_midpoint().subdivide_midpoint();
        let n = mesh.num_vertices() as u32;
        mesh.faces.push([1, n - 2, 1]);
        mesh.positions.push(DVec3::new(0.3, 0.2, 0.1));
        let nf = mesh.faces.len();
        let topo = Topology::build(&mesh);
        let (s, _, _) = varied_job(nf, mesh.num_vertices());
        let areas: Vec<f64> = (0..nf).map(|f| 0.5 + (f % 7) as f64 * 0.125).collect();
        let one = vertex_mean_scale(&mesh, &areas, &s);
        assert_eq!(one[n as usize], 1.0, "the vertex in no face");
        assert!(one.iter().any(|&c| c != 1.0), "means to compare");
        let by_ranges = crate::ordered::on_threads(4, || {
            assert_eq!(vertex_ranges(mesh.num_vertices(), nf).len() - 1, 4);
            let model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
            model.vertex_mean_scale(&mesh, &areas, &s)
        });
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
        assert_eq!(bits(&one), bits(&by_ranges));
    }

    /// `shape_pattern`, from the faces alone, is the model's pattern: on
    /// spot, and on spot with a collapsed face, a repeated face, a needle
    /// and a vertex in no face added (their pairs stay in the pattern).
    #[test]
    fn shape_pattern_from_the_faces_is_the_models() {
        let (mut mesh, model) = spot_model();
        let pattern = |m: &ShapeModel| {
            (
                m.matrix().iso.col_ptr.clone(),
                m.matrix().iso.row_idx.clone(),
            )
        };
        assert_eq!(
            shape_pattern(mesh.positions.len(), &mesh.faces),
            pattern(&model)
        );
        let n = mesh.positions.len() as u32;
        let f0 = mesh.faces[0];
        let far = mesh.faces[mesh.faces.len() / 2];
        mesh.faces.push([f0[0], f0[0], far[1]]);
        mesh.faces.push(f0);
        mesh.positions
            .push(mesh.positions[far[0] as usize] + DVec3::new(1e-9, 0.0, 0.0));
        mesh.faces.push([far[0], far[1], n]);
        mesh.positions.push(DVec3::new(5.0, 5.0, 5.0));
        let topo = Topology::build(&mesh);
        let model = ShapeModel::new(&mesh, &topo, Vec::new()).unwrap();
        let (col_ptr, row_idx) = shape_pattern(mesh.positions.len(), &mesh.faces);
        assert_eq!(col_ptr.len(), n as usize + 3);
        assert!(row_idx.len() > pattern(&spot_model().1).1.len());
        assert_eq!((col_ptr, row_idx), pattern(&model));
    }

    /// Where the topology leaves no face out of its vertices' faces (no
    /// collapsed or duplicate face), its list is [`vertex_faces`]' (which the
    /// model then takes instead of making it); where it does, they differ.
    #[test]
    fn the_topologys_vertex_faces_are_the_models_where_no_face_is_left_out() {
        let (mut mesh, _) = spot_model();
        let topo = Topology::build(&mesh);
        assert!(topo.collapsed_faces.is_empty() && topo.duplicate_faces.is_empty());
        let (start, faces) = vertex_faces(mesh.num_vertices(), &mesh.faces);
        assert_eq!((topo.vf_start, topo.vf_index), (start, faces));
        mesh.faces.push(mesh.faces[0]);
        let topo = Topology::build(&mesh);
        let (start, faces) = vertex_faces(mesh.num_vertices(), &mesh.faces);
        assert_ne!((topo.vf_start, topo.vf_index), (start, faces));
    }

    /// A model given its pattern from another thread
    /// ([`ShapeModel::with_solver_and_pattern`]) is the model that makes its
    /// own, entry for entry and slot for slot; so is one whose channel holds
    /// no pattern, or one of the wrong size (refused).
    #[test]
    fn a_model_given_its_pattern_is_the_model_that_makes_it() {
        let (mesh, own) = spot_model();
        let topo = Topology::build(&mesh);
        let n = mesh.positions.len();
        let made = |sent: Option<(Vec<usize>, Vec<usize>)>| {
            let (tx, rx) = std::sync::mpsc::channel();
            let ready = Arc::new(std::sync::atomic::AtomicBool::new(false));
            if let Some(p) = sent {
                tx.send(Arc::new(p)).unwrap();
                ready.store(true, std::sync::atomic::Ordering::Release);
            }
            drop(tx);
            let share = SharedPattern { pattern: rx, ready };
            let solver = Box::new(BlockPcgSolver::new());
            ShapeModel::with_solver_and_pattern(&mesh, &topo, Vec::new(), solver, Some(share))
                .unwrap()
        };
        let (col_ptr, row_idx) = shape_pattern(n, &mesh.faces);
        let short = (col_ptr[..n].to_vec(), row_idx[..col_ptr[n - 1]].to_vec());
        // The flag set before the pattern is sent (from a thread, a moment
        // later): the model gives its own up at its first chunk and waits.
        let late = {
            let (tx, rx) = std::sync::mpsc::channel();
            let ready = Arc::new(std::sync::atomic::AtomicBool::new(true));
            let sent = Arc::new((col_ptr.clone(), row_idx.clone()));
            let sender = std::thread::spawn(move || {
                std::thread::sleep(std::time::Duration::from_millis(50));
                tx.send(sent).unwrap();
            });
            let share = SharedPattern { pattern: rx, ready };
            let solver = Box::new(BlockPcgSolver::new());
            let model =
                ShapeModel::with_solver_and_pattern(&mesh, &topo, Vec::new(), solver, Some(share))
                    .unwrap();
            sender.join().unwrap();
            model
        };
        let stop = std::sync::atomic::AtomicBool::new(true);
        assert!(two_ring_pattern(&own.cot.start, &own.cot.idx, &stop).is_none());
        let models = [
            made(Some((col_ptr, row_idx))),
            made(None),
            made(Some(short)),
            late,
        ];
        for model in models {
            let (a, b) = (model.matrix(), own.matrix());
            assert_eq!(a.iso.col_ptr, b.iso.col_ptr);
            assert_eq!(a.iso.row_idx, b.iso.row_idx);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
            assert_eq!(bits(&a.iso.values), bits(&b.iso.values));
            assert_eq!(model.face_slots, own.face_slots);
            assert_eq!(model.mv_slots, own.mv_slots);
        }
    }

    /// The Laplacians made row by row from each vertex's faces are, to the
    /// bit, those of all faces' corners' triplets sorted at once, on one
    /// thread and on four: on spot with a collapsed face (one vertex at two
    /// corners), a repeated face, a needle and a skipped face.
    #[test]
    fn laplacians_by_rows_are_those_of_all_the_triplets() {
        let (mut mesh, _) = spot_model();
        let n = mesh.positions.len() as u32;
        let (f0, far) = (mesh.faces[0], mesh.faces[mesh.faces.len() / 2]);
        mesh.faces.push([f0[0], f0[0], far[1]]);
        mesh.faces.push(f0);
        mesh.positions
            .push(mesh.positions[far[0] as usize] + DVec3::new(1e-9, 0.0, 0.0));
        mesh.faces.push([far[0], far[1], n]);
        let x = &mesh.positions;
        let mut skip = mesh.degenerate_faces(x);
        skip[3] = true;
        assert!(skip.iter().filter(|&&s| s).count() >= 3);
        // Every face's corners' weights as (row, column, weight) triplets.
        let by_triplets = |corner: &dyn FaceCorner, normalise| {
            let mut t = Vec::new();
            let mut out = Vec::new();
            for (fi, &f) in mesh.faces.iter().enumerate() {
                for k in 0..3 {
                    out.clear();
                    corner(fi, f, k, &mut out);
                    t.extend(out.iter().map(|&(j, w)| (f[k], j, w)));
                }
            }
            SparseRows::from_triplets(x.len(), t, normalise)
        };
        let want = [
            by_triplets(&cotangent_corner(x, &skip), false),
            by_triplets(&mean_value_corner(x, &skip), true),
        ];
        for threads in [1, 4] {
            let got = crate::ordered::on_threads(threads, || {
                [
                    cotangent_laplacian_masked(&mesh, x, &skip),
                    mean_value_laplacian_masked(&mesh, x, &skip),
                ]
            });
            for (got, want) in got.iter().zip(&want) {
                assert_eq!((&got.start, &got.idx), (&want.start, &want.idx));
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
                assert_eq!(bits(&got.w), bits(&want.w), "{threads} threads");
                assert_eq!(bits(&got.diag), bits(&want.diag), "{threads} threads");
            }
        }
    }

    /// Scale factors varying over the faces, curvature targets and
    /// fine-tune-like weights (E_m and E_l strong) for `nf` faces and `n`
    /// vertices.
    /// `mesh`'s positions, each scaled by up to `1 +- amount`.
    fn perturbed(mesh: &Mesh, amount: f64) -> Vec<DVec3> {
        mesh.positions
            .iter()
            .enumerate()
            .map(|(i, p)| *p * (1.0 + amount * (i as f64 * 0.1).sin()))
            .collect()
    }

    fn varied_job(nf: usize, n: usize) -> (Vec<f64>, Vec<f64>, ShapeWeights) {
        let s = (0..nf).map(|f| 1.1 + 0.05 * (f as f64).sin()).collect();
        let w = ShapeWeights {
            k_f: 1.0,
            k_m: 100.0,
            k_l: 100.0,
            k_p: 0.0,
        };
        (s, vec![1.1; n], w)
    }

    /// A varied job's `(s, c, w)` ([`varied_job`]).
    type Job = (Vec<f64>, Vec<f64>, ShapeWeights);

    /// spot with a varied job at perturbed positions, E_p weighted: the
    /// mesh, its topology, the job and the positions.
    fn handle_job() -> (Mesh, Topology, Job, Vec<DVec3>) {
        let (mesh, _) = spot_model();
        let topo = Topology::build(&mesh);
        let (s, c, mut w) = varied_job(mesh.num_faces(), mesh.num_vertices());
        w.k_p = 10.0;
        let xc = perturbed(&mesh, 0.02);
        (mesh, topo, (s, c, w), xc)
    }

    /// Three handles on spot, near their vertices (none unless `with`).
    fn spot_handles(mesh: &Mesh, with: bool) -> Vec<HandleTarget> {
        [5u32, 700, 1400]
            .iter()
            .filter(|_| with)
            .map(|&v| HandleTarget {
                vertex: v,
                target: mesh.positions[v as usize] + DVec3::new(0.01, 0.0, -0.02),
            })
            .collect()
    }

    /// `isotropic_part` is the `K` that an assembly at the same positions
    /// and weights gives a solver that reads `K` apart (the matrix its
    /// factor is made from), to the bit: every isotropic term, handles
    /// included, held rows identity.
    #[test]
    fn isotropic_part_is_the_assemblys_k_to_the_bit() {
        let (mesh, topo, (s, c, w), xc) = handle_job();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        // With handles (E_p), and without (a held vertex).
        for with_handles in [true, false] {
            let handles = spot_handles(&mesh, with_handles);
            let solver = Box::new(solver_cpu::CholeskySolver::new());
            let mut model = ShapeModel::with_solver(&mesh, &topo, handles, solver).unwrap();
            assert_eq!(model.fixed.iter().any(|&f| f), !with_handles);
            model.assemble_and_factor(&mesh, &xc, &s, &c, &w).unwrap();
            let assembled = model.matrix().iso_held_identity(&model.fixed);
            let k = model.isotropic_part(&mesh, &xc, &w);
            assert_eq!(
                (&k.col_ptr, &k.row_idx),
                (&assembled.col_ptr, &assembled.row_idx)
            );
            assert_eq!(bits(&k.values), bits(&assembled.values));
            let elsewhere = model.isotropic_part(&mesh, &mesh.positions, &w);
            assert_ne!(bits(&elsewhere.values), bits(&assembled.values));
        }
    }

    /// The energy and the gradient are those of the product `H dx` with the
    /// held dofs left out, with handles and with a held vertex: where `dx`
    /// is zero at the held vertex (as the fine-tune's steps are) and where
    /// it is not.
    #[test]
    fn energy_and_gradient_are_the_products_held_dofs_left_out() {
        let (mesh, topo, (s, c, w), xc) = handle_job();
        let n = mesh.num_vertices();
        for with_handles in [true, false] {
            let handles = spot_handles(&mesh, with_handles);
            let mut model = ShapeModel::new(&mesh, &topo, handles).unwrap();
            model.assemble_and_factor(&mesh, &xc, &s, &c, &w).unwrap();
            let held = |i: usize| model.fixed[i / 3];
            // Handles are soft (E_p); without them one vertex is held.
            assert_eq!((0..3 * n).any(held), !with_handles);
            let zero = vec![0.0; 3 * n];
            assert_eq!(model.energy(&zero), 0.0);
            let g0: Vec<f64> = (0..3 * n)
                .map(|i| {
                    if held(i) {
                        0.0
                    } else {
                        model.reference_gradient()[i]
                    }
                })
                .collect();
            assert!(g0.iter().any(|&g| g != 0.0));
            assert_eq!(model.gradient_at(&zero), g0);
            let moved: Vec<f64> = (0..3 * n).map(|i| 1e-3 * (0.37 * i as f64).sin()).collect();
            let still: Vec<f64> = (0..3 * n)
                .map(|i| if held(i) { 0.0 } else { moved[i] })
                .collect();
            for dx in [&still, &moved] {
                let mut hd = vec![0.0; 3 * n];
                model.matrix().mul_vec(dx, &mut hd);
                // The sum over the free dofs of the product with the free part.
                let mut hf = vec![0.0; 3 * n];
                model.matrix().mul_vec(&still, &mut hf);
                let want: f64 = (0..3 * n)
                    .filter(|&i| !held(i))
                    .map(|i| 0.5 * still[i] * hf[i] + model.reference_gradient()[i] * dx[i])
                    .sum();
                let got = model.energy(dx);
                assert!(want.abs() > 1e-9, "an energy to compare: {want}");
                assert!(
                    (got - want).abs() <= 1e-11 * want.abs(),
                    "{got} against {want}"
                );
                let g = model.gradient_at(dx);
                let scale = hd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for i in 0..3 * n {
                    let want = if held(i) {
                        0.0
                    } else {
                        hd[i] + model.reference_gradient()[i]
                    };
                    assert!((g[i] - want).abs() <= 1e-12 * scale, "gradient {i}");
                }
            }
        }
    }

    /// The energy is quadratic in the increment with gradient `H dx + g0`
    /// (held entries zero): the Newton direction `H^-1 (-grad E)` at `dx` is
    /// the one at zero minus `dx`, which the fine-tune uses instead of a
    /// solve after its first step.
    #[test]
    fn newton_direction_at_dx_is_the_one_at_zero_minus_dx() {
        let (mesh, _) = spot_model();
        // A direct solver: its solves are exact to rounding.
        let topo = Topology::build(&mesh);
        let solver = Box::new(solver_cpu::CholeskySolver::new());
        let mut model = ShapeModel::with_solver(&mesh, &topo, Vec::new(), solver).unwrap();
        let n = mesh.num_vertices();
        let (s, c, w) = varied_job(mesh.num_faces(), n);
        model
            .assemble_and_factor(&mesh, &mesh.positions, &s, &c, &w)
            .unwrap();
        let direction = |model: &mut ShapeModel, dx: &[f64]| {
            let mut y: Vec<f64> = model.gradient_at(dx).iter().map(|g| -g).collect();
            model.solver().solve_in_place(&mut y, 1).unwrap();
            y
        };
        let zero = vec![0.0; 3 * n];
        let dx: Vec<f64> = (0..3 * n)
            .map(|i| match model.fixed[i / 3] {
                true => 0.0,
                false => 1e-2 * (0.7 * i as f64).cos(),
            })
            .collect();
        let y0 = direction(&mut model, &zero);
        let y = direction(&mut model, &dx);
        let scale = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 1e-3, "{scale}");
        for i in 0..3 * n {
            assert!(
                (y[i] - (y0[i] - dx[i])).abs() <= 1e-9 * scale,
                "entry {i}: {} against {}",
                y[i],
                y0[i] - dx[i]
            );
        }
    }

    /// A solver that no longer reads `K` apart: the model puts E_l's whole
    /// term into the rings' `C_i`; with `.1`, it adds E_m's Hessian itself
    /// (its own `to_blocks` does), so the model leaves it out of `K`.
    struct WholeRings(solver_cpu::CholeskySolver, bool);

    impl SpdSolver for WholeRings {
        fn prepare(
            &mut self,
            a: &solver_cpu::SymCsc,
        ) -> std::result::Result<(), solver_cpu::SolverError> {
            self.0.prepare(a)
        }
        fn prepare_blocks(
            &mut self,
            a: &solver_cpu::BlockSym3,
            fixed: &[bool],
        ) -> std::result::Result<(), solver_cpu::SolverError> {
            self.0.prepare_blocks(a, fixed)
        }
        fn wants_isotropic_part(&self) -> bool {
            false
        }
        fn adds_laplacian_square(&self) -> bool {
            self.1
        }
        fn solve_in_place(
            &mut self,
            rhs: &mut [f64],
            ncols: usize,
        ) -> std::result::Result<solver_cpu::SolveInfo, solver_cpu::SolverError> {
            self.0.solve_in_place(rhs, ncols)
        }
        fn counters(&self) -> solver_cpu::WorkCounters {
            self.0.counters()
        }
        fn name(&self) -> &str {
            "whole rings"
        }
    }

    /// With E_l's isotropic part in the rings instead of `K`, and E_m's
    /// Hessian named instead of in `K` where the solver adds it, the matrix
    /// is the same (its product to rounding, its energy and its solution
    /// too), `K` lacks those parts, and the `C_i` are no longer traceless.
    #[test]
    fn el_term_in_the_rings_gives_the_same_matrix() {
        for square in [false, true] {
            el_term_in_the_rings_gives_the_same_matrix_with(square);
        }
    }

    fn el_term_in_the_rings_gives_the_same_matrix_with(square: bool) {
        let (mesh, _) = spot_model();
        let topo = Topology::build(&mesh);
        let n = mesh.num_vertices();
        let (s, c, w) = varied_job(mesh.num_faces(), n);
        let split_solver = Box::new(solver_cpu::CholeskySolver::new());
        let mut split = ShapeModel::with_solver(&mesh, &topo, Vec::new(), split_solver).unwrap();
        let whole_solver = Box::new(WholeRings(solver_cpu::CholeskySolver::new(), square));
        let mut whole = ShapeModel::with_solver(&mesh, &topo, Vec::new(), whole_solver).unwrap();
        for m in [&mut split, &mut whole] {
            m.assemble_and_factor(&mesh, &mesh.positions, &s, &c, &w)
                .unwrap();
        }
        let (a, b) = (split.matrix(), whole.matrix());
        assert!(a.laplacian_square.is_none());
        assert_eq!(b.laplacian_square.is_some(), square);
        let trace = |c: &[f64; 6]| c[0] + c[1] + c[2];
        let scale_c = a.ring_c.iter().fold(0.0f64, |m, c| m.max(c[0].abs()));
        assert!(a.ring_c.iter().all(|c| trace(c).abs() <= 1e-12 * scale_c));
        assert!(b.ring_c.iter().any(|c| trace(c) > 1e-3 * scale_c));
        let kmax = a.iso.values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let kdiff = a
            .iso
            .values
            .iter()
            .zip(&b.iso.values)
            .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
        assert!(kdiff > 1e-6 * kmax, "K still holds E_l's part: {kdiff}");
        if square {
            // E_m's Hessian dominates K's diagonal on this job.
            let d = |h: &IsoRingSym3, v: usize| h.iso.values[h.diagonal_slot(v)];
            assert!((0..n).all(|v| d(b, v) < 0.5 * d(a, v)), "K still holds E_m");
        }
        let x: Vec<f64> = (0..3 * n).map(|i| (0.37 * i as f64).sin()).collect();
        let (ea, eb) = (split.energy(&x), whole.energy(&x));
        assert!(
            (ea - eb).abs() <= 1e-12 * ea.abs(),
            "energy {ea} against {eb}"
        );
        let (mut ya, mut yb) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
        a.mul_vec(&x, &mut ya);
        b.mul_vec(&x, &mut yb);
        let ymax = ya.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(ymax > 0.0);
        for i in 0..3 * n {
            assert!(
                (ya[i] - yb[i]).abs() <= 1e-12 * ymax,
                "entry {i}: {} against {}",
                ya[i],
                yb[i]
            );
        }
        let g = split.reference_gradient().to_vec();
        assert_eq!(g, whole.reference_gradient());
        let (mut da, mut db) = (g.clone(), g);
        split.solver().solve_in_place(&mut da, 1).unwrap();
        whole.solver().solve_in_place(&mut db, 1).unwrap();
        let dmax = da.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(dmax > 0.0);
        for i in 0..3 * n {
            assert!((da[i] - db[i]).abs() <= 1e-9 * dmax, "solution entry {i}");
        }
    }

    /// The E_m Hessian added on the fly through the mean-value pair slots equals
    /// the stored one (the path of meshes whose Laplacians differ in pattern).
    #[test]
    fn em_hessian_on_the_fly_equals_the_stored_one() {
        let (mesh, mut model) = spot_model();
        assert!(model.hm.is_empty(), "spot's Laplacians share their pattern");
        let nf = mesh.num_faces();
        let n = mesh.num_vertices();
        let s: Vec<f64> = (0..nf)
            .map(|f| 1.0 + 0.1 * (f as f64 * 0.3).sin())
            .collect();
        let c = vec![1.05; n];
        let w = ShapeWeights {
            k_f: 10.0,
            k_m: 3.0,
            k_l: 2.0,
            k_p: 0.0,
        };
        model
            .assemble_and_factor(&mesh, &mesh.positions, &s, &c, &w)
            .unwrap();
        let on_the_fly = model.matrix().clone();
        model.hm = em_hessian(&model.cot, &model.vertex_area, &on_the_fly);
        model
            .assemble_and_factor(&mesh, &mesh.positions, &s, &c, &w)
            .unwrap();
        let stored = model.matrix();
        let scale = stored.iso.values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        for (a, b) in on_the_fly.iso.values.iter().zip(&stored.iso.values) {
            assert!((a - b).abs() <= 1e-12 * scale, "{a} vs {b}");
        }
        assert_eq!(on_the_fly.ring_c, stored.ring_c);
        assert!(
            stored.ring_c.iter().any(|c| c[3] != 0.0),
            "E_l is anisotropic"
        );
    }

    /// Eq. 4 with the fourth frame vertex (Sec. 2.1) kept as an unknown and
    /// minimised out, face by face, equals the model's eliminated frame energy:
    /// the closed-form elimination changes no result.
    #[test]
    fn eliminated_fourth_vertex_is_the_minimum_of_the_four_vertex_energy() {
        use glam::DMat3;
        let (mesh, mut model) = spot_model();
        let (nf, n) = (mesh.num_faces(), mesh.num_vertices());
        let xc = &mesh.positions;
        let s: Vec<f64> = (0..nf)
            .map(|f| 1.0 + 0.2 * (f as f64 * 0.7).sin())
            .collect();
        let w = ShapeWeights {
            k_f: 1.0,
            k_m: 0.0,
            k_l: 0.0,
            k_p: 0.0,
        };
        model
            .assemble_and_factor(&mesh, xc, &s, &vec![1.0; n], &w)
            .unwrap();
        let scale = model.mean_edge();
        let dx: Vec<f64> = (0..3 * n)
            .map(|i| {
                if model.fixed[i / 3] {
                    0.0
                } else {
                    0.3 * scale * (i as f64 * 1.37).sin()
                }
            })
            .collect();
        let x: Vec<DVec3> = (0..n)
            .map(|v| xc[v] + DVec3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]))
            .collect();
        // Per face: V^c = [e1, e2, n / sqrt|n|] (deformation transfer's fourth
        // vertex), V(u) = [e1', e2', u]; min over u of ||V(u) (V^c)^-1 - s I||_F^2
        // is linear least squares in u.
        let four_vertex = |p: &[DVec3], f: usize| -> f64 {
            let t = mesh.faces[f];
            let (a, b, c) = (xc[t[0] as usize], xc[t[1] as usize], xc[t[2] as usize]);
            let nrm = (b - a).cross(c - a);
            let m = DMat3::from_cols(b - a, c - a, nrm / nrm.length().sqrt()).inverse();
            let (pa, pb, pc) = (p[t[0] as usize], p[t[1] as usize], p[t[2] as usize]);
            let rows = [m.row(0), m.row(1), m.row(2)];
            let outer = |u: DVec3, r: DVec3| DMat3::from_cols(u * r.x, u * r.y, u * r.z);
            let base = outer(pb - pa, rows[0]) + outer(pc - pa, rows[1])
                - DMat3::from_diagonal(DVec3::splat(s[f]));
            let m3 = rows[2];
            let u = -(base * m3) / m3.length_squared();
            let r = base + outer(u, m3);
            r.x_axis.length_squared() + r.y_axis.length_squared() + r.z_axis.length_squared()
        };
        let want: f64 = (0..nf)
            .map(|f| model.face_weight[f] * (four_vertex(&x, f) - four_vertex(xc, f)))
            .sum();
        let got = model.energy(&dx);
        assert!(
            want.abs() > 1e-3,
            "the displacement changes the frame energy ({want})"
        );
        assert!(
            (got - want).abs() <= 1e-9 * want.abs(),
            "eliminated {got} vs four-vertex minimum {want}"
        );
    }
}
