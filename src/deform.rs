//! The whole method: scale-driven deformation (Sec. 2.4: Eq. 3 then Eq. 7,
//! iterated) followed by the fine-tune with hard constraints (Eq. 8, solved by
//! sequential linearly constrained Newton steps through the Schur complement of
//! Eqs. 15-18 on a Hessian factored once).

use crate::anderson::Anderson;
use crate::job::{curvature_label, handle_label, Job, MetricKind, SolverSpec};
use crate::metrics::{Constraint, Selection, VolumeShare};
use crate::scale_factors::{Regulariser, ScaleConstraint, ScaleFactorSystem};
use crate::schur::{constrained_step_warm, Linearized, Multipliers};
use crate::selection::{build_curve, build_handle_vertices, build_region};
use crate::shape::{HandleTarget, ShapeModel, ShapeWeights};
use crate::topology::Topology;
use crate::validate::{require_volume, validate, MeshCheck};
use crate::{Error, Mesh, Result};
use glam::DVec3;
use solver_cpu::cholesky::NESTED_DISSECTION_FROM;
use solver_cpu::{
    nested_dissection_of_pattern, BlockPcgSolver, CholeskySolver, FillOrdering, SpdSolver, SymCsc,
    SystemKind, WorkCounters,
};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Meshes from this many vertices on give an iterative backend the vertex
/// positions for the scale-driven shape systems too (Eq. 7), so that its AMG
/// takes the affine motions as near-null space (the fine-tune always does).
/// Measured on the GPU backend on lavapipe, 2026-11-22 (BENCHMARKS.md, "AMG
/// near-null space: translations or affine motions"; the full table is in its
/// git history): with
/// translations the PCG iterations grow with the mesh (120 on spot's 2.9k
/// vertices, 527 on spot x16's 47k, 727-768 on 54k, ~1850 on 216k), with
/// affine modes they stay near 45-60, and an affine V-cycle costs 3-4x a
/// translations one plus its set-up: a loss on spot (22.6 s against 28.9 s
/// end to end on lavapipe), 9x fewer iterations on spot x16. The crossover,
/// translations needing about 4x the affine iterations, is near 10k vertices.
pub const AFFINE_SCALE_DRIVEN_MIN_VERTICES: usize = 10_000;

/// How the E_m target of each vertex is scaled (Eq. 21).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CurvatureTarget {
    /// `c_i` = area-weighted mean scale factor around vertex i (pitfall (b); default).
    #[default]
    Scaled,
    /// `c_i` = 1 (Eq. 5 as printed), except in curvature regions.
    Literal,
}

/// Which linear solvers a run uses (`--backend`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SolverBackend {
    /// CPU reference: shape systems by block PCG preconditioned with the sparse
    /// Cholesky factor of their isotropic part, the scale-factor system by sparse
    /// Cholesky (faer, symbolic factor reused).
    #[default]
    Cpu,
    /// CPU, sparse Cholesky of every system (no iteration at all).
    CpuDirect,
    /// GPU: every system by the WGSL preconditioned conjugate gradient.
    Gpu,
}

impl SolverBackend {
    pub fn name(self) -> &'static str {
        match self {
            SolverBackend::Cpu => "cpu",
            SolverBackend::CpuDirect => "cpu-direct",
            SolverBackend::Gpu => "gpu",
        }
    }

    /// A solver for the shape systems (Eqs. 7, 8 and 16-18).
    pub fn shape_solver(self) -> Result<Box<dyn SpdSolver>> {
        match self {
            SolverBackend::Cpu => Ok(Box::new(BlockPcgSolver::new())),
            SolverBackend::CpuDirect => Ok(Box::new(CholeskySolver::new())),
            SolverBackend::Gpu => open_gpu(),
        }
    }

    /// Relative residual the shape solves of the fine-tune reach (iterative
    /// backends; the direct one is exact).
    pub fn fine_tune_tolerance(self) -> f64 {
        match self {
            SolverBackend::Cpu | SolverBackend::CpuDirect => CPU_TOLERANCE,
            SolverBackend::Gpu => GPU_TOLERANCE,
        }
    }

    /// A solver for the scale-factor system (Eq. 3).
    pub fn scale_solver(self) -> Result<Box<dyn SpdSolver>> {
        match self {
            SolverBackend::Cpu | SolverBackend::CpuDirect => Ok(Box::new(CholeskySolver::new())),
            SolverBackend::Gpu => open_gpu(),
        }
    }
}

/// Relative residual the CPU PCG solves reach in the fine-tune.
pub const CPU_TOLERANCE: f64 = 1e-10;

/// Relative residual of the shape solves of the scale-driven phase (Eq. 7) on
/// iterative backends. That phase's iterate only seeds the next scale estimate
/// and the fine-tune, so 1e-10 buys nothing; the fine-tune (which makes the
/// metrics exact) uses the tight one. Not looser than 1e-8: Anderson mixing
/// amplifies solve error, and at 1e-6 the PCG and direct CPU results of the
/// homer Table-1 job drifted 2e-4 % of the bbox diagonal apart (2e-7 % at 1e-8).
pub const SCALE_DRIVEN_TOLERANCE: f64 = 1e-8;

