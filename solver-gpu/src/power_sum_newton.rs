//! Drives `shaders/power_sum_newton.wgsl`: the scale factors' estimation
//! (paper Eq. 3) as Newton steps run on the GPU, in f64, with no host work
//! between them.
//!
//! `min (s - 1)^T A (s - 1)  s.t.  C_j(s) = sum_e c_e s_{f_e}^p_j / T_j - 1 = 0`
//!
//! A step (Sec. 4, Eqs. 15-18, one multiplier per constraint): the values
//! `C(s)`, the Jacobian rows `L`, `Y = A^-1 L^T` by the supernodal factor of
//! `A` (a direct f64 solve, [`crate::supernodal`]; only the rows of degree
//! above 1 change after the first step, and they are ordered first so that
//! the later solves take those columns alone), `y = 1 - s`, `S = L Y`,
//! `lambda = pinv(S) (L y + C)`, `dx = y - Y lambda`, the step length that
//! keeps every `s` above the floor, `s += alpha dx`. The stopping rules are
//! [`solver_cpu::NewtonRules`]'. A batch of steps is one submission; the host
//! reads the state and `s` back after it (one wait) and records another only
//! where the steps have not stopped. A batch has as many steps as the last
//! estimation took (the scale-driven iteration's estimations take about as
//! many each), so that most estimations wait once.
//!
//! Bindings: see the shader's header. `rows` and `ycols` are also the
//! factor's right-hand sides and solutions (`r` and `z` of
//! [`crate::supernodal::SupernodalSteps`]).

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader};
use crate::supernodal::{GpuFactor, Pipelines, SupernodalKernels, SupernodalSteps};
use crate::GpuError;
use solver_cpu::{NewtonInfo, NewtonRules, PowerSum};
use std::sync::Arc;

pub(crate) const SOURCE: &str = include_str!("../../shaders/power_sum_newton.wgsl");

/// Most constraints: the column count of one batch of the factor's solves.
pub(crate) const KMAX: usize = crate::CMAX;

const BINDINGS: [(u32, Bind); 11] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
    (8, Bind::ReadWrite),
    (9, Bind::ReadWrite),
    (10, Bind::ReadWrite),
];

const WG: usize = 256;

/// Steps of an estimation's first batch when no estimation came before.
const FIRST_BATCH: usize = 4;
/// Steps of a batch after one that did not stop.
const MORE: usize = 2;

/// As `NewtonParams` in the shader.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct NewtonParams {
    pub(crate) n: u32,
    pub(crate) ge: u32,
    pub(crate) gn: u32,
    pub(crate) pad: u32,
}

/// As `State` in the shader.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct NewtonState {
    /// 0 running, 1 converged (every `|C_j|` below `tol_res`), 2 a step
    /// moved less than `tol_moved`, 3 the step budget spent.
    pub(crate) done: u32,
    pub(crate) steps: u32,
    pub(crate) max_steps: u32,
    pub(crate) pad: u32,
    pub(crate) tol_res: f64,
    pub(crate) tol_moved: f64,
    pub(crate) floor: f64,
    pub(crate) max_res: f64,
    pub(crate) alpha: f64,
    pub(crate) moved: f64,
    pub(crate) values: [f64; KMAX],
    pub(crate) lambda: [f64; KMAX],
}

/// The entry points.
pub(crate) struct NewtonKernels {
    shader: Shader,
    init: Kernel,
    values: Kernel,
    finish_values: Kernel,
    rows: Kernel,
    dots: Kernel,
    multipliers: Kernel,
    direction: Kernel,
    step_length: Kernel,
    advance: Kernel,
    finish_step: Kernel,
}

impl NewtonKernels {
    /// Its kernels: an estimation runs every one, with one column per constraint.
    pub fn kernels(&self) -> [&Kernel; 10] {
        [
            &self.init,
            &self.values,
            &self.finish_values,
            &self.rows,
            &self.dots,
            &self.multipliers,
            &self.direction,
            &self.step_length,
            &self.advance,
            &self.finish_step,
        ]
    }

    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "power_sum_newton.wgsl", SOURCE, &BINDINGS)?;
        let k = |label, entry| Kernel::new(&shader, label, entry);
        Ok(NewtonKernels {
            init: k("newton init", "init"),
            values: k("newton values", "values"),
            finish_values: k("newton finish_values", "finish_values"),
            rows: k("newton jacobian_rows", "jacobian_rows"),
            dots: k("newton dots", "dots"),
            multipliers: k("newton multipliers", "multipliers"),
            direction: k("newton direction", "direction"),
            step_length: k("newton step_length", "step_length"),
            advance: k("newton advance", "advance"),
            finish_step: k("newton finish_step", "finish_step"),
            shader,
        })
    }
}

