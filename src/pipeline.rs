//! The whole method: scale-driven deformation (Sec. 2.4: Eq. 3 then Eq. 7,
//! iterated) followed by the fine-tune with hard constraints (Eq. 8, solved by
//! sequential linearly constrained Newton steps through the Schur complement of
//! Eqs. 15-18 on a Hessian factored once).

use crate::anderson::Anderson;
use crate::constrained_step::{group_count, Multipliers};
use crate::fine_tune::{fine_tune, FineTuneParams};
use crate::metrics::{MetricKind, VolumeShare};
use crate::problem::{max_error, Problem};
use crate::scale_factors::{Regulariser, ScaleConstraint, ScaleFactorSystem};
use crate::shape::{
    curvature_factors, curvature_targets, CurvatureTarget, ShapeModel, ShapeWeights,
};
use crate::{Error, Mesh, Result};
use glam::DVec3;
use rayon::iter::{
    IndexedParallelIterator, IntoParallelIterator, IntoParallelRefMutIterator, ParallelIterator,
};
use solver_cpu::cholesky::NESTED_DISSECTION_FROM;
use solver_cpu::{
    coordinate_nested_dissection, coordinate_nested_dissection_of_pairs,
    nested_dissection_of_pattern, BlockPcgSolver, CholeskySolver, FactorAhead, FactorPlan,
    FillOrdering, SolverError, SpdSolver, SymCsc, SystemKind, WorkCounters,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// Faces from which the scale factors' system (Eq. 3) is ordered by the
/// nested dissection of the faces' centroids
/// ([`coordinate_nested_dissection_of_pairs`]) instead of minimum degree:
/// homer's factors of that system (2-core development machine,
/// 2026-11-27) had 3.47M values against 3.08M at 108k faces, 15.98M against
/// 16.75M at 432k and 48.5M against 53.2M at 1.2M, for 0.25G flops to
/// factor against 0.24G, 2.1G against 3.3G and 9.9G against 17.0G.
pub const COORDINATE_ORDERING_FACES_FROM: usize = 300_000;

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

    /// Whether its shape solver wants METIS's ordering of the shape
    /// factor ([`SpdSolver::wants_nested_dissection`]), known before the
    /// solver is opened: the ordering starts while a GPU's device opens.
    /// The opened solvers agree (tested).
    pub fn wants_nested_dissection(self) -> bool {
        match self {
            SolverBackend::Cpu | SolverBackend::CpuDirect => true,
            SolverBackend::Gpu => false,
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
/// (BENCHMARKS.md, "`auto` crossover"). `None` would mean at no measured
/// size. On an NVIDIA H100 against its 16-core host (2026-11-27, the
/// Cholesky preconditioner with teams of lanes) the GPU backend was 11.5x
/// slower on the 5.9k-face demo job, 1.95x slower at 12k faces, even at 48k
/// (1.05x faster, one run), 1.29x and 1.67x faster at 108k (two runs), 2.19x
/// faster at 1.2M and at least 2.0x faster at 4.3M: from 100k faces on it was
/// faster in every run.
pub const GPU_FASTER_FROM_FACES: Option<usize> = Some(100_000);

/// Whether `--backend auto` runs a mesh of `faces` faces on the GPU: only on
/// a hardware adapter (never a CPU emulation such as lavapipe) and only from
/// the measured crossover [`GPU_FASTER_FROM_FACES`] on.
pub fn auto_uses_gpu(faces: usize, hardware_adapter: bool) -> bool {
    hardware_adapter && GPU_FASTER_FROM_FACES.is_some_and(|from| faces >= from)
}

/// The backend a name picks ([`choose_backend`]).
#[derive(Debug, Clone)]
pub struct BackendChoice {
    pub backend: SolverBackend,
    /// The GPU adapter (GPU backend only).
    pub adapter: Option<String>,
    /// What to tell the user about the choice.
    pub note: Option<String>,
    /// The note is a fallback or a warning: said even when asked to be quiet.
    pub note_always: bool,
}

/// The backend `name` (`auto`, `cpu` or `gpu`) picks for a mesh of `faces`
/// faces: `auto` is the GPU on a hardware adapter from the measured crossover
/// on ([`auto_uses_gpu`]), else the CPU; `gpu` without a usable adapter is
/// bad input.
pub fn choose_backend(name: &str, faces: usize) -> Result<BackendChoice> {
    let cpu = |note: Option<String>, note_always| BackendChoice {
        backend: SolverBackend::Cpu,
        adapter: None,
        note,
        note_always,
    };
    match name {
        "cpu" => Ok(cpu(None, false)),
        "gpu" => match solver_gpu::default_adapter() {
            Ok(a) => Ok(BackendChoice {
                backend: SolverBackend::Gpu,
                note: (a.device_type == "Cpu").then(|| {
                    format!(
                        "warning: --backend gpu runs on {}, a CPU emulation of a GPU: expect it to be \
                         far slower than --backend cpu (250-300x measured on the demo)",
                        a.name
                    )
                }),
                note_always: true,
                adapter: Some(a.name),
            }),
            Err(why) => Err(Error::bad(format!(
                "--backend gpu: no usable GPU adapter: {why}"
            ))),
        },
        "auto" => Ok(match solver_gpu::default_adapter() {
            Ok(a) if auto_uses_gpu(faces, a.device_type != "Cpu") => BackendChoice {
                backend: SolverBackend::Gpu,
                note: Some(format!("backend: gpu (auto: adapter {}, {faces} faces)", a.name)),
                note_always: false,
                adapter: Some(a.name),
            },
            Ok(a) if a.device_type != "Cpu" => cpu(
                Some(format!(
                    "backend: cpu (auto: the GPU backend is measured faster than the CPU {}, \
                     not at {faces} faces; --backend gpu uses {} anyway)",
                    GPU_FASTER_FROM_FACES
                        .map_or("at no size".into(), |f| format!("from {f} faces on")),
                    a.name
                )),
                false,
            ),
            Ok(a) => cpu(
                Some(format!(
                    "backend: cpu (auto: the only adapter, {}, is a CPU emulation; --backend gpu \
                     uses it anyway)",
                    a.name
                )),
                true,
            ),
            Err(why) => cpu(Some(format!("backend: cpu (auto: {why})")), true),
        }),
        other => Err(Error::bad(format!(
            "unknown backend '{other}': expected auto, cpu or gpu"
        ))),
    }
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
    /// Whether a backend that factors the shape systems' `K` ahead on other
    /// threads (the GPU's) starts the scale-driven kind's factorization,
    /// from the input's positions, as soon as `K`'s symbolic analysis is
    /// made (`Some(true)`), beside the scale factors' set-up, rather than
    /// after that set-up (`Some(false)`). Either way the fine-tune's starts
    /// once the scale-driven kind's is handed over, and the factors, and so
    /// the result, are the same to the bit. `None` (the default): where
    /// rayon has at least [`OVERLAP_FACTORIZATIONS_FROM_THREADS`] threads
    /// ([`overlaps_factorizations`]). On an H200's 16-core host it took homer
    /// 1.2M's GPU run from 15.2 to 13.0 s, its host peak (VmHWM) 2,748
    /// against 2,721 MiB: the peak is set later, by the fine-tune's factor.
    /// On the 2-core development machine it raised the Rust heap's peak to
    /// 2,676 MiB against 2,217, and no speed-up was to be seen there.
    pub overlap_factorizations: Option<bool>,
    /// Checked at every progress report: once set, the run stops with
    /// [`Error::Interrupted`].
    pub interrupt: Option<Arc<AtomicBool>>,
}

impl Options {
    /// [`Error::Interrupted`] once the interrupt flag is set.
    pub fn check_interrupt(&self) -> Result<()> {
        match &self.interrupt {
            Some(flag) if flag.load(Ordering::Relaxed) => Err(Error::Interrupted),
            _ => Ok(()),
        }
    }
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
            overlap_factorizations: None,
            backend: SolverBackend::Cpu,
            interrupt: None,
        }
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
        setups_from_factors_ahead: a.setups_from_factors_ahead + b.setups_from_factors_ahead,
        solves: a.solves + b.solves,
        iterations: a.iterations + b.iterations,
        iterations_max: a.iterations_max.max(b.iterations_max),
        device_seconds: a.device_seconds + b.device_seconds,
        device_waits: a.device_waits + b.device_waits,
        device_waits_beside: a.device_waits_beside + b.device_waits_beside,
        submit_seconds: a.submit_seconds + b.submit_seconds,
        bytes_to_device: a.bytes_to_device + b.bytes_to_device,
        bytes_from_device: a.bytes_from_device + b.bytes_from_device,
        device_dispatches: a.device_dispatches + b.device_dispatches,
        device_bytes: a.device_bytes + b.device_bytes,
        device_bytes_minimal: a.device_bytes_minimal + b.device_bytes_minimal,
        device_serial_steps: a.device_serial_steps + b.device_serial_steps,
        device_timed_passes: a.device_timed_passes + b.device_timed_passes,
        device_timed_seconds: a.device_timed_seconds + b.device_timed_seconds,
        device_compiles: a.device_compiles + b.device_compiles,
        device_compile_seconds: a.device_compile_seconds + b.device_compile_seconds,
        device_compiles_ahead: a.device_compiles_ahead + b.device_compiles_ahead,
        device_compile_ahead_seconds: a.device_compile_ahead_seconds
            + b.device_compile_ahead_seconds,
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
        "{phase}: {time}{:.3} s waiting for the GPU in {} waits; {} more on threads beside), \
         {} preconditioner set-ups, {} solves, {} iterations (most in one solve {}), \
         {} bytes to and {} from the device, {:.3} s in queue submissions; kernels: {} dispatches, \
         {} bytes modelled ({} for the operator applications in their least storage), \
         {} serial steps; {:.3} s of device time in {} timed passes; {} pipelines compiled \
         at their first use in {:.3} s, {} ahead on another thread in {:.3} s",
        w.device_seconds,
        w.device_waits,
        w.device_waits_beside,
        w.preconditioner_setups,
        w.solves,
        w.iterations,
        w.iterations_max,
        w.bytes_to_device,
        w.bytes_from_device,
        w.submit_seconds,
        w.device_dispatches,
        w.device_bytes,
        w.device_bytes_minimal,
        w.device_serial_steps,
        w.device_timed_seconds,
        w.device_timed_passes,
        w.device_compiles,
        w.device_compile_seconds,
        w.device_compiles_ahead,
        w.device_compile_ahead_seconds
    );
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
        crate::memory::resident_memory_mb()
    );
    // The scale factors' set-up (its pattern, symbolic analysis and factor;
    // Eq. 3) needs the input alone: it starts now, beside the shape model's,
    // and takes a solver on the shape solver's device where it has one.
    let mut scale_early = (!p.constraints.is_empty()).then(|| start_scale_system(p, o, &areas0));
    // The shape systems' fill ordering (`shape_fill_ordering`) and the
    // symbolic analysis of their `K` need the faces alone: the pattern and
    // its ordering start now on their own thread, while the solver (on a
    // GPU, its device: 0.24 s on the H200) is opened; the analysis once the
    // solver has said how it factors (`ShapeWork::hand`).
    let shape_steps = !p.constraints.is_empty() || !p.handles.is_empty() || !p.curvature.is_empty();
    let large = n >= NESTED_DISSECTION_FROM;
    let nested = large && o.backend.wants_nested_dissection();
    let ordering = if nested {
        ShapeOrdering::Metis
    } else if large {
        ShapeOrdering::Coordinates
    } else {
        ShapeOrdering::Solvers
    };
    // The pattern made on the shape pattern's thread, shared with the model.
    let (pattern_tx, pattern_rx) = std::sync::mpsc::channel();
    let pattern_ready = Arc::new(AtomicBool::new(false));
    let shape_work = shape_steps
        .then(|| start_shape_work(mesh, ordering, (pattern_tx, pattern_ready.clone())))
        .flatten();
    let mut shape_solver = o.backend.shape_solver()?;
    if let Some(early) = scale_early.as_mut() {
        early.give_solver(shape_solver.sibling());
    }
    shape_solver.set_system_kind(SystemKind::ScaleDriven);
    let fine_tune_follows = o.preview.is_none() && !p.constraints.is_empty();
    // A GPU's pipelines for the shape solves, compiled on another thread
    // while the systems are set up: one column in the scale-driven phase;
    // the fine-tune's first step solves one more than its multipliers.
    if shape_steps {
        shape_solver.warm_up(SystemKind::ScaleDriven, &[1]);
    }
    if fine_tune_follows {
        let m = multiplier_count(&groups, o.multipliers);
        shape_solver.warm_up(SystemKind::FineTune, &[m + 1, m]);
    }
    if ordering == ShapeOrdering::Coordinates {
        // Where no analysis is made ahead (no thread), the solver's own.
        shape_solver.set_fill_ordering(FillOrdering::Amd);
    }
    let analyser = shape_steps
        .then(|| shape_solver.isotropic_analyser())
        .flatten();
    let (mut analysis_early, ordering_early) = match shape_work {
        Some(work) => work.hand(analyser, nested),
        None => (None, None),
    };
    let mut ordering_early = match (nested && analysis_early.is_none(), ordering_early) {
        (true, None) => start_shape_ordering(mesh),
        (_, early) => early,
    };
    let mut model = ShapeModel::with_solver_and_pattern(
        mesh,
        &p.topo,
        p.handles.clone(),
        shape_solver,
        Some(crate::shape::SharedPattern {
            pattern: pattern_rx,
            ready: pattern_ready,
        }),
    )?;
    if nested && analysis_early.is_none() {
        shape_fill_ordering(&mut model, ordering_early.take());
    }
    crate::memory::release_free_memory();
    model
        .solver()
        .set_tolerance(SCALE_DRIVEN_TOLERANCE.max(o.backend.fine_tune_tolerance()));
    let curvature_factor = curvature_factors(n, &p.curvature);
    let has_curvature = !p.curvature.is_empty();
    let has_handles = !p.handles.is_empty();

    let mut x = x0.clone();
    let mut best = (max_error(p, &x), x.clone());
    // The largest metric error at `x`, measured once per position (the
    // end of one outer iteration reports the start of the next).
    let mut err_at_x = best.0;
    let mut iterations = 0usize;
    let mut history: Vec<f64> = Vec::new();
    let mut stop_reason = String::from("no constraints");
    let cap = o.preview.unwrap_or(o.max_iterations);
    let mut summary = SolverSummary {
        shape_blocks: 2 * model.matrix().iso.nnz() - n,
        ..SolverSummary::default()
    };
    let mut scale_factor_work = None;
    let mut fine_tune_ahead = None;
    let mut scale_system_dropped = None;
    if !p.constraints.is_empty() || has_handles || has_curvature {
        let make_scale_system = |early: Option<ScaleEarly>| {
            move || -> Result<Option<ScaleFactorSystem>> { early.map(ScaleEarly::join).transpose() }
        };
        // Where asked for, the scale-driven kind's factor of the input's
        // `K` starts as soon as `K`'s symbolic analysis is made, beside the
        // scale factors' set-up (`Options::overlap_factorizations`).
        let early = ScaleDrivenFromAnalysis::prepare(&mut model, mesh, &x, o);
        // A solver that makes no factor ahead needs the analysis at its
        // first shape step only: the first scale factors are estimated
        // meanwhile (the CPU backend's METIS, 4.8 s at 1.2M, runs on).
        let factors_ahead = model
            .solver()
            .isotropic_factor_plan(SystemKind::ScaleDriven)
            .is_some();
        // The fine-tune's `K` of the input (its factor's, made ahead from
        // the first outer iteration on) is assembled while the scale
        // factors' set-up is waited for.
        // A solver that factors on its device takes the fine-tune's `K` of
        // the input at the second outer iteration, where its GPU idles while
        // the host assembles the shape matrix.
        let fine_tune_on_device = fine_tune_follows
            && model
                .solver()
                .factors_isotropic_on_device(SystemKind::FineTune);
        let fine_tune_k = |model: &ShapeModel| {
            (fine_tune_follows && (factors_ahead || fine_tune_on_device))
                .then(|| isotropic_part_logged(model, mesh, x0, &o.fine_tune, SystemKind::FineTune))
        };
        // A solver that makes the factor on its device from `K`'s values
        // (the GPU backend's `METRICDEFORM_GPU_FACTORIZATION=gpu`) gets the
        // input's `K` once the first scale factors are estimated (the device
        // runs its work in the order given, and the estimation waits for
        // its own): the device factors while the host assembles the first
        // shape matrix. It is assembled while the scale factors' set-up
        // runs on.
        let scale_driven_on_device = model
            .solver()
            .factors_isotropic_on_device(SystemKind::ScaleDriven);
        let scale_driven_k_of = |model: &ShapeModel| {
            isotropic_part_logged(model, mesh, x0, &o.shape, SystemKind::ScaleDriven)
        };
        let mut scale_driven_k = None;
        // The scale-driven kind's factor went to the device in slices
        // beside the scale factors' set-up; its other slices go once the
        // first scale factors are estimated.
        let mut scale_driven_sliced = false;
        let (mut scale_system, early, mut fine_tune_k) = if analysis_early.is_some()
            && !factors_ahead
        {
            // Assembled while the scale factors' set-up runs on; so is
            // the scale-driven kind's factorization on the device
            // recorded, on the analysis: at homer 4.3M on the H200 its
            // recording took 0.80 s after the first estimation, while
            // the scale factors' set-up ran on for 1.5 s after the main
            // thread had assembled `K`. The scale-driven kind's `K`
            // comes first (the fine-tune's took 0.72 s before it there).
            scale_driven_k = scale_driven_on_device.then(|| scale_driven_k_of(&model));
            if let Some(k) = &scale_driven_k {
                if let Some(analysis) = analysis_early.take() {
                    adopt_early_analysis(&mut model, analysis);
                }
                model
                    .solver()
                    .prepare_factor_on_device(SystemKind::ScaleDriven, k);
            }
            let mut k = None;
            let mut assemble = |model: &ShapeModel| k = fine_tune_k(model);
            match scale_driven_k.take() {
                Some(sd) => {
                    scale_driven_sliced =
                        scale_driven_factor_beside(&mut model, &sd, scale_early.as_ref(), assemble);
                    // Else submitted once the first scale factors are
                    // estimated (the device runs its work in the order
                    // given, and the estimation waits for its own).
                    scale_driven_k = (!scale_driven_sliced).then_some(sd);
                }
                None => assemble(&model),
            }
            let scale_system = make_scale_system(scale_early.take())()?;
            // One more slice while the host makes the first estimation's
            // coefficients.
            if scale_driven_sliced {
                model.solver().advance_factor_on_device();
            }
            (scale_system, None, k)
        } else {
            let analysis = analysis_early.take();
            scale_system_beside_analysis(
                &mut model,
                make_scale_system(scale_early.take()),
                early,
                analysis,
                fine_tune_k,
            )?
        };
        crate::memory::release_free_memory();
        // Else the first shape matrix's `K` (it depends on the positions and
        // weights only) is factored while the first scale factors are
        // estimated. The fine-tune's is started at the first outer
        // iteration either way, once the scale-driven kind's is handed over.
        let mut scale_driven_ahead = early.or_else(|| {
            factor_ahead(
                &mut model,
                (mesh, &x),
                &o.shape,
                SystemKind::ScaleDriven,
                None,
            )
        });
        if scale_driven_ahead.is_none() && scale_driven_on_device && !scale_driven_sliced {
            // Its factor is of the analysis made from the start (the
            // positions' ordering), waited for here.
            if let Some(analysis) = analysis_early.take() {
                adopt_early_analysis(&mut model, analysis);
            }
            scale_driven_k.get_or_insert_with(|| scale_driven_k_of(&model));
        }
        stop_reason = "iteration cap".into();
        // The constraints in scale-factor form; their coefficients are
        // refilled at every iteration.
        let mut cons: Vec<ScaleConstraint> = p
            .constraints
            .iter()
            .zip(&groups)
            .map(|(c, &g)| ScaleConstraint {
                coeffs: Vec::new(),
                degree: c.degree(),
                target: c.target,
                group: g,
            })
            .collect();
        let mut anderson = Anderson::new(if nf >= o.anderson_from_faces {
            o.anderson_depth
        } else {
            0
        });
        loop {
            // The fine-tune's factor, once made, goes to the solver at once
            // (the GPU uploads it): the host need not hold it meanwhile. It
            // is the fine-tune kind's set-up, made early: its upload and
            // time count in the scale-driven phase's totals, not in an
            // outer iteration's (the set-up itself in the fine-tune's).
            // Not before the scale-driven kind's set-up, in the first, has
            // taken its own factor made ahead: the solver keeps one such.
            if iterations > 0
                && fine_tune_ahead
                    .as_ref()
                    .is_some_and(FactorAhead::is_finished)
            {
                let ahead = fine_tune_ahead.take().unwrap();
                adopt_factor_ahead(&mut model, ahead, SystemKind::FineTune);
            }
            let t_iter = Instant::now();
            let before = work_sum(
                model.solver().counters(),
                scale_system.as_ref().map(|s| s.counters()),
            );
            let areas = mesh.face_areas(&x);
            // The host's parts of the iteration, for the debug line at its
            // end: areas and coefficients, estimation, curvature targets.
            let mut parts = [0.0f64; 3];
            // Eq. 3: scale factors on the current mesh.
            let (s, max_ds) = match scale_system.as_mut() {
                Some(sys) => {
                    // The constraints at once (a volume's walks every face).
                    cons.par_iter_mut().zip(&p.constraints).for_each(|(sc, c)| {
                        c.face_coefficients_into(mesh, &x, &areas, o.volume_share, &mut sc.coeffs)
                    });
                    parts[0] = t_iter.elapsed().as_secs_f64();
                    let waited = sys.counters().device_seconds;
                    let (s, info) = sys.estimate(&cons, o.multipliers)?;
                    let waited = sys.counters().device_seconds - waited;
                    let seconds = t_iter.elapsed().as_secs_f64();
                    log::debug!(
                        "scale factors: {} Newton steps, {seconds:.3} s ({:.3} s of it on the host, \
                         GPU waits excluded), resident {:.0} MiB",
                        info.newton_iterations,
                        seconds - waited,
                        crate::memory::resident_memory_mb()
                    );
                    let m = s.iter().fold(0.0f64, |m, v| m.max((v - 1.0).abs()));
                    parts[1] = t_iter.elapsed().as_secs_f64() - parts[0];
                    (s, m)
                }
                None => (vec![1.0; nf], 0.0),
            };
            let err = err_at_x;
            progress(Progress::ScaleDriven {
                iteration: iterations,
                max_error: err,
                max_scale_change: max_ds,
            });
            o.check_interrupt()?;
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
            // c_i of Eq. 21; the curvature regions' factors in the first step only.
            let t_curvature = Instant::now();
            let c = curvature_targets(
                &model,
                mesh,
                &areas,
                &s,
                o.curvature_target,
                (iterations == 0 && has_curvature).then_some(&curvature_factor[..]),
            );
            parts[2] = t_curvature.elapsed().as_secs_f64();
            // Eq. 7 / 19. On large meshes an iterative backend's AMG takes the
            // vertices' affine motions as near-null space here too (see
            // AFFINE_SCALE_DRIVEN_MIN_VERTICES).
            if let Some(k) = scale_driven_k.take() {
                model
                    .solver()
                    .factor_isotropic_on_device(SystemKind::ScaleDriven, &k, 1);
            }
            if std::mem::take(&mut scale_driven_sliced) {
                finish_factor_submission(&mut model);
            }
            // A slice of the fine-tune's factor while the host makes the
            // shape matrix (the scale factors' estimation, which waits for
            // the device, is done).
            if fine_tune_on_device && iterations >= 1 {
                fine_tune_factor_slice(&mut model, &mut fine_tune_k);
            }
            let t_shape = Instant::now();
            let shape_before = model.solver().counters();
            let affine = n >= AFFINE_SCALE_DRIVEN_MIN_VERTICES;
            // The first matrix's terms are summed while its kind's factor
            // made ahead may still be on its way (the factor is not read
            // by them), then the factor is taken and the matrix handed
            // over: at homer 1.2M on an H200's host the main thread waited
            // 1.46 s for the factor, then assembled for 0.47 s.
            let ahead = scale_driven_ahead.take();
            if ahead.is_some() {
                model.assemble(mesh, &x, &s, &c, &o.shape)?;
            }
            let assembled = ahead.is_some();
            if let Some(ahead) = ahead {
                adopt_factor_ahead(&mut model, ahead, SystemKind::ScaleDriven);
            }
            if let Some(analysis) = analysis_early.take() {
                adopt_early_analysis(&mut model, analysis);
            }
            match assembled {
                true => model.hand_over_with_positions(&x, &o.shape, affine)?,
                false => model.assemble_with_positions(mesh, &x, &s, &c, &o.shape, affine)?,
            }
            // Also where the device refused the scale-driven kind's factor
            // (the same pattern): the host makes the fine-tune's ahead.
            if iterations == 0
                && fine_tune_follows
                && !model
                    .solver()
                    .factors_isotropic_on_device(SystemKind::FineTune)
            {
                fine_tune_ahead = factor_ahead(
                    &mut model,
                    (mesh, &x),
                    &o.fine_tune,
                    SystemKind::FineTune,
                    fine_tune_k.take(),
                );
            }
            let t_solve = Instant::now();
            let g = model.solve_unconstrained(&x)?;
            let solved = t_solve.elapsed().as_secs_f64();
            // And one while the host takes the Anderson step, measures, and
            // makes the next estimation's coefficients (the scale-driven
            // kind has taken its own factor by now).
            if fine_tune_on_device {
                fine_tune_factor_slice(&mut model, &mut fine_tune_k);
            }
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
                "outer iteration {iterations}: max |s-1| {max_ds:.4}, assemble+factor {:.3} s, solve {:.3} s \
                 (shape step {:.3} s on the host, GPU waits excluded, {:.3} s of it in queue submissions), \
                 total {:.3} s, resident {:.0} MiB (peak {:.0})",
                (t_solve - t_shape).as_secs_f64(),
                t_solve.elapsed().as_secs_f64(),
                t_shape.elapsed().as_secs_f64()
                    - (model.solver().counters().device_seconds - shape_before.device_seconds),
                model.solver().counters().submit_seconds - shape_before.submit_seconds,
                t_iter.elapsed().as_secs_f64(),
                crate::memory::resident_memory_mb(),
                crate::memory::peak_memory_mb()
            );
            let t_metrics = Instant::now();
            let e = max_error(p, &x);
            err_at_x = e;
            if e < best.0 || has_handles || has_curvature {
                best = (e, x.clone());
            }
            log::debug!(
                "outer iteration {iterations}, its parts: areas and coefficients {:.3} s, \
                 estimation {:.3} s, curvature targets {:.3} s, shape matrix {:.3} s, solve \
                 {solved:.3} s, Anderson {:.3} s, metrics {:.3} s",
                parts[0],
                parts[1],
                parts[2],
                (t_solve - t_shape).as_secs_f64(),
                (t_metrics - t_solve).as_secs_f64() - solved,
                t_metrics.elapsed().as_secs_f64()
            );
        }
        scale_factor_work = scale_system.as_ref().map(|s| s.counters());
        // Its solver (on a GPU, its device and buffers) is released while
        // the fine-tune runs.
        scale_system_dropped = scale_system.map(drop_beside);
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
    if let Some(analysis) = analysis_early.take() {
        adopt_early_analysis(&mut model, analysis);
    }
    if fine_tune_follows {
        if let Some(ahead) = fine_tune_ahead.take() {
            adopt_factor_ahead(&mut model, ahead, SystemKind::FineTune);
        }
        model
            .solver()
            .set_tolerance(o.backend.fine_tune_tolerance());
        let params = FineTuneParams {
            weights: o.fine_tune,
            tolerance: o.tolerance,
            max_iterations: o.fine_tune_iterations,
            multipliers: o.multipliers,
        };
        let mut report = |iteration, max_error| {
            progress(Progress::FineTune {
                iteration,
                max_error,
            });
            o.check_interrupt()
        };
        let (xf, it) = fine_tune(p, &params, &mut model, &groups, &x, &mut report)?;
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
        .into_par_iter()
        .map(|f| {
            let a = mesh.face_area(&x, f);
            if areas0[f] > 0.0 {
                (a / areas0[f]).sqrt()
            } else {
                1.0
            }
        })
        .collect();
    if let Some(thread) = scale_system_dropped.flatten() {
        if let Err(panic) = thread.join() {
            std::panic::resume_unwind(panic);
        }
    }
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

/// `value` dropped on a thread of its own, to be joined (`None`: no thread
/// could be had, and it was dropped here).
fn drop_beside<T: Send + 'static>(value: T) -> Option<std::thread::JoinHandle<()>> {
    std::thread::Builder::new()
        .name("drop beside".into())
        .spawn(move || drop(value))
        .inspect_err(|e| log::debug!("no thread to drop on ({e}): dropped here"))
        .ok()
}

/// A solver opened for another system of the run ([`SpdSolver::sibling`]).
type SolverMade = std::result::Result<Box<dyn SpdSolver>, SolverError>;

/// The scale factors' system (Eq. 3) being set up on its own thread, which
/// waits for its solver ([`ScaleEarly::give_solver`]) once its host work is
/// done; or, where no thread could be made, to be set up when joined.
enum ScaleEarly {
    Started(
        std::thread::JoinHandle<Result<ScaleFactorSystem>>,
        std::sync::mpsc::Sender<Option<SolverMade>>,
    ),
    Later(std::sync::Arc<ScaleSetUp>, Option<Option<SolverMade>>),
}

impl ScaleEarly {
    /// The set-up's solver: `Some`, a sibling of the shape solver's;
    /// `None`, the backend's own.
    fn give_solver(&mut self, solver: Option<SolverMade>) {
        match self {
            // A set-up that failed before its solver came wants none.
            ScaleEarly::Started(_, tx) => tx.send(solver).unwrap_or_default(),
            ScaleEarly::Later(_, given) => *given = Some(solver),
        }
    }

    /// Whether its thread is done (no thread: nothing runs beside).
    fn is_done(&self) -> bool {
        match self {
            ScaleEarly::Started(handle, _) => handle.is_finished(),
            ScaleEarly::Later(..) => true,
        }
    }

    /// The system set up (joined, or made here).
    fn join(self) -> Result<ScaleFactorSystem> {
        match self {
            ScaleEarly::Started(handle, tx) => {
                drop(tx);
                match handle.join() {
                    Ok(made) => made,
                    Err(panic) => std::panic::resume_unwind(panic),
                }
            }
            ScaleEarly::Later(set_up, given) => {
                let host = set_up.host_part();
                set_up.finish(host, given.flatten())
            }
        }
    }
}

/// What the scale factors' set-up needs, apart from its solver.
struct ScaleSetUp {
    face_pairs: Vec<[u32; 2]>,
    areas: Vec<f64>,
    centroids: Option<Vec<DVec3>>,
    k_d: f64,
    k_r: f64,
    regulariser: Regulariser,
    backend: SolverBackend,
    newton_columns: Option<[usize; 2]>,
}

/// The set-up's host work: its fill ordering, its matrix, and on a GPU that
/// matrix's analysis with its factor ([`factor_ahead_of_its_solver`]), or
/// without, where the GPU is asked to make it
/// (`METRICDEFORM_GPU_FACTORIZATION=gpu`).
struct ScaleHostPart {
    fill: FillOrdering,
    hessian: SymCsc,
    factored: Option<(CholeskySolver, Option<CholeskySolver>)>,
}

impl ScaleSetUp {
    /// Everything the solver is not needed for, on this thread: made while
    /// the shape solver's device is opened.
    fn host_part(&self) -> ScaleHostPart {
        // See shape_fill_ordering. The matrix is made beside the ordering,
        // not after it (0.43 s at homer 4.3M on the development machine).
        let ordering = || {
            let t = Instant::now();
            self.centroids
                .as_ref()
                .and_then(|c| coordinate_nested_dissection_of_pairs(c, &self.face_pairs))
                .map_or(FillOrdering::Amd, |forward| {
                    log::debug!(
                        "fill ordering of the faces (their centroids' nested dissection): {:.3} s",
                        t.elapsed().as_secs_f64()
                    );
                    FillOrdering::Given(forward.into())
                })
        };
        let matrix = || {
            ScaleFactorSystem::hessian(
                &self.face_pairs,
                &self.areas,
                self.k_d,
                self.k_r,
                self.regulariser,
            )
        };
        let (fill, hessian, waited) = crate::ordered::join_timed(ordering, matrix);
        log::debug!(
            "the scale factors' fill ordering and matrix: {waited:.3} s before rayon's threads \
             took them up"
        );
        // A GPU's scale factors are preconditioned by their factor unless
        // another preconditioner is asked for.
        let cholesky =
            solver_gpu::Preconditioner::from_env() == solver_gpu::Preconditioner::Cholesky;
        let on_device = solver_gpu::Factorization::from_env() == solver_gpu::Factorization::Gpu;
        let factored = (self.backend == SolverBackend::Gpu && cholesky)
            .then(|| factor_ahead_of_its_solver(&hessian, &fill, !on_device))
            .flatten();
        ScaleHostPart {
            fill,
            hessian,
            factored,
        }
    }

    /// The system on `solver` (`None`: the backend's own), with the host
    /// part's matrix, ordering and factor.
    fn finish(&self, host: ScaleHostPart, solver: Option<SolverMade>) -> Result<ScaleFactorSystem> {
        let mut solver = match solver {
            Some(made) => made?,
            None => self.backend.scale_solver()?,
        };
        solver.set_system_kind(SystemKind::ScaleFactors);
        if let Some(columns) = self.newton_columns {
            solver.warm_up(SystemKind::ScaleFactors, &columns);
        }
        solver.set_fill_ordering(host.fill);
        if let Some((analysed, factored)) = host.factored {
            solver.adopt_isotropic_analysis(analysed);
            match factored {
                Some(factored) => solver.adopt_isotropic_factor(SystemKind::ScaleFactors, factored),
                // Submitted to the device, which factors while this thread
                // hands the system over; its set-up waits for it. Where the
                // device makes no factor, the set-up makes it on the host.
                None => {
                    solver.factor_isotropic_on_device(SystemKind::ScaleFactors, &host.hessian, 1)
                }
            }
        }
        ScaleFactorSystem::with_hessian(host.hessian, solver)
    }
}

/// The scale factors' matrix analysed and (`numeric`) factored on the host
/// in f64 (a GPU's Cholesky preconditioner of the scale factors, made
/// before its device is open; [`SpdSolver::adopt_isotropic_factor`] takes
/// it where it is of the precision and pattern the solver's set-up wants,
/// and the set-up factors again otherwise): the analysed solver and its
/// factored numeric twin. `None` where either step fails (the set-up
/// reports it). At homer 108k on the H200's host the factor took 0.146 s
/// after a 0.24-s device open.
fn factor_ahead_of_its_solver(
    h: &SymCsc,
    fill: &FillOrdering,
    numeric: bool,
) -> Option<(CholeskySolver, Option<CholeskySolver>)> {
    let t = Instant::now();
    let mut analysed = CholeskySolver::new();
    analysed.supernodal = true;
    analysed.set_fill_ordering(fill.clone());
    analysed.analyse(h).ok()?;
    if !numeric {
        log::debug!(
            "scale factors' matrix analysed on the host before its solver: {:.3} s",
            t.elapsed().as_secs_f64()
        );
        return Some((analysed, None));
    }
    let mut factored = analysed.numeric_twin(false)?;
    factored.prepare(h).ok()?;
    log::debug!(
        "scale factors' factor made on the host before its solver: {:.3} s",
        t.elapsed().as_secs_f64()
    );
    Some((analysed, Some(factored)))
}

/// The scale factors' solver made, analysed and factored on another thread
/// (it depends on the input mesh and the options alone), beside the shape
/// model's set-up and the shape pattern's symbolic analysis: at homer 1.2M
/// they and it take 1.2-1.4 s and 2.2 s on the development machine, one
/// after the other before. Its host work (ordering, matrix, and on a GPU
/// the factor) runs while the shape solver's device is opened; it then
/// waits for its solver ([`ScaleEarly::give_solver`]).
fn start_scale_system(p: &Problem, o: &Options, areas0: &[f64]) -> ScaleEarly {
    // The Newton steps on a GPU take one column per constraint (per
    // constraint multipliers only: the others step on the host); after the
    // first step only the rows of degree above 1 change and are solved.
    let newton_columns = (o.multipliers == Multipliers::PerConstraint).then(|| {
        let changing = p.constraints.iter().filter(|c| c.degree() != 1).count();
        [p.constraints.len(), changing.max(1)]
    });
    let mesh = &p.mesh;
    let centroids = (mesh.faces.len() >= COORDINATE_ORDERING_FACES_FROM).then(|| {
        mesh.faces
            .iter()
            .map(|f| f.iter().map(|&v| mesh.positions[v as usize]).sum::<DVec3>() / 3.0)
            .collect::<Vec<DVec3>>()
    });
    let set_up = std::sync::Arc::new(ScaleSetUp {
        face_pairs: p.topo.face_pairs.clone(),
        areas: areas0.to_vec(),
        centroids,
        k_d: o.k_d,
        k_r: o.k_r,
        regulariser: o.regulariser,
        backend: o.backend,
        newton_columns,
    });
    let (tx, rx) = std::sync::mpsc::channel::<Option<SolverMade>>();
    let mine = set_up.clone();
    let spawned = std::thread::Builder::new()
        .name("scale factors' set-up".into())
        .spawn(move || {
            let host = mine.host_part();
            match rx.recv() {
                Ok(solver) => mine.finish(host, solver),
                Err(_) => Err(Error::Internal(
                    "the run ended before the scale factors' solver was opened".into(),
                )),
            }
        });
    match spawned {
        Ok(handle) => ScaleEarly::Started(handle, tx),
        Err(e) => {
            log::debug!("no thread for the scale factors' set-up ({e}): made when joined");
            ScaleEarly::Later(set_up, None)
        }
    }
}

/// `make_scale_system()` (the scale factors' solver set up and factored,
/// Eq. 3), with the shape solver's symbolic analysis of `K` made at the same
/// time on another thread, where the solver has one to make
/// ([`SpdSolver::isotropic_analyser`]): the analysis depends on `K`'s pattern
/// and fill ordering alone, both known by now, and otherwise stands between
/// the first scale estimate and the first shape solve (2.7-2.8 s at 1.2M
/// faces on the development machine, on both backends). A failed analysis
/// ahead is left to the first factorization, which makes it again and
/// reports what fails. With `early` (where asked for), that thread then
/// starts the scale-driven kind's numeric factorization
/// ([`ScaleDrivenFromAnalysis::start`]); it comes back with the scale system.
/// Where the analysis was made from the start, `meanwhile` runs on this
/// thread after it, before the scale factors' set-up is waited for (at
/// homer 1.2M on the H200's host, 1.7 s of waiting), and its result comes
/// back too.
fn scale_system_beside_analysis<T>(
    model: &mut ShapeModel,
    make_scale_system: impl FnOnce() -> Result<Option<ScaleFactorSystem>>,
    early: Option<ScaleDrivenFromAnalysis>,
    analysis: Option<EarlyAnalysis>,
    meanwhile: impl FnOnce(&ShapeModel) -> Option<T>,
) -> Result<(Option<ScaleFactorSystem>, Option<FactorAhead>, Option<T>)> {
    if let Some(analysis) = analysis {
        let started = match analysis.join_logged() {
            Some(analysed) => {
                let started = early.and_then(|e| e.start(&analysed));
                model.solver().adopt_isotropic_analysis(analysed);
                started
            }
            None => None,
        };
        let made = meanwhile(model);
        return Ok((make_scale_system()?, started, made));
    }
    let Some(analyser) = model.solver().isotropic_analyser() else {
        return Ok((make_scale_system()?, None, None));
    };
    let (made, analysed, seconds) = solver_cpu::analyse_beside_then(
        analyser,
        &model.matrix().iso,
        |analysed| early.and_then(|e| e.start(analysed)),
        make_scale_system,
    );
    let started = match analysed {
        Ok((analysed, started)) => {
            log::debug!(
                "symbolic analysis of the shape systems' K, beside the scale factors' set-up: \
                 {seconds:.3} s"
            );
            model.solver().adopt_isotropic_analysis(analysed);
            started
        }
        Err(e) => {
            log::debug!("symbolic analysis of K ahead: {e}; left to the factorization");
            None
        }
    };
    Ok((made?, started, None))
}

/// From this many of rayon's threads on, [`Options::overlap_factorizations`]
/// is on unless set: the scale-driven kind's factorization and the scale
/// factors' set-up each use several threads, which a 2-core host does not
/// have to spare (BENCHMARKS.md, "Real GPU").
pub const OVERLAP_FACTORIZATIONS_FROM_THREADS: usize = 8;

/// [`Options::overlap_factorizations`], or by default whether rayon's pool
/// (the calling thread's) has [`OVERLAP_FACTORIZATIONS_FROM_THREADS`].
pub fn overlaps_factorizations(o: &Options) -> bool {
    o.overlap_factorizations
        .unwrap_or_else(|| rayon::current_num_threads() >= OVERLAP_FACTORIZATIONS_FROM_THREADS)
}

/// The scale-driven kind's factor of the input's `K`, to be made on another
/// thread as soon as `K`'s symbolic analysis is made
/// ([`scale_system_beside_analysis`]), beside the scale factors' set-up,
/// where [`Options::overlap_factorizations`] asks for it: its `K`
/// (assembled before the analysis: it needs the pattern, not the analysis)
/// and how the shape solver makes its factor
/// ([`SpdSolver::isotropic_factor_plan`]). The fine-tune's is made once this
/// one is handed over ([`factor_ahead`]): both at once held two factors on
/// the host (homer 1.2M: the GPU path's Rust heap peak 3,797 MiB).
struct ScaleDrivenFromAnalysis {
    scale_driven: (SymCsc, FactorPlan),
}

impl ScaleDrivenFromAnalysis {
    /// `None` unless `o` asks for it and the solver makes factors ahead.
    fn prepare(
        model: &mut ShapeModel,
        mesh: &Mesh,
        x: &[DVec3],
        o: &Options,
    ) -> Option<ScaleDrivenFromAnalysis> {
        if !overlaps_factorizations(o) {
            return None;
        }
        let plan = model
            .solver()
            .isotropic_factor_plan(SystemKind::ScaleDriven)?;
        let k = isotropic_part_logged(model, mesh, x, &o.shape, SystemKind::ScaleDriven);
        Some(ScaleDrivenFromAnalysis {
            scale_driven: (k, plan),
        })
    }

    /// On the analysing thread, `analysed` just made: the scale-driven
    /// kind's factorization started on its own thread (`None` where no
    /// twin or thread could be had: it is made after the scale factors'
    /// set-up then, [`factor_ahead`]).
    fn start(self, analysed: &CholeskySolver) -> Option<FactorAhead> {
        let (k, plan) = self.scale_driven;
        log::debug!("ScaleDriven system's factor ahead from the symbolic analysis on");
        FactorAhead::spawn(plan.twin(analysed)?, k)
            .inspect_err(|e| log::debug!("ScaleDriven system's factor of K ahead: {e}"))
            .ok()
    }
}

/// `kind`'s preconditioner, the Cholesky factor of `K` for the weights `w`
/// at the positions `x`, started on another thread where the shape solver
/// makes one ([`SpdSolver::isotropic_factorer`]; the GPU backend, whose
/// host otherwise waits on the GPU for most of the scale-driven iteration).
/// Each kind's numeric factorization stood in the way of its first solve
/// (at 1.2M faces 2.5-2.9 s for the scale-driven kind, 5.5-5.8 s for the
/// fine-tune's). The scale-driven kind's is made from its first matrix's
/// `K` itself (the input's positions), while the first scale factors are
/// estimated: the same factor (or from the symbolic analysis on, where
/// asked for, [`ScaleDrivenFromAnalysis`]). The fine-tune's is made from the
/// input's positions too (where the first scale-driven step starts)
/// instead of the fine-tune's start, while the scale-driven iteration runs,
/// once the scale-driven kind's is handed over (so that the host holds one
/// at a time): another preconditioner of the same systems (the same
/// fine-tune PCG iterations at 108k and 1.2M faces, BENCHMARKS.md), handed
/// to the solver as soon as it is made (the GPU uploads it beside the
/// scale-driven factor, so that the host does not hold it).
/// Dropped unjoined (the iteration stopped before its first step), the
/// thread finishes on its own.
/// Both kinds' factors are numeric twins of the shape systems' symbolic
/// analysis, in its fill ordering (on a GPU, the coordinates' nested
/// dissection, [`shape_fill_ordering`]).
/// `k`, where given, is that `K`, assembled before.
fn factor_ahead(
    model: &mut ShapeModel,
    (mesh, x): (&Mesh, &[DVec3]),
    w: &ShapeWeights,
    kind: SystemKind,
    k: Option<SymCsc>,
) -> Option<FactorAhead> {
    let twin = model.solver().isotropic_factorer(kind)?;
    let k = k.unwrap_or_else(|| isotropic_part_logged(model, mesh, x, w, kind));
    // The fine-tune's is waited for only when the fine-tune starts: its
    // work yields the cores to the scale-driven iteration's.
    let spawned = match kind {
        SystemKind::FineTune => FactorAhead::spawn_in_background(twin, k),
        _ => FactorAhead::spawn(twin, k),
    };
    spawned
        .inspect_err(|e| log::debug!("{kind:?} system's factor of K ahead: {e}"))
        .ok()
}

/// [`ShapeModel::isotropic_part`], for `kind`'s factor made ahead, timed.
fn isotropic_part_logged(
    model: &ShapeModel,
    mesh: &Mesh,
    x: &[DVec3],
    w: &ShapeWeights,
    kind: SystemKind,
) -> SymCsc {
    let t = Instant::now();
    let k = model.isotropic_part(mesh, x, w);
    log::debug!(
        "{kind:?} system's K for its factor ahead assembled in {:.3} s",
        t.elapsed().as_secs_f64()
    );
    k
}

/// Hands the factor `ahead` made for `kind` to the shape solver, once made;
/// a failed one is left to the kind's own set-up, which factors again and
/// reports what fails.
fn adopt_factor_ahead(model: &mut ShapeModel, ahead: FactorAhead, kind: SystemKind) {
    let t = Instant::now();
    match ahead.join() {
        (Ok(factored), seconds) => {
            log::debug!(
                "{kind:?} system's factor of K, made ahead on another thread: {seconds:.3} s \
                 (waited for {:.3} s)",
                t.elapsed().as_secs_f64()
            );
            model.solver().adopt_isotropic_factor(kind, factored);
        }
        (Err(e), _) => log::debug!("{kind:?} system's factor of K ahead: {e}; left to its set-up"),
    }
}

/// The fill-reducing ordering of the shape factor (the preconditioner of
/// Eqs. 7 and 8, on the 2-ring pattern; made on the host, and uploaded as the
/// GPU backend's Cholesky preconditioner), from [`NESTED_DISSECTION_FROM`]
/// vertices on:
/// - METIS nested dissection where the solver wants it
///   ([`SpdSolver::wants_nested_dissection`]: the CPU backend, whose solves
///   stream the factor from host memory; METIS's factors are the smallest,
///   homer 1.2M's 102M values);
/// - else (a GPU's, whose set-ups bound its speed-up) the nested dissection
///   of the vertices' positions ([`coordinate_nested_dissection`]): made on
///   every thread, in 0.57 s at homer 1.2M on the development machine's two
///   against METIS's 4.5 s on one, for 123M values (minimum degree's,
///   the GPU's before, 147M; 71G flops to factor against 112G, 25
///   levels against 26). Both shape kinds' factors are made in it, so the
///   fine-tune's needs no METIS either.
///
/// Below that size the solver's own choice (minimum degree) stands. Both are
/// chosen in [`deform`], before the symbolic analysis starts on its own
/// thread ([`start_shape_analysis`]); this sets a solver that makes no
/// analysis ahead ([`SpdSolver::isotropic_analyser`]) to `early`'s METIS
/// ordering (made since the start, [`start_shape_ordering`]), or makes it
/// here.
///
/// The scale factors' face pattern (Eq. 3) is ordered by minimum degree
/// below [`COORDINATE_ORDERING_FACES_FROM`] faces and by the nested
/// dissection of the faces' centroids from there on ([`start_scale_system`]),
/// on both backends: METIS runs one call at a time
/// ([`nested_dissection_of_pattern`]: its random numbers are global state,
/// and two calls at once gave orderings that differed from run to run).
fn shape_fill_ordering(model: &mut ShapeModel, early: Option<EarlyOrdering>) {
    let t = Instant::now();
    let vertices = match early {
        Some(early) => early.join(),
        None => {
            let h = model.matrix();
            nested_dissection_of_pattern(h.n(), &h.iso.col_ptr, &h.iso.row_idx)
                .map(|(forward, _)| forward)
        }
    };
    log::debug!(
        "fill ordering of the shape pattern (METIS): waited {:.3} s",
        t.elapsed().as_secs_f64()
    );
    if let Some(forward) = vertices {
        model
            .solver()
            .set_fill_ordering(FillOrdering::Given(forward.into()));
    }
}

/// What the thread of the shape pattern's work ([`start_shape_work`],
/// [`start_shape_ordering`]) ends with.
enum ShapeWorkDone {
    /// The solver's analyser, having analysed the pattern in its ordering.
    Analysed(std::result::Result<Box<CholeskySolver>, SolverError>),
    /// The pattern's ordering alone (`forward[new] = old`; `None`: none
    /// was made, or METIS failed), where no analyser came.
    Ordered(Option<Vec<usize>>),
}

/// The shape pattern's METIS nested dissection (`forward[new] = old`),
/// being made on its own thread ([`start_shape_ordering`]).
struct EarlyOrdering(std::thread::JoinHandle<ShapeWorkDone>);

impl EarlyOrdering {
    /// Waits for the ordering: `None` where METIS failed.
    fn join(self) -> Option<Vec<usize>> {
        match self.0.join() {
            Ok(ShapeWorkDone::Ordered(forward)) => forward,
            Ok(ShapeWorkDone::Analysed(_)) => None,
            Err(panic) => std::panic::resume_unwind(panic),
        }
    }
}

/// The symbolic analysis of the shape systems' `K`, being made on its own
/// thread ([`start_shape_work`]).
struct EarlyAnalysis(std::thread::JoinHandle<ShapeWorkDone>);

impl EarlyAnalysis {
    /// Waits for the analysed solver: `None` where the analysis failed
    /// (left to the first factorization, which reports what fails).
    fn join_logged(self) -> Option<CholeskySolver> {
        let t = Instant::now();
        match self.0.join() {
            Ok(ShapeWorkDone::Analysed(Ok(analysed))) => {
                log::debug!(
                    "symbolic analysis of the shape systems' K, made from the start on its own \
                     thread: waited {:.3} s",
                    t.elapsed().as_secs_f64()
                );
                Some(*analysed)
            }
            Ok(ShapeWorkDone::Analysed(Err(e))) => {
                log::debug!("symbolic analysis of K ahead: {e}; left to the factorization");
                None
            }
            Ok(ShapeWorkDone::Ordered(_)) => None,
            Err(_) => {
                log::debug!("symbolic analysis of K ahead panicked; left to the factorization");
                None
            }
        }
    }
}

/// Slices a factor made on the device ahead is submitted in
/// ([`SpdSolver::factor_isotropic_on_device`], then
/// [`SpdSolver::advance_factor_on_device`]). The fine-tune's: the
/// pipeline submits one at each of the scale-driven phase's windows where
/// the device would idle (after each solve, before each shape matrix), the
/// rest at the fine-tune's set-up. Whole, it ran before the second
/// iteration's solve: on the H200 at homer 1.2M that solve took 0.314 s
/// against 0.065-0.078 s for the next ones, at 4.3M 2.225 s against
/// 0.25-0.31 s (the factorization alone 0.26 s and 2.07 s). In five slices,
/// one before each shape matrix, four of them outlasted their windows at
/// 4.3M (about 0.3 s of host work each) by 0.02-0.32 s; ten, two an outer
/// iteration, give the windows after the solves too (six outer iterations
/// give eleven).
const FACTOR_SLICES: usize = 10;

/// The fine-tune's factor made on the device in slices
/// ([`SpdSolver::factor_isotropic_on_device`], then
/// [`SpdSolver::advance_factor_on_device`]): its first slice where `k` is
/// still here, else the next one. Called at the scale-driven phase's two
/// idle windows of the device in each outer iteration, after the solve and
/// before the shape matrix: on the H200 at homer 4.3M, five slices before
/// the shape matrices alone outlasted those windows (about 0.3 s of host
/// work each) by 0.02-0.32 s.
fn fine_tune_factor_slice(model: &mut ShapeModel, k: &mut Option<SymCsc>) {
    match k.take() {
        Some(k) => {
            model
                .solver()
                .factor_isotropic_on_device(SystemKind::FineTune, &k, FACTOR_SLICES)
        }
        None => {
            model.solver().advance_factor_on_device();
        }
    }
}

/// The scale-driven kind's factor on the device in slices while the scale
/// factors' set-up runs on (on the H200 at homer 4.3M its recording was
/// done 1.4 s before the scale factors' factor was submitted, and its 2.0 s
/// on the device came after the first estimation): the first slice now,
/// then one each time the device has done the last, until that set-up is
/// done, so that the scale factors' factor waits for one slice at most.
/// The fine-tune's `K` is assembled while the first slice runs. Whether
/// the factor was started (its other slices go to the device once the
/// first scale factors are estimated: [`finish_factor_submission`]).
fn scale_driven_factor_beside(
    model: &mut ShapeModel,
    k: &SymCsc,
    scale_early: Option<&ScaleEarly>,
    mut meanwhile: impl FnMut(&ShapeModel),
) -> bool {
    let set_up_runs = || scale_early.is_some_and(|e| !e.is_done());
    if !set_up_runs() {
        meanwhile(model);
        return false;
    }
    model
        .solver()
        .factor_isotropic_on_device(SystemKind::ScaleDriven, k, FACTOR_SLICES);
    meanwhile(model);
    loop {
        model.solver().wait_for_device();
        if !set_up_runs() || !model.solver().advance_factor_on_device() {
            return true;
        }
    }
}

/// The slices of the factor on the device not yet submitted, at once.
fn finish_factor_submission(model: &mut ShapeModel) {
    while model.solver().advance_factor_on_device() {}
}

/// The analysis made from the start, waited for and handed to the shape
/// solver, where it was made.
fn adopt_early_analysis(model: &mut ShapeModel, analysis: EarlyAnalysis) {
    if let Some(analysed) = analysis.join_logged() {
        model.solver().adopt_isotropic_analysis(analysed);
    }
    // METIS's and the analysis's scratch, freed on their thread, handed
    // back before the factorization that follows.
    crate::memory::release_free_memory();
}

/// The shape pattern's work on its own thread ([`start_shape_work`]): it
/// waits for the solver's analyser once the pattern is ordered.
struct ShapeWork {
    analyser: std::sync::mpsc::Sender<Option<CholeskySolver>>,
    thread: std::thread::JoinHandle<ShapeWorkDone>,
}

impl ShapeWork {
    /// Hands the thread `analyser` ([`SpdSolver::isotropic_analyser`]):
    /// with one, the analysis being made; without, where `nested`, the METIS
    /// ordering for [`shape_fill_ordering`] (else nothing: the thread ends
    /// on its own).
    fn hand(
        self,
        analyser: Option<CholeskySolver>,
        nested: bool,
    ) -> (Option<EarlyAnalysis>, Option<EarlyOrdering>) {
        let analyses = analyser.is_some();
        // A thread that ended (it panicked) is seen when joined.
        self.analyser.send(analyser).unwrap_or_default();
        match (analyses, nested) {
            (true, _) => (Some(EarlyAnalysis(self.thread)), None),
            (false, true) => (None, Some(EarlyOrdering(self.thread))),
            (false, false) => (None, None),
        }
    }
}

/// On its own thread from the start, on [`crate::shape::shape_pattern`]
/// (the model's pattern, known from the faces): the pattern's `ordering`
/// ([`shape_fill_ordering`]), made while the shape solver is opened, then
/// the symbolic analysis of the shape systems' `K` by the analyser the
/// solver hands over ([`ShapeWork::hand`]; [`SpdSolver::isotropic_analyser`],
/// in the ordering made), beside the shape model's set-up, not after it
/// (homer 1.2M on the development machine: minimum degree's analysis 1.15
/// s; METIS and its analysis 4.8 and 0.4 s; the vertices' nested
/// dissection and its analysis 0.57 and 0.33 s). `None` where no thread could
/// be had (the analysis is then made beside the scale factors' set-up).
fn start_shape_work(
    mesh: &Mesh,
    ordering: ShapeOrdering,
    model: PatternSender,
) -> Option<ShapeWork> {
    let positions = (ordering == ShapeOrdering::Coordinates).then(|| mesh.positions.clone());
    let (tx, rx) = std::sync::mpsc::channel::<Option<CholeskySolver>>();
    let thread = on_shape_pattern(
        mesh,
        "shape pattern's ordering and analysis",
        Some(model),
        move |n, pattern| {
            let (col_ptr, row_idx) = (&pattern.0, &pattern.1);
            let forward = match (ordering, positions) {
                (ShapeOrdering::Metis, _) => shape_nested_dissection(n, col_ptr, row_idx),
                (ShapeOrdering::Coordinates, Some(positions)) => {
                    let t = Instant::now();
                    let (forward, waited) = crate::ordered::on_pool_timed(|| {
                        coordinate_nested_dissection(&positions, col_ptr, row_idx)
                    });
                    log::debug!(
                        "fill ordering of the shape pattern (the vertices' nested dissection), on \
                         its own thread from the start: {:.3} s ({waited:.3} s of it before \
                         rayon's threads took it up)",
                        t.elapsed().as_secs_f64()
                    );
                    forward
                }
                _ => None,
            };
            let Ok(Some(mut analyser)) = rx.recv() else {
                return ShapeWorkDone::Ordered(forward);
            };
            if let Some(forward) = forward {
                analyser.set_fill_ordering(FillOrdering::Given(forward.into()));
            }
            // The model has copied its share by now, as a rule: no copy here.
            let (col_ptr, row_idx) = Arc::try_unwrap(pattern).unwrap_or_else(|p| (*p).clone());
            let pattern = SymCsc {
                n,
                col_ptr,
                row_idx,
                values: Vec::new(),
            };
            ShapeWorkDone::Analysed(analyser.analyse(&pattern).map(|()| Box::new(analyser)))
        },
    )?;
    Some(ShapeWork {
        analyser: tx,
        thread,
    })
}

/// Which fill ordering the shape systems' analysis ahead is made in
/// ([`shape_fill_ordering`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ShapeOrdering {
    /// The solver's own (minimum degree).
    Solvers,
    /// METIS's nested dissection of the pattern.
    Metis,
    /// The nested dissection of the vertices' positions.
    Coordinates,
}