/// Default depth of the Anderson acceleration of the scale-driven phase.
pub const ANDERSON_DEPTH: usize = 3;

/// `acceleration = "auto"` accelerates the scale-driven phase from this many
/// faces on. Below it the plain iteration needs few steps (8 on the spot demo)
/// and its early stop leaves the fine-tune a less sheared start: on the demo,
/// quasi-conformal distortion mean/max 1.12/1.59 plain against 1.17/1.98
/// accelerated, which lands where the plain iteration run on to a 0.01
/// threshold does (1.15/1.93).
pub const ANDERSON_FROM_FACES: usize = 100_000;

/// Relative residual the GPU solves must reach. The f32 PCG with f64 refinement
/// stalls near 1e-9 on the fine-tune systems (weights 1/100/100, biharmonic-dominated);
/// 1e-8 leaves the metrics exact (they are measured, and Newton corrects) and the
/// result within the parity bound of the CPU's.
pub const GPU_TOLERANCE: f64 = 1e-8;

fn open_gpu() -> Result<Box<dyn SpdSolver>> {
    match solver_gpu::open() {
        Ok(mut s) => {
            s.set_tolerance(GPU_TOLERANCE);
            Ok(Box::new(s))
        }
        Err(e @ solver_gpu::GpuError::NoAdapter(_)) => Err(Error::bad(format!(
            "--backend gpu: no usable GPU adapter: {e}"
        ))),
        Err(e) => Err(Error::Solver(e.into())),
    }
}

/// `--backend auto`'s measured crossover: the smallest mesh, in faces, from
/// which the GPU backend ran faster than the CPU backend on the same machine
/// (BENCHMARKS.md, "`auto` crossover"). `None`: at no measured size. On an
/// NVIDIA H100 against its 16-core host the GPU backend was 1.74x slower at
/// 108k faces and 1.57x slower at 1.2M (2026-11-24; 5-11x at 5.9k-1.2M
/// before), so `auto` uses the CPU until a measurement shows the GPU ahead.
pub const GPU_FASTER_FROM_FACES: Option<usize> = None;

/// Whether `--backend auto` runs a mesh of `faces` faces on the GPU: only on
/// a hardware adapter (never a CPU emulation such as lavapipe) and only from
/// the measured crossover [`GPU_FASTER_FROM_FACES`] on.
pub fn auto_uses_gpu(faces: usize, hardware_adapter: bool) -> bool {
    hardware_adapter && GPU_FASTER_FROM_FACES.is_some_and(|from| faces >= from)
}

/// Solver settings (`[solver]` of the job file, with defaults).
#[derive(Debug, Clone)]
pub struct Options {
    pub tolerance: f64,
    /// Cap on scale-driven (outer) iterations.
    pub max_iterations: usize,
    pub fine_tune_iterations: usize,
    /// Stop the scale-driven phase when max |s - 1| falls below this.
    pub scale_threshold: f64,
    pub shape: ShapeWeights,
    /// Weights of the fine-tune (Eq. 8; the paper uses k_f, k_m, k_l = 1, 100, 100).
    pub fine_tune: ShapeWeights,
    pub k_d: f64,
    pub k_r: f64,
    pub multipliers: Multipliers,
    pub regulariser: Regulariser,
    pub curvature_target: CurvatureTarget,
    pub volume_share: VolumeShare,
    /// `--preview N`: stop the scale-driven phase after N iterations, skip the fine-tune.
    pub preview: Option<usize>,
    /// Anderson acceleration depth of the scale-driven iteration (0: plain, as in
    /// the paper; `acceleration = "none"`).
    pub anderson_depth: usize,
    /// Meshes with fewer faces run the plain iteration (`acceleration = "auto"`,
    /// the default; `"anderson"` sets 0).
    pub anderson_from_faces: usize,
    pub backend: SolverBackend,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            tolerance: 1e-5,
            max_iterations: 100,
            fine_tune_iterations: 50,
            scale_threshold: 0.05,
            shape: ShapeWeights {
                k_f: 1000.0,
                k_m: 1.0,
                k_l: 1.0,
                k_p: 1000.0,
            },
            fine_tune: ShapeWeights {
                k_f: 1.0,
                k_m: 100.0,
                k_l: 100.0,
                k_p: 1000.0,
            },
            k_d: 1.0,
            k_r: 0.01,
            multipliers: Multipliers::PerConstraint,
            regulariser: Regulariser::Area,
            curvature_target: CurvatureTarget::Scaled,
            volume_share: VolumeShare::Area,
            preview: None,
            anderson_depth: ANDERSON_DEPTH,
            anderson_from_faces: ANDERSON_FROM_FACES,
            backend: SolverBackend::Cpu,
        }
    }
}