/// The constraints as the shader reads them, columns of degree above 1
/// first, and whether each unknown appears at most once per constraint.
pub(crate) struct Packed {
    pub offsets: Vec<u32>,
    pub faces: Vec<u32>,
    pub coef: Vec<f64>,
    pub meta: Vec<f64>,
    /// Constraints whose rows change from step to step (the first ones).
    pub moving: usize,
    /// Entries of the longest constraint.
    pub longest: usize,
}

/// Why a problem is left to the host's steps (`None`: it runs here).
pub(crate) fn unsupported(constraints: &[PowerSum], n: usize) -> Option<String> {
    let k = constraints.len();
    if k == 0 || k > KMAX {
        return Some(format!("{k} constraints (1 to {KMAX} run on the GPU)"));
    }
    if let Some(c) = constraints.iter().find(|c| !(1..=3).contains(&c.degree)) {
        return Some(format!("a constraint of degree {}", c.degree));
    }
    if n > u32::MAX as usize / 2 {
        return Some(format!("{n} unknowns"));
    }
    None
}

impl Packed {
    /// Pack `constraints` (moving ones first) into the kept vectors of
    /// `self`; `mark` (one per unknown) finds repeats. Returns false where
    /// an unknown is out of range or repeats within a constraint.
    pub fn fill(&mut self, constraints: &[PowerSum], n: usize, mark: &mut Vec<u32>) -> bool {
        self.offsets.clear();
        self.faces.clear();
        self.coef.clear();
        self.meta.clear();
        self.offsets.push(0);
        self.longest = 0;
        if mark.len() != n {
            mark.clear();
            mark.resize(n, u32::MAX);
        }
        let order = constraints
            .iter()
            .filter(|c| c.degree != 1)
            .chain(constraints.iter().filter(|c| c.degree == 1));
        for (j, c) in order.enumerate() {
            for &(f, v) in c.coeffs {
                let Some(m) = mark.get_mut(f as usize).filter(|m| **m != j as u32) else {
                    mark.iter_mut().for_each(|m| *m = u32::MAX);
                    return false;
                };
                *m = j as u32;
                self.faces.push(f);
                self.coef.push(v);
            }
            self.longest = self.longest.max(c.coeffs.len());
            self.offsets.push(self.faces.len() as u32);
            self.meta.push(c.degree as f64);
            self.meta.push(c.target);
        }
        // The marks hold constraint numbers 0..k: reset for the next fill.
        for &f in &self.faces {
            mark[f as usize] = u32::MAX;
        }
        self.moving = constraints.iter().filter(|c| c.degree != 1).count();
        true
    }
}

/// The buffers of one problem size, bound to one factor.
pub(crate) struct NewtonData {
    /// `(n, k, entries it has room for, the factor's set-up stamp)`.
    pub(crate) stamp: (usize, usize, usize, usize),
    params: wgpu::Buffer,
    offsets: wgpu::Buffer,
    faces: wgpu::Buffer,
    coef: wgpu::Buffer,
    meta: wgpu::Buffer,
    s: wgpu::Buffer,
    rows: wgpu::Buffer,
    state: wgpu::Buffer,
    /// `Y`, the step and the partial sums, read through the bind groups only.
    _bound: [wgpu::Buffer; 3],
    bg: wgpu::BindGroup,
    steps: SupernodalSteps,
    staging: Option<wgpu::Buffer>,
    /// Steps the last estimation took.
    pub(crate) last_steps: Option<usize>,
    /// The host's packing and repeat marks, kept from one estimation to the
    /// next (at a million faces they are tens of MB).
    pub(crate) packed: Packed,
    pub(crate) mark: Vec<u32>,
}