/// The shape pattern's nested dissection ([`nested_dissection_of_pattern`]
/// of [`crate::shape::shape_pattern`]) started on its own thread: it needs
/// the faces alone, so it runs beside the shape model's and the scale
/// factors' set-ups instead of after them (METIS takes 4.8 s at homer 1.2M
/// on the development machine, one thread). `None` where no thread could
/// be had (the caller orders on its own then).
fn start_shape_ordering(mesh: &Mesh) -> Option<EarlyOrdering> {
    on_shape_pattern(mesh, "shape fill ordering", None, |n, pattern| {
        ShapeWorkDone::Ordered(shape_nested_dissection(n, &pattern.0, &pattern.1))
    })
    .map(EarlyOrdering)
}

/// Where the shape pattern's thread sends the pattern for the shape model
/// ([`ShapeModel::with_solver_and_pattern`]), which takes it where it has
/// come by then, instead of making the same pattern again (homer 4.3M:
/// 0.77-1.0 s on the development machine's two threads).
/// It sends the pattern, then sets the flag (the model gives up its own on
/// seeing it).
type PatternSender = (
    std::sync::mpsc::Sender<Arc<(Vec<usize>, Vec<usize>)>>,
    Arc<AtomicBool>,
);

/// `then(n, pattern)` on the shape pattern `(col_ptr, row_idx)` of `mesh`
/// ([`crate::shape::shape_pattern`]), on a thread of its own named `name`,
/// the pattern shared with `model` first where given; `None` where no
/// thread could be had.
fn on_shape_pattern<T: Send + 'static>(
    mesh: &Mesh,
    name: &str,
    model: Option<PatternSender>,
    then: impl FnOnce(usize, Arc<(Vec<usize>, Vec<usize>)>) -> T + Send + 'static,
) -> Option<std::thread::JoinHandle<T>> {
    let (n, faces) = (mesh.num_vertices(), mesh.faces.clone());
    std::thread::Builder::new()
        .name(name.into())
        .spawn(move || {
            let t = Instant::now();
            let (pattern, waited) =
                crate::ordered::on_pool_timed(|| crate::shape::shape_pattern(n, &faces));
            drop(faces);
            log::debug!(
                "shape pattern made on its own thread in {:.3} s ({waited:.3} s of it before \
                 rayon's threads took it up)",
                t.elapsed().as_secs_f64()
            );
            let pattern = Arc::new(pattern);
            if let Some((model, ready)) = model {
                // A model already past its pattern dropped its end.
                model.send(pattern.clone()).unwrap_or_default();
                ready.store(true, Ordering::Release);
            }
            then(n, pattern)
        })
        .inspect_err(|e| log::debug!("no thread for the {name}: {e}"))
        .ok()
}