impl Options {
    /// Defaults overridden by the job's `[solver]` table.
    pub fn from_spec(spec: &SolverSpec) -> Options {
        let mut o = Options::default();
        if let Some(t) = spec.tolerance {
            o.tolerance = t;
        }
        if let Some(m) = spec.max_iterations {
            o.max_iterations = m;
        }
        if let Some(m) = spec.fine_tune_iterations {
            o.fine_tune_iterations = m;
        }
        if let Some(t) = spec.scale_threshold {
            o.scale_threshold = t;
        }
        if let Some(w) = &spec.weights {
            if let Some(v) = w.k_f {
                o.shape.k_f = v;
            }
            if let Some(v) = w.k_m {
                o.shape.k_m = v;
            }
            if let Some(v) = w.k_l {
                o.shape.k_l = v;
            }
            if let Some(v) = w.k_p {
                o.shape.k_p = v;
                o.fine_tune.k_p = v;
            }
            if let Some(v) = w.k_d {
                o.k_d = v;
            }
            if let Some(v) = w.k_r {
                o.k_r = v;
            }
        }
        match spec.multipliers.as_deref() {
            Some("per_kind") => o.multipliers = Multipliers::PerKind,
            _ => o.multipliers = Multipliers::PerConstraint,
        }
        if spec.regulariser.as_deref() == Some("uniform") {
            o.regulariser = Regulariser::Uniform;
        }
        if spec.curvature_target.as_deref() == Some("literal") {
            o.curvature_target = CurvatureTarget::Literal;
        }
        if spec.volume_share.as_deref() == Some("tetrahedra") {
            o.volume_share = VolumeShare::Tetrahedra;
        }
        match spec.acceleration.as_deref() {
            Some("none") => o.anderson_depth = 0,
            Some("anderson") => o.anderson_from_faces = 0,
            _ => {}
        }
        o
    }
}

/// A curvature region of Eq. 21: its vertices and factor.
#[derive(Debug, Clone)]
pub struct CurvatureRegion {
    pub vertices: Vec<u32>,
    pub scale: f64,
}

/// A job resolved on its mesh: everything the solver needs.
pub struct Problem {
    pub mesh_path: PathBuf,
    pub mesh: Mesh,
    pub topo: Topology,
    pub check: MeshCheck,
    pub constraints: Vec<Constraint>,
    pub handles: Vec<HandleTarget>,
    pub curvature: Vec<CurvatureRegion>,
    /// Tolerated defects of the input worth telling the user (zero-area, needle and
    /// duplicate faces, ...), one line each without a `warning:` prefix; they are
    /// also logged with `log::warn!` when found.
    pub warnings: Vec<String>,
}

/// A bad-input message that does not name the job file yet gets it in front
/// (contract: bad-input messages name the job file).
fn naming_job(job: &Job, e: Error) -> Error {
    match e {
        Error::BadInput(m) if !job.origin.is_empty() && !m.starts_with(&job.origin) => {
            Error::BadInput(format!("{}: {m}", job.origin))
        }
        Error::Io { path, source } if !job.origin.is_empty() => Error::BadInput(format!(
            "{}: cannot read {}: {source}",
            job.origin,
            path.display()
        )),
        e => e,
    }
}

impl Problem {
    /// Read the job's mesh and resolve every selection on it.
    pub fn load(job: &Job) -> Result<Problem> {
        let mesh_path = job.mesh_path();
        let mesh = crate::io::read_mesh(&mesh_path).map_err(|e| naming_job(job, e))?;
        Problem::build(job, mesh, &mesh_path)
    }

    /// Resolve the job's selections on an already loaded mesh. Bad-input messages
    /// name the job file.
    pub fn build(job: &Job, mesh: Mesh, mesh_path: &Path) -> Result<Problem> {
        Self::build_named(job, mesh, mesh_path).map_err(|e| naming_job(job, e))
    }