impl NewtonData {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &Context,
        kernels: &NewtonKernels,
        chol_kernels: &Arc<SupernodalKernels>,
        factor: &GpuFactor,
        n: usize,
        k: usize,
        entries: usize,
        factor_stamp: usize,
        limit: u64,
    ) -> Result<Self, GpuError> {
        let gn = n.div_ceil(WG).max(1);
        let max_dim = ctx.limits.max_compute_workgroups_per_dimension as usize;
        if gn > max_dim || entries.div_ceil(WG) > max_dim || k * (k + 1) > max_dim {
            return Err(GpuError::LimitExceeded {
                what: format!("Newton steps over {n} unknowns, {entries} entries"),
                limit_name: "max_compute_workgroups_per_dimension",
                needed: gn.max(entries.div_ceil(WG)) as u64,
                limit: max_dim as u64,
            });
        }
        let ge = entries.div_ceil(WG).max(1);
        let params = ctx.uniform_of(
            "newton params",
            &NewtonParams {
                n: n as u32,
                ge: 0,
                gn: gn as u32,
                pad: 0,
            },
        )?;
        let offsets = ctx.storage("newton offsets", ((k + 1) * 4) as u64)?;
        let faces = ctx.storage("newton faces", (entries * 4) as u64)?;
        let coef = ctx.storage("newton coefficients", (entries * 8) as u64)?;
        let meta = ctx.storage("newton degrees and targets", (2 * k * 8) as u64)?;
        let s = ctx.storage("newton s", (n * 8) as u64)?;
        let rows = ctx.storage("newton Jacobian rows", (k * n * 8) as u64)?;
        let ycols = ctx.storage("newton Y", (k * n * 8) as u64)?;
        let dx = ctx.storage("newton dx", (n * 8) as u64)?;
        let slots = (k * ge).max(k * (k + 1) * gn).max(gn);
        let partials = ctx.storage("newton partials", (slots * 8) as u64)?;
        let state = ctx.storage("newton state", std::mem::size_of::<NewtonState>() as u64)?;
        let bg = kernels.shader.bind(
            ctx,
            &[
                (0, &params),
                (1, &offsets),
                (2, &faces),
                (3, &coef),
                (4, &meta),
                (5, &s),
                (6, &rows),
                (7, &ycols),
                (8, &dx),
                (9, &partials),
                (10, &state),
            ],
        )?;
        let steps = SupernodalSteps::new(ctx, chol_kernels, factor, &rows, &ycols, 1, k, limit)?;
        Ok(NewtonData {
            stamp: (n, k, entries, factor_stamp),
            params,
            offsets,
            faces,
            coef,
            meta,
            s,
            rows,
            state,
            _bound: [ycols, dx, partials],
            bg,
            steps,
            staging: None,
            last_steps: None,
            packed: Packed {
                offsets: Vec::new(),
                faces: Vec::new(),
                coef: Vec::new(),
                meta: Vec::new(),
                moving: 0,
                longest: 0,
            },
            mark: Vec::new(),
        })
    }

    /// Whether it serves `n` unknowns, `k` constraints of `entries` entries
    /// with the factor of set-up `factor_stamp`.
    pub fn fits(&self, n: usize, k: usize, entries: usize, factor_stamp: usize) -> bool {
        let (sn, sk, se, sf) = self.stamp;
        sn == n && sk == k && entries <= se && sf == factor_stamp
    }
}

/// What an estimation did on the device.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Estimation {
    pub info: NewtonInfo,
    /// Why the steps stopped (the state's `done`).
    pub done: u32,
    pub batches: usize,
    /// Solves of the factor recorded (one per step, the batches' steps past
    /// the stop included).
    pub solves: usize,
}