/// METIS's nested dissection of the shape pattern, `forward[new] = old`.
fn shape_nested_dissection(n: usize, col_ptr: &[usize], row_idx: &[usize]) -> Option<Vec<usize>> {
    let t = Instant::now();
    let forward = nested_dissection_of_pattern(n, col_ptr, row_idx).map(|(forward, _)| forward);
    log::debug!(
        "fill ordering of the shape pattern (METIS), on its own thread from the start: {:.3} s",
        t.elapsed().as_secs_f64()
    );
    forward
}

/// The fine-tune's multipliers (Eq. 8): one per constraint, or one per
/// kind of metric among `groups` (compacted ids).
fn multiplier_count(groups: &[usize], multipliers: Multipliers) -> usize {
    match multipliers {
        Multipliers::PerConstraint => groups.len(),
        Multipliers::PerKind => group_count(groups),
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The shape pattern ([`crate::shape::shape_pattern`]) of an `nx x ny`
    /// grid of vertices cut into triangles, as a diagonally dominant
    /// (so SPD) matrix: -1 off the diagonal, one more than the row's
    /// neighbours on it.
    fn grid_k(nx: usize, ny: usize) -> SymCsc {
        let v = |i: usize, j: usize| (i * ny + j) as u32;
        let faces: Vec<[u32; 3]> = (0..nx - 1)
            .flat_map(|i| (0..ny - 1).map(move |j| (i, j)))
            .flat_map(|(i, j)| {
                [
                    [v(i, j), v(i + 1, j), v(i + 1, j + 1)],
                    [v(i, j), v(i + 1, j + 1), v(i, j + 1)],
                ]
            })
            .collect();
        let n = nx * ny;
        let (col_ptr, row_idx) = crate::shape::shape_pattern(n, &faces);
        let mut neighbours = vec![0.0; n];
        for c in 0..n {
            for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
                if r != c {
                    neighbours[r] += 1.0;
                    neighbours[c] += 1.0;
                }
            }
        }
        let values = (0..n)
            .flat_map(|c| {
                row_idx[col_ptr[c]..col_ptr[c + 1]]
                    .iter()
                    .map(move |&r| (r, c))
            })
            .map(|(r, c)| if r == c { neighbours[c] + 1.0 } else { -1.0 })
            .collect();
        SymCsc {
            n,
            col_ptr,
            row_idx,
            values,
        }
    }

    type Calls = std::sync::Arc<std::sync::Mutex<Vec<String>>>;

    /// A solver that records the calls of a factor made on its device in
    /// slices; its `release`-th wait for the device lets the scale factors'
    /// set-up (a thread waiting for it) end, and returns once it has.
    struct SliceCalls {
        calls: Calls,
        left: usize,
        waits: usize,
        release: usize,
        set_up: Option<(std::sync::mpsc::Sender<()>, std::sync::mpsc::Receiver<()>)>,
    }

    impl SpdSolver for SliceCalls {
        fn prepare(&mut self, _a: &SymCsc) -> std::result::Result<(), SolverError> {
            Ok(())
        }
        fn prepare_blocks(
            &mut self,
            _a: &solver_cpu::BlockSym3,
            _fixed: &[bool],
        ) -> std::result::Result<(), SolverError> {
            Ok(())
        }
        fn solve_in_place(
            &mut self,
            _rhs: &mut [f64],
            _ncols: usize,
        ) -> std::result::Result<solver_cpu::SolveInfo, SolverError> {
            Err(SolverError::NotPrepared)
        }
        fn counters(&self) -> solver_cpu::WorkCounters {
            solver_cpu::WorkCounters::default()
        }
        fn name(&self) -> &str {
            "slice calls"
        }
        fn factor_isotropic_on_device(&mut self, kind: SystemKind, _k: &SymCsc, slices: usize) {
            self.calls
                .lock()
                .unwrap()
                .push(format!("{kind:?} in {slices}"));
            self.left = slices - 1;
        }
        fn advance_factor_on_device(&mut self) -> bool {
            let next = self.left > 0;
            if next {
                self.left -= 1;
                self.calls.lock().unwrap().push("slice".into());
            }
            next
        }
        fn wait_for_device(&mut self) {
            self.calls.lock().unwrap().push("wait".into());
            self.waits += 1;
            if self.waits == self.release {
                let (go, ended) = self.set_up.take().unwrap();
                go.send(()).unwrap();
                ended.recv().unwrap();
                // Past its last statement: the thread is done.
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
        }
    }

    /// The scale-driven kind's factor goes to the device in slices while
    /// the scale factors' set-up runs: the first at once, the fine-tune's
    /// `K` made meanwhile, then one after each wait for the device until
    /// that set-up is done; the rest at once later. Where the set-up is
    /// done first, nothing is submitted beside it.
    #[test]
    fn the_scale_driven_factor_goes_in_slices_while_the_scale_factors_are_set_up() {
        let mesh = Mesh::from_arrays(
            &[[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            &[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap();
        let topo = crate::mesh::topology::Topology::build(&mesh);
        let k = grid_k(3, 3);
        let run = |release: usize, set_up_runs: bool| {
            let calls = Calls::default();
            let (go, wait_go) = std::sync::mpsc::channel::<()>();
            let (ended_tx, ended) = std::sync::mpsc::channel::<()>();
            let thread = std::thread::spawn(move || {
                if set_up_runs {
                    wait_go.recv().unwrap();
                }
                ended_tx.send(()).unwrap();
                Err(crate::Error::Internal("no scale factors here".into()))
            });
            if !set_up_runs {
                ended.recv().unwrap();
                while !thread.is_finished() {
                    std::thread::yield_now();
                }
            }
            let solver = SliceCalls {
                calls: calls.clone(),
                left: 0,
                waits: 0,
                release,
                set_up: Some((go, ended)),
            };
            let mut model =
                ShapeModel::with_solver(&mesh, &topo, Vec::new(), Box::new(solver)).unwrap();
            let early = ScaleEarly::Started(thread, std::sync::mpsc::channel().0);
            let log = calls.clone();
            let sliced = scale_driven_factor_beside(&mut model, &k, Some(&early), |_| {
                log.lock().unwrap().push("fine-tune K".into())
            });
            finish_factor_submission(&mut model);
            assert!(early.join().is_err());
            let calls = calls.lock().unwrap().clone();
            (sliced, calls)
        };
        let slices = |n: usize| vec!["slice".to_string(); n];
        let (sliced, calls) = run(3, true);
        assert!(sliced);
        let mut expected = vec!["ScaleDriven in 10".to_string(), "fine-tune K".into()];
        for _ in 0..2 {
            expected.push("wait".into());
            expected.push("slice".into());
        }
        expected.push("wait".into());
        expected.extend(slices(10 - 1 - 2));
        assert_eq!(calls, expected);
        // The set-up done before the factor's recording: nothing beside it.
        let (sliced, calls) = run(0, false);
        assert!(!sliced);
        assert_eq!(calls, vec!["fine-tune K".to_string()]);
    }

    /// Made from the symbolic analysis on, the scale-driven kind's factor
    /// is a twin of that analysis (the factor the first shape solve would
    /// make), and nothing else is started: the fine-tune's waits for its
    /// hand-over.
    #[test]
    fn from_the_analysis_on_the_scale_driven_factor_is_a_twin() {
        let k = grid_k(30, 20);
        let mut analysed = CholeskySolver::new();
        analysed.supernodal = true;
        analysed.analyse(&k).unwrap();
        let plan = FactorPlan {
            single: false,
            largest_supernode_bytes: u64::MAX,
            inverted: false,
        };
        let early = ScaleDrivenFromAnalysis {
            scale_driven: (k.clone(), plan),
        };
        let mut factored = early.start(&analysed).unwrap().join().0.unwrap();
        assert!(factored.is_factored_on(&analysed));
        let mut direct = CholeskySolver::new();
        direct.prepare(&k).unwrap();
        let b: Vec<f64> = (0..k.n).map(|i| (i as f64 * 0.7).sin()).collect();
        let (mut x, mut y) = (b.clone(), b);
        factored.solve_in_place(&mut x, 1).unwrap();
        direct.solve_in_place(&mut y, 1).unwrap();
        let e = x
            .iter()
            .zip(&y)
            .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
        assert!(e < 1e-12, "{e}");
    }

    /// What a backend says of the shape factor's ordering before its
    /// solver is opened is what the opened solver says (a GPU where one is
    /// at hand).
    #[test]
    fn backends_want_the_ordering_their_solvers_want() {
        for backend in [
            SolverBackend::Cpu,
            SolverBackend::CpuDirect,
            SolverBackend::Gpu,
        ] {
            if backend == SolverBackend::Gpu && !solver_gpu::gpu_available() {
                continue;
            }
            let solver = backend.shape_solver().unwrap();
            assert_eq!(
                backend.wants_nested_dissection(),
                solver.wants_nested_dissection(),
                "{}",
                backend.name()
            );
        }
    }

    /// Unset, the overlap follows the calling thread's rayon pool: on from
    /// [`OVERLAP_FACTORIZATIONS_FROM_THREADS`] threads, off below; set, it
    /// is what was set on any pool.
    #[test]
    fn factorizations_overlap_by_default_on_hosts_with_threads_to_spare() {
        let on = |threads: usize, set: Option<bool>| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let o = Options {
                overlap_factorizations: set,
                ..Options::default()
            };
            pool.install(|| overlaps_factorizations(&o))
        };
        let from = OVERLAP_FACTORIZATIONS_FROM_THREADS;
        assert!(!on(2, None));
        assert!(!on(from - 1, None));
        assert!(on(from, None));
        assert!(on(16, None));
        assert!(on(2, Some(true)));
        assert!(!on(16, Some(false)));
    }
}