    fn build_named(job: &Job, mesh: Mesh, mesh_path: &Path) -> Result<Problem> {
        let topo = Topology::build(&mesh);
        let check = validate(&mesh, &topo, mesh_path)?;
        // Duplicate faces count once in whole-mesh metrics.
        let skip: Vec<bool> = if topo.duplicate_faces.is_empty() {
            Vec::new()
        } else {
            topo.is_duplicate.clone()
        };
        let x = &mesh.positions;
        let mut constraints = Vec::new();
        for (i, spec) in job.spec.constraint.iter().enumerate() {
            let label = job.constraint_label(i);
            let (selection, orientation) = match spec.kind {
                MetricKind::Length => {
                    let curve = spec.curve.as_ref().ok_or_else(|| {
                        Error::bad(format!("{label}: a length constraint needs a curve"))
                    })?;
                    (
                        Selection::Curve(build_curve(curve, &mesh, &topo, &label)?),
                        1.0,
                    )
                }
                MetricKind::Area => {
                    let region = spec.region.as_ref().ok_or_else(|| {
                        Error::bad(format!("{label}: an area constraint needs a region"))
                    })?;
                    (
                        Selection::Region(build_region(region, &mesh, job, &label)?),
                        1.0,
                    )
                }
                MetricKind::Volume => {
                    require_volume(&mesh, &topo, &check, mesh_path, &label)?;
                    let v = Constraint {
                        kind: MetricKind::Volume,
                        name: String::new(),
                        selection: Selection::Whole,
                        original: 0.0,
                        target: 0.0,
                        orientation: 1.0,
                        skip: skip.clone(),
                    }
                    .measure(&mesh, x);
                    if v == 0.0 || !v.is_finite() {
                        return Err(Error::bad(format!(
                            "{label}: the mesh {} encloses no volume",
                            mesh_path.display()
                        )));
                    }
                    (Selection::Whole, v.signum())
                }
            };
            let mut c = Constraint {
                kind: spec.kind,
                name: spec
                    .name
                    .clone()
                    .unwrap_or_else(|| format!("{} {}", spec.kind, i + 1)),
                selection,
                original: 0.0,
                target: 0.0,
                orientation,
                skip: skip.clone(),
            };
            c.original = c.measure(&mesh, x);
            if !(c.original > 0.0) || !c.original.is_finite() {
                return Err(Error::bad(format!(
                    "{label}: the {} measures {} on the input mesh",
                    spec.kind, c.original
                )));
            }
            c.target = match (spec.scale, spec.value) {
                (Some(s), None) => s * c.original,
                (None, Some(v)) => v,
                (None, None) => c.original,
                (Some(_), Some(_)) => {
                    return Err(Error::bad(format!(
                        "{label}: give either scale or value, not both"
                    )))
                }
            };
            constraints.push(c);
        }
        let mut handles = Vec::new();
        for (i, h) in job.spec.handle.iter().enumerate() {
            let what = handle_label(i);
            let t = h.translate.unwrap_or([0.0; 3]);
            let t = DVec3::from_array(t);
            for v in build_handle_vertices(h, &mesh, job, &what)? {
                handles.push(HandleTarget {
                    vertex: v,
                    target: x[v as usize] + t,
                });
            }
        }
        let mut curvature = Vec::new();
        for (i, c) in job.spec.curvature.iter().enumerate() {
            let what = curvature_label(i);
            if !(c.scale.is_finite()) {
                return Err(Error::bad(format!("{what}: scale must be a finite number")));
            }
            let region = build_region(&c.region, &mesh, job, &what)?;
            curvature.push(CurvatureRegion {
                vertices: region.vertices(&mesh),
                scale: c.scale,
            });
        }
        Ok(Problem {
            mesh_path: mesh_path.to_path_buf(),
            mesh,
            topo,
            constraints,
            handles,
            curvature,
            warnings: check.warnings.clone(),
            check,
        })
    }
}

/// Progress of a run, for the progress bar.
#[derive(Debug, Clone)]
pub enum Progress {
    ScaleDriven {
        iteration: usize,
        max_error: f64,
        max_scale_change: f64,
    },
    FineTune {
        iteration: usize,
        max_error: f64,
    },
}

/// What a run produced.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub positions: Vec<DVec3>,
    pub scale_driven_iterations: usize,
    pub fine_tune_iterations: usize,
    pub seconds_scale_driven: f64,
    pub seconds_fine_tune: f64,
    /// Per-face scale factor of the result relative to the input (sqrt of the area ratio).
    pub face_scale: Vec<f64>,
    /// Why the scale-driven phase stopped.
    pub stop_reason: String,
    /// What the linear solvers did (the report's `solver` section).
    pub solver: SolverSummary,
}

/// The linear solvers' work in one run, by phase.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SolverSummary {
    /// The scale-factor solver (Eq. 3), over the whole run.
    pub scale_factors: WorkCounters,
    /// The shape solver during the scale-driven phase (Eq. 7).
    pub scale_driven: WorkCounters,
    /// The shape solver during the fine-tune (Eq. 8).
    pub fine_tune: WorkCounters,
    /// Per scale-driven outer iteration: both solvers' work in it, and its
    /// wall seconds.
    pub outer: Vec<OuterIteration>,
    /// Stored 3x3 blocks of the shape matrix, both triangles: one set of its
    /// values is `72 * shape_blocks` bytes in f64.
    pub shape_blocks: usize,
}

/// One scale-driven outer iteration's solver work.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OuterIteration {
    pub work: WorkCounters,
    pub seconds: f64,
}

impl SolverSummary {
    fn phases(&self) -> [&WorkCounters; 3] {
        [&self.scale_factors, &self.scale_driven, &self.fine_tune]
    }

    /// Most iterations of any one solve.
    pub fn iterations_max(&self) -> usize {
        self.phases()
            .iter()
            .map(|w| w.iterations_max)
            .max()
            .unwrap_or(0)
    }

    /// Seconds the host waited for the GPU.
    pub fn device_seconds(&self) -> f64 {
        self.phases().iter().map(|w| w.device_seconds).sum()
    }

    /// Seconds the device spent in the PCG passes, by timestamp queries; None
    /// where no pass was timed (CPU backend, or an adapter without them).
    pub fn device_timed_seconds(&self) -> Option<f64> {
        let phases = self.phases();
        (phases.iter().map(|w| w.device_timed_passes).sum::<u64>() > 0)
            .then(|| phases.iter().map(|w| w.device_timed_seconds).sum())
    }