/// Run the steps for the constraints packed in `data.packed` (k of them)
/// from `s = 1`; `s` receives the result.
pub(crate) fn estimate(
    ctx: &Context,
    kernels: &NewtonKernels,
    data: &mut NewtonData,
    rules: &NewtonRules,
    s: &mut [f64],
) -> Result<Estimation, GpuError> {
    let (n, k) = (data.stamp.0, data.stamp.1);
    let packed = &data.packed;
    let (moving, entries) = (packed.moving, packed.faces.len());
    let ge = packed.longest.div_ceil(WG).max(1);
    let gn = n.div_ceil(WG).max(1);
    ctx.write_buffer(
        &data.params,
        0,
        bytemuck::bytes_of(&NewtonParams {
            n: n as u32,
            ge: ge as u32,
            gn: gn as u32,
            pad: 0,
        }),
    );
    ctx.write_buffer(&data.offsets, 0, bytemuck::cast_slice(&packed.offsets));
    // The entries (homer 1.2M's volume alone: 14.4 MB an estimation) into
    // the staging memory on rayon's threads.
    ctx.write_buffer_par(&data.faces, bytemuck::cast_slice(&packed.faces));
    ctx.write_buffer_par(&data.coef, bytemuck::cast_slice(&packed.coef));
    ctx.write_buffer(&data.meta, 0, bytemuck::cast_slice(&packed.meta));
    let start = NewtonState {
        max_steps: rules.max_steps.min(u32::MAX as usize) as u32,
        tol_res: rules.residual,
        tol_moved: rules.moved,
        floor: rules.floor,
        ..NewtonState::default()
    };
    ctx.write_buffer(&data.state, 0, bytemuck::bytes_of(&start));

    let p = |kern: &Kernel| kern.pipeline(ctx, k);
    let pipes = [
        p(&kernels.values)?,
        p(&kernels.finish_values)?,
        p(&kernels.rows)?,
        p(&kernels.dots)?,
        p(&kernels.multipliers)?,
        p(&kernels.direction)?,
        p(&kernels.step_length)?,
        p(&kernels.advance)?,
        p(&kernels.finish_step)?,
    ];
    let [values, finish_values, rows, dots, multipliers, direction, step_length, advance, finish_step] =
        &pipes;
    let solve_all = data.steps.pipelines(ctx, k)?;
    let solve_moving = match moving {
        0 => None,
        m => Some(data.steps.pipelines(ctx, m)?),
    };
    // Modelled work of a step's kernels and of the trailing evaluation.
    let (nb, eb) = ((n * 8) as u64, entries as u64);
    let evaluate =
        KernelWork::other(eb * 20 + (k * ge * 8) as u64) + KernelWork::other((k * ge * 8) as u64);
    let step_kernels = evaluate
        + KernelWork::other(eb * 28)
        + KernelWork::other((k * (k + 1)) as u64 * 2 * nb)
        + KernelWork::other((k * (k + 1) * gn * 8) as u64)
        + KernelWork::other((3 + k as u64) * nb)
        + KernelWork::other((gn * 8) as u64)
        + KernelWork::other(3 * nb)
        + KernelWork::other((gn * 8) as u64);

    let mut enc = ctx.encoder("newton steps");
    enc.clear_buffer(&data.rows, 0, Some((k * n * 8) as u64));
    let mut est = Estimation::default();
    let mut batch = data.last_steps.unwrap_or(FIRST_BATCH).max(1);
    let mut first = true;
    let state_bytes = std::mem::size_of::<NewtonState>() as u64;
    let state = loop {
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("newton steps"),
                timestamp_writes: ctx.pass_timestamps(),
            });
            let bg = &data.bg;
            if first {
                dispatch(
                    &mut pass,
                    &kernels.init.pipeline(ctx, k)?,
                    bg,
                    (gn as u32, 1),
                );
                ctx.count_kernels(KernelWork::other(nb));
            }
            let evaluate_s = |pass: &mut wgpu::ComputePass| {
                dispatch(pass, values, bg, (ge as u32, k as u32));
                dispatch(pass, finish_values, bg, (1, 1));
            };
            for step in 0..batch {
                evaluate_s(&mut pass);
                dispatch(&mut pass, rows, bg, (ge as u32, k as u32));
                // The first step solves every column, later ones the
                // moving ones (a degree-1 row is constant).
                let solve: Option<(&Pipelines, usize)> = match (first && step == 0, &solve_moving) {
                    (true, _) => Some((&solve_all, k)),
                    (false, Some(m)) => Some((m, moving)),
                    (false, None) => None,
                };
                if let Some((pipelines, cols)) = solve {
                    data.steps.record(&mut pass, pipelines);
                    ctx.count_kernels(data.steps.work(cols));
                    est.solves += 1;
                }
                dispatch(&mut pass, dots, bg, (gn as u32, (k * (k + 1)) as u32));
                dispatch(&mut pass, multipliers, bg, (1, 1));
                dispatch(&mut pass, direction, bg, (gn as u32, 1));
                dispatch(&mut pass, step_length, bg, (1, 1));
                dispatch(&mut pass, advance, bg, (gn as u32, 1));
                dispatch(&mut pass, finish_step, bg, (1, 1));
            }
            // The stop after the last step (and max |C| at the `s` read).
            evaluate_s(&mut pass);
        }
        ctx.count_kernels(step_kernels.times(batch as u64) + evaluate);
        ctx.resolve_pass_time(&mut enc);
        est.batches += 1;
        first = false;
        let mut parts: Vec<(&wgpu::Buffer, u64)> = vec![(&data.state, state_bytes), (&data.s, nb)];
        parts.extend(ctx.pass_time_buffer());
        let mut read = ctx.read_parts(&parts, &mut data.staging, Some(enc))?;
        if ctx.pass_time_buffer().is_some() {
            let times = read.pop().unwrap_or_default();
            ctx.count_pass_time(&times);
            ctx.recycle(times);
        }
        let mut read = read.into_iter();
        let bytes = read.next().unwrap_or_default();
        let state: NewtonState = match bytes.get(..state_bytes as usize) {
            Some(b) => bytemuck::pod_read_unaligned(b),
            None => return Err(GpuError::Backend("Newton state not read back".into())),
        };
        ctx.recycle(bytes);
        if state.done != 0 {
            let bytes = read.next().unwrap_or_default();
            if bytes.len() < n * 8 {
                return Err(GpuError::Backend("Newton s not read back".into()));
            }
            for (o, c) in s.iter_mut().zip(bytes.chunks_exact(8)) {
                *o = f64::from_le_bytes(c.try_into().unwrap());
            }
            ctx.recycle(bytes);
            break state;
        }
        batch = MORE;
        enc = ctx.encoder("newton steps");
    };
    est.done = state.done;
    est.info = NewtonInfo {
        steps: state.steps as usize,
        max_residual: state.max_res,
    };
    data.last_steps = Some(est.info.steps.max(1));
    Ok(est)
}