    /// Bytes moved between host and device, both ways.
    pub fn transfer_bytes(&self) -> u64 {
        self.phases()
            .iter()
            .map(|w| w.bytes_to_device + w.bytes_from_device)
            .sum()
    }
}

/// Both solvers' counters added (the scale-factor one may be absent).
fn work_sum(a: WorkCounters, b: Option<WorkCounters>) -> WorkCounters {
    let b = b.unwrap_or_default();
    WorkCounters {
        preconditioner_setups: a.preconditioner_setups + b.preconditioner_setups,
        solves: a.solves + b.solves,
        iterations: a.iterations + b.iterations,
        iterations_max: a.iterations_max.max(b.iterations_max),
        device_seconds: a.device_seconds + b.device_seconds,
        device_waits: a.device_waits + b.device_waits,
        bytes_to_device: a.bytes_to_device + b.bytes_to_device,
        bytes_from_device: a.bytes_from_device + b.bytes_from_device,
        device_dispatches: a.device_dispatches + b.device_dispatches,
        device_bytes: a.device_bytes + b.device_bytes,
        device_bytes_minimal: a.device_bytes_minimal + b.device_bytes_minimal,
        device_timed_passes: a.device_timed_passes + b.device_timed_passes,
        device_timed_seconds: a.device_timed_seconds + b.device_timed_seconds,
    }
}

/// One `info` line for a phase's solver work.
fn log_work(phase: &str, w: &WorkCounters, seconds: Option<f64>) {
    let time = match seconds {
        Some(t) => format!(
            "{t:.3} s ({:.3} s on the host, ",
            (t - w.device_seconds).max(0.0)
        ),
        None => "(".into(),
    };
    log::info!(
        "{phase}: {time}{:.3} s waiting for the GPU in {} waits), \
         {} preconditioner set-ups, {} solves, {} iterations (most in one solve {}), \
         {} bytes to and {} from the device; kernels: {} dispatches, {} bytes modelled \
         ({} for the operator applications in their least storage); \
         {:.3} s of device time in {} timed passes",
        w.device_seconds,
        w.device_waits,
        w.preconditioner_setups,
        w.solves,
        w.iterations,
        w.iterations_max,
        w.bytes_to_device,
        w.bytes_from_device,
        w.device_dispatches,
        w.device_bytes,
        w.device_bytes_minimal,
        w.device_timed_seconds,
        w.device_timed_passes
    );
}

/// Largest relative metric error.
pub fn max_error(p: &Problem, x: &[DVec3]) -> f64 {
    p.constraints
        .iter()
        .map(|c| c.residual(&p.mesh, x).abs())
        .fold(0.0, f64::max)
}

/// `model.assemble_and_factor` at `x`; with `affine`, the solver is given the
/// vertex positions for the factorization (an iterative backend's AMG then
/// takes the vertices' affine motions as near-null space) and they are
/// cleared after it.
fn assemble_with_positions(
    model: &mut ShapeModel,
    mesh: &Mesh,
    x: &[DVec3],
    s: &[f64],
    c: &[f64],
    w: &ShapeWeights,
    affine: bool,
) -> Result<()> {
    if affine {
        let positions: Vec<[f64; 3]> = x.iter().map(|p| p.to_array()).collect();
        model.solver().set_vertex_positions(&positions);
    }
    let done = model.assemble_and_factor(mesh, x, s, c, w);
    model.solver().set_vertex_positions(&[]);
    done
}

/// The curvature targets `c_i` of Eq. 21: per vertex, the area-weighted
/// mean of its faces' scale factors `s` (1 for a vertex in no face).
pub fn vertex_mean_scale(mesh: &Mesh, areas: &[f64], s: &[f64]) -> Vec<f64> {
    let n = mesh.num_vertices();
    let mut num = vec![0.0; n];
    let mut den = vec![0.0; n];
    for (f, t) in mesh.faces.iter().enumerate() {
        for &v in t {
            num[v as usize] += areas[f] * s[f];
            den[v as usize] += areas[f];
        }
    }
    (0..n)
        .map(|v| if den[v] > 0.0 { num[v] / den[v] } else { 1.0 })
        .collect()
}

/// Run the method on a resolved problem.
pub fn deform(p: &Problem, o: &Options, progress: &mut dyn FnMut(Progress)) -> Result<Outcome> {
    let mesh = &p.mesh;
    let x0 = &mesh.positions;
    let nf = mesh.num_faces();
    let n = mesh.num_vertices();
    let t0 = Instant::now();
    let areas0 = mesh.face_areas(x0);
    let groups: Vec<usize> = p
        .constraints
        .iter()
        .map(|c| match c.kind {
            MetricKind::Length => 0,
            MetricKind::Area => 1,
            MetricKind::Volume => 2,
        })
        .collect();
    // Compact group ids so that per-kind grouping has no empty group.
    let groups = compact(&groups);

    log::debug!(
        "deform: {nf} faces, resident {:.0} MiB at the start",
        crate::report::resident_memory_mb()
    );
    let mut shape_solver = o.backend.shape_solver()?;
    shape_solver.set_system_kind(SystemKind::ScaleDriven);
    let mut model = ShapeModel::with_solver(mesh, &p.topo, p.handles.clone(), shape_solver)?;
    let face_ordering = fill_orderings(p, o, &mut model);
    crate::report::release_free_memory();
    model
        .solver()
        .set_tolerance(SCALE_DRIVEN_TOLERANCE.max(o.backend.fine_tune_tolerance()));
    let mut curvature_factor = vec![1.0; n];
    for r in &p.curvature {
        for &v in &r.vertices {
            curvature_factor[v as usize] *= r.scale;
        }
    }
    let has_curvature = !p.curvature.is_empty();
    let has_handles = !p.handles.is_empty();

    let mut x = x0.clone();
    let mut best = (max_error(p, &x), x.clone());
    let mut iterations = 0usize;
    let mut history: Vec<f64> = Vec::new();
    let mut stop_reason = String::from("no constraints");
    let cap = o.preview.unwrap_or(o.max_iterations);
    let mut summary = SolverSummary {
        shape_blocks: 2 * model.matrix().iso.nnz() - n,
        ..SolverSummary::default()
    };
    let mut scale_factor_work = None;
    if !p.constraints.is_empty() || has_handles || has_curvature {
        let mut scale_system = if p.constraints.is_empty() {
            None
        } else {
            Some(ScaleFactorSystem::with_solver(
                &p.topo.face_pairs,
                &areas0,
                o.k_d,
                o.k_r,
                o.regulariser,
                {
                    let mut solver = o.backend.scale_solver()?;
                    solver.set_system_kind(SystemKind::ScaleFactors);
                    if let Some(order) = face_ordering {
                        solver.set_fill_ordering(FillOrdering::Given(order.into()));
                    }
                    solver
                },
            )?)
        };
        crate::report::release_free_memory();
        stop_reason = "iteration cap".into();
        let mut anderson = Anderson::new(if nf >= o.anderson_from_faces {
            o.anderson_depth
        } else {
            0
        });
        loop {
            let t_iter = Instant::now();
            let before = work_sum(
                model.solver().counters(),
                scale_system.as_ref().map(|s| s.counters()),
            );
            let areas = mesh.face_areas(&x);
            // Eq. 3: scale factors on the current mesh.
            let (s, max_ds) = match scale_system.as_mut() {
                Some(sys) => {
                    let cons: Vec<ScaleConstraint> = p
                        .constraints
                        .iter()
                        .zip(&groups)
                        .map(|(c, &g)| ScaleConstraint {
                            coeffs: c.face_coefficients(mesh, &x, &areas, o.volume_share),
                            degree: c.degree(),
                            target: c.target,
                            group: g,
                        })
                        .collect();
                    let (s, info) = sys.estimate(&cons, o.multipliers)?;
                    log::debug!(
                        "scale factors: {} Newton steps, {:.3} s, resident {:.0} MiB",
                        info.newton_iterations,
                        t_iter.elapsed().as_secs_f64(),
                        crate::report::resident_memory_mb()
                    );
                    let m = s.iter().fold(0.0f64, |m, v| m.max((v - 1.0).abs()));
                    (s, m)
                }
                None => (vec![1.0; nf], 0.0),
            };
            let err = max_error(p, &x);
            progress(Progress::ScaleDriven {
                iteration: iterations,
                max_error: err,
                max_scale_change: max_ds,
            });
            // Stopping rule (Sec. 2.4) plus stagnation and the cap.
            let first_free_step = iterations == 0 && (has_handles || has_curvature);
            if max_ds < o.scale_threshold && !first_free_step {
                stop_reason = format!(
                    "max |s - 1| = {max_ds:.2e} below the threshold {}",
                    o.scale_threshold
                );
                break;
            }
            if iterations >= cap {
                break;
            }
            if history.len() >= 4 {
                let old = history[history.len() - 4];
                if max_ds > 0.9 * old {
                    stop_reason = format!(
                        "stagnation: max |s - 1| = {max_ds:.3} after {iterations} iterations"
                    );
                    break;
                }
            }
            history.push(max_ds);
            // c_i of Eq. 21.
            let mut c = if o.curvature_target == CurvatureTarget::Scaled {
                vertex_mean_scale(mesh, &areas, &s)
            } else {
                vec![1.0; n]
            };
            if iterations == 0 && has_curvature {
                for v in 0..n {
                    c[v] *= curvature_factor[v];
                }
            }
            // Eq. 7 / 19. On large meshes an iterative backend's AMG takes the
            // vertices' affine motions as near-null space here too (see
            // AFFINE_SCALE_DRIVEN_MIN_VERTICES).
            let t_shape = Instant::now();
            let affine = n >= AFFINE_SCALE_DRIVEN_MIN_VERTICES;
            assemble_with_positions(&mut model, mesh, &x, &s, &c, &o.shape, affine)?;
            let t_solve = Instant::now();
            let g = model.solve_unconstrained(&x)?;
            // The first step of a curvature job has its own targets (Eq. 21 factors
            // applied once): accelerate from the second step on.
            x = if iterations == 0 {
                g
            } else {
                let (next, info) = anderson.step(&x, g);
                log::debug!(
                    "anderson: {} columns, |G(x) - x| {:.3e}{}",
                    info.columns,
                    info.residual,
                    if info.restarted { ", restarted" } else { "" }
                );
                next
            };
            iterations += 1;
            let work = work_sum(
                model.solver().counters(),
                scale_system.as_ref().map(|s| s.counters()),
            )
            .since(&before);
            summary.outer.push(OuterIteration {
                work,
                seconds: t_iter.elapsed().as_secs_f64(),
            });
            log::debug!(
                "outer iteration {iterations}: max |s-1| {max_ds:.4}, assemble+factor {:.3} s, solve {:.3} s, total {:.3} s, resident {:.0} MiB (peak {:.0})",
                (t_solve - t_shape).as_secs_f64(),
                t_solve.elapsed().as_secs_f64(),
                t_iter.elapsed().as_secs_f64(),
                crate::report::resident_memory_mb(),
                crate::report::peak_memory_mb()
            );
            let e = max_error(p, &x);
            if e < best.0 || has_handles || has_curvature {
                best = (e, x.clone());
            }
        }
        scale_factor_work = scale_system.as_ref().map(|s| s.counters());
    }
    let t1 = Instant::now();
    summary.scale_driven = model.solver().counters();
    summary.scale_factors = scale_factor_work.unwrap_or_default();
    log_work(
        "scale-driven phase, shape solver",
        &summary.scale_driven,
        Some((t1 - t0).as_secs_f64()),
    );
    let mut x = best.1;
    let mut ft_iterations = 0;
    if o.preview.is_none() && !p.constraints.is_empty() {
        model
            .solver()
            .set_tolerance(o.backend.fine_tune_tolerance());
        let (xf, it) = fine_tune(p, o, &mut model, &groups, &x, progress)?;
        x = xf;
        ft_iterations = it;
    }
    let t2 = Instant::now();
    summary.fine_tune = model.solver().counters().since(&summary.scale_driven);
    if summary.fine_tune.solves == 0 {
        summary.fine_tune.iterations_max = 0;
    }
    log_work(
        "fine-tune, shape solver",
        &summary.fine_tune,
        Some((t2 - t1).as_secs_f64()),
    );
    log_work("scale factors (whole run)", &summary.scale_factors, None);
    let face_scale = (0..nf)
        .map(|f| {
            let a = mesh.face_area(&x, f);
            if areas0[f] > 0.0 {
                (a / areas0[f]).sqrt()
            } else {
                1.0
            }
        })
        .collect();
    Ok(Outcome {
        positions: x,
        scale_driven_iterations: iterations,
        fine_tune_iterations: ft_iterations,
        seconds_scale_driven: (t1 - t0).as_secs_f64(),
        seconds_fine_tune: (t2 - t1).as_secs_f64(),
        face_scale,
        stop_reason,
        solver: summary,
    })
}

/// The CPU backends' two large factorizations (scale factors on faces, Eq. 3;
/// the shape preconditioner on vertices, Eq. 7) each begin with a METIS nested
/// dissection, several seconds apiece at a million faces. Their patterns are
/// known once the shape model is set up, so both orderings are computed here at
/// the same time on two threads; the shape model's solver gets its ordering, the
/// face ordering is returned for the scale-factor solver. Sizes below
/// [`NESTED_DISSECTION_FROM`] keep the solvers' own (AMD) choice.
fn fill_orderings(p: &Problem, o: &Options, model: &mut ShapeModel) -> Option<Vec<usize>> {
    if !matches!(o.backend, SolverBackend::Cpu | SolverBackend::CpuDirect) {
        return None;
    }
    let (nf, nv) = (p.mesh.num_faces(), p.mesh.num_vertices());
    let faces_big = !p.constraints.is_empty() && nf >= NESTED_DISSECTION_FROM;
    let vertices_big = nv >= NESTED_DISSECTION_FROM;
    if !faces_big || !vertices_big {
        return None;
    }
    let t = Instant::now();
    let h = model.matrix();
    let (faces, vertices) = std::thread::scope(|scope| {
        let faces = scope.spawn(|| {
            let graph = SymCsc::from_pattern(
                nf,
                p.topo
                    .face_pairs
                    .iter()
                    .map(|q| (q[0] as usize, q[1] as usize)),
            );
            nested_dissection_of_pattern(nf, &graph.col_ptr, &graph.row_idx)
        });
        let vertices = nested_dissection_of_pattern(h.n(), &h.iso.col_ptr, &h.iso.row_idx);
        (faces.join().ok().flatten(), vertices)
    });
    log::debug!(
        "fill orderings (faces and vertices, two threads): {:.3} s",
        t.elapsed().as_secs_f64()
    );
    if let Some((forward, _)) = vertices {
        model
            .solver()
            .set_fill_ordering(FillOrdering::Given(forward.into()));
    }
    faces.map(|(forward, _)| forward)
}

fn compact(groups: &[usize]) -> Vec<usize> {
    let mut ids: Vec<usize> = groups.to_vec();
    ids.sort_unstable();
    ids.dedup();
    groups
        .iter()
        .map(|g| ids.binary_search(g).unwrap())
        .collect()
}

/// Eq. 8 (and Eq. 20 with handles): minimise the shape energy relative to the
/// scale-driven result subject to the metrics as hard constraints.
fn fine_tune(
    p: &Problem,
    o: &Options,
    model: &mut ShapeModel,
    groups: &[usize],
    xstart: &[DVec3],
    progress: &mut dyn FnMut(Progress),
) -> Result<(Vec<DVec3>, usize)> {
    let mesh = &p.mesh;
    let n = mesh.num_vertices();
    let nf = mesh.num_faces();
    let ones_f = vec![1.0; nf];
    let ones_v = vec![1.0; n];
    // One factorization for the whole fine-tune (symbolic analysis reused).
    crate::report::release_free_memory();
    model.solver().set_system_kind(SystemKind::FineTune);
    // The fine-tune Hessian (k_m = k_l = 100 k_f) is nearly blind to local
    // affine motions: an AMG of the matrix itself (the GPU's `affine-amg`)
    // takes them as its near-null space (4-7x fewer GPU PCG iterations on
    // spot, BENCHMARKS.md); the GPU's default squared Laplacian ignores them.
    assemble_with_positions(model, mesh, xstart, &ones_f, &ones_v, &o.fine_tune, true)?;
    let goal = 0.01 * o.tolerance;
    let mut dx = vec![0.0; 3 * n];
    let apply = |dx: &[f64]| -> Vec<DVec3> {
        (0..n)
            .map(|v| xstart[v] + DVec3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]))
            .collect()
    };
    let mut x = xstart.to_vec();
    let mut mu: f64 = 0.0;
    let mut it = 0;
    let residuals =
        |x: &[DVec3]| -> Vec<f64> { p.constraints.iter().map(|c| c.residual(mesh, x)).collect() };
    let merit = |model: &ShapeModel, dx: &[f64], c: &[f64], mu: f64| -> f64 {
        model.energy(dx) + mu * c.iter().map(|v| v.abs()).sum::<f64>()
    };
    let mut c = residuals(&x);
    // Solutions of the previous Newton step: the initial guess of iterative solvers.
    let mut warm = Vec::new();
    while it < o.fine_tune_iterations {
        let err = c.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        progress(Progress::FineTune {
            iteration: it,
            max_error: err,
        });
        if err <= goal {
            break;
        }
        let g = model.gradient_at(&dx);
        let neg: Vec<f64> = g.iter().map(|v| -v).collect();
        let rows: Vec<Vec<f64>> = p
            .constraints
            .iter()
            .map(|con| {
                let mut r = vec![0.0; 3 * n];
                con.add_gradient(mesh, &x, 1.0 / con.target, &mut r);
                for v in 0..n {
                    if model.fixed[v] {
                        r[3 * v..3 * v + 3].iter_mut().for_each(|e| *e = 0.0);
                    }
                }
                r
            })
            .collect();
        let mut lin = Linearized {
            values: c.clone(),
            rows,
        };
        if o.multipliers == Multipliers::PerKind {
            lin = lin.grouped(groups);
        }
        let step = constrained_step_warm(model.solver(), neg, lin, &mut warm)?;
        let lam_max = match o.multipliers {
            Multipliers::PerConstraint => step.lambda.iter().fold(0.0f64, |m, l| m.max(l.abs())),
            Multipliers::PerKind => groups
                .iter()
                .zip(&c)
                .map(|(&g, cj)| (2.0 * step.lambda[g] * cj).abs())
                .fold(0.0, f64::max),
        };
        mu = mu.max(2.0 * lam_max + 1e-6);
        let phi0 = merit(model, &dx, &c, mu);
        let mut alpha = 1.0;
        let mut accepted = false;
        while alpha > 1.0 / 1024.0 {
            let trial: Vec<f64> = dx
                .iter()
                .zip(&step.dx)
                .map(|(a, b)| a + alpha * b)
                .collect();
            let xt = apply(&trial);
            let ct = residuals(&xt);
            if merit(model, &trial, &ct, mu) < phi0 {
                dx = trial;
                x = xt;
                c = ct;
                accepted = true;
                break;
            }
            alpha *= 0.5;
        }
        it += 1;
        log::debug!(
            "fine-tune step {it}: step length {alpha}, resident {:.0} MiB (peak {:.0})",
            crate::report::resident_memory_mb(),
            crate::report::peak_memory_mb()
        );
        if !accepted {
            log::info!("fine-tune: line search stalled at iteration {it}");
            break;
        }
    }
    Ok((x, it))
}
