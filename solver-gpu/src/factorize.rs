//! Drives `shaders/supernodal_factor.wgsl`: the numeric Cholesky
//! factorization `P K P^T = L L^T` on the GPU, on the host's symbolic
//! analysis (the supernodes, their rows and the ordering `P`), straight into
//! the inverted form that [`crate::supernodal`]'s solves read: `L_ss^-1` in
//! each diagonal block, `B_s = L_rs L_ss^-1` below it
//! ([`solver_cpu::SupernodalFactor::invert_diagonal_blocks`] on the host).
//!
//! Left-looking, level by level of the supernodal elimination tree (leaves
//! first; a level's supernodes are independent, their descendants final):
//! - `update`: `A_s -= sum_d L_d[rows of s] L_d[columns of s]^T` over the
//!   descendants `d`, one dot product per value of the level; on the levels
//!   where those sums are long ([`UpdateWork::tiled`]), `update_tiled`
//!   makes them a 32 x 32 tile a workgroup;
//! - then the dense Cholesky of each supernode's `(m + q) x m` block, in
//!   block columns of [`BLOCK`], the level's supernodes at once: `diag`
//!   factors each block's diagonal tile `L_bb` in one workgroup's memory and
//!   inverts it beside (`X_bb = L_bb^-1`), `below` makes the rows under the
//!   tile as products `l_i = a_i X_bb^T` (a lane an entry), and `trailing`
//!   updates the columns right of the block (a tile a workgroup, the whole
//!   GPU).
//!
//! Then the tiles of `X = L_ss^-1` left of the diagonal (`X_bb` being its
//! diagonal tiles), `B = L_rs X` a tile column at a time, and `X` over
//! `L_ss`.
//!
//! The long sums (`update_tiled`, `trailing`, `inv_offdiag`, `inv_below`)
//! are made in tiles: a workgroup reads a tile's rows and columns into its
//! memory, [`PANEL`] terms at a time, and each lane adds its four entries'
//! products from there, so each value is read from device memory once a
//! tile, not once an entry. On an NVIDIA H200 the factorization's time went
//! with the bytes it read (BENCHMARKS.md, "GPU numeric factorization":
//! 2.8-3.0 TB/s modelled at homer 1.2M and 4.3M, where its chain of
//! dependent steps differed 2.4x and its bytes 7.3x); the tiles read
//! 12-14x fewer bytes there. Each dispatch waits for the one before, so
//! where a dispatch's work is small its time is its longest invocation's
//! chain of dependent steps (the serial steps the plan counts, summed over
//! the dispatches); the tiles lengthen that chain (a lane's four entries,
//! a barrier every [`PANEL`] terms), in workgroup memory.
//!
//! What goes up is `K`'s stored values (f64) once per
//! factorization, what comes back is one word (the first column whose pivot
//! was not positive); the factor itself never crosses the bus, where the
//! host's factorization sends all of it (985 MB at homer 1.2M). The
//! dispatches are planned from the structure alone
//! ([`FactorizationPlan`]), so their work is counted for any mesh without a
//! device.
//!
//! f64 only (the shape `K` is not positive definite in f32 at 1.2M faces),
//! and at most two value buffers (two storage bindings: homer 4.3M's 3.5 GB
//! on an H100's 2 GiB bindings); a larger factor is factored on the host
//! ([`GpuFactorization::new`] says so).
//!
//! Bindings (group 0), as documented in the shader: 0 `P` uniform
//! ([`FactorParams`], one per dispatch), 1 `idx` (the factor's index
//! sections, [`GpuFactor`]), 2 `fidx` (the supernodes in level order,
//! `K`'s map, the block columns' tasks, the scratch's and the values'
//! offsets), 3 `vals` (read-write), 4 `kv` (`K`'s values), 5 `flag`
//! (read-write), 6 `xs` (the scratch, read-write), 7 `vals1` (the second
//! value buffer, read-write).

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::supernodal::{GpuFactor, Placement};
use crate::GpuError;
use rayon::prelude::*;
use solver_cpu::{SupernodalFactor, SymCsc};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

pub(crate) const SOURCE: &str = include_str!("../../shaders/supernodal_factor.wgsl");

const BINDINGS: [(u32, Bind); 8] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
    (7, Bind::ReadWrite),
];

/// Parameters, as `FParams` in `supernodal_factor.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct FactorParams {
    pub(crate) sn0: u32,
    pub(crate) n_sn: u32,
    pub(crate) v0: u32,
    pub(crate) nval: u32,
    pub(crate) n: u32,
    pub(crate) nnz_k: u32,
    pub(crate) slots: u32,
    pub(crate) o_sn: u32,
    pub(crate) o_rows: u32,
    pub(crate) o_tptr: u32,
    pub(crate) o_tpos: u32,
    pub(crate) o_owner: u32,
    pub(crate) o_slot_owner: u32,
    pub(crate) o_order: u32,
    pub(crate) o_map: u32,
    pub(crate) o_task: u32,
    pub(crate) task0: u32,
    pub(crate) n_task: u32,
    pub(crate) kb: u32,
    pub(crate) o_xo: u32,
    pub(crate) o_gvo: u32,
    pub(crate) c1: u32,
    /// Lanes a row in `below`: a power of two, at least the dispatch's
    /// widest block.
    pub(crate) lpr: u32,
    /// `update_tiled`'s lists: per tile column of a tiled supernode, where
    /// its descendants start in `o_dlist` (one more at the end); per
    /// descendant, the supernode and its first slot at or past the tile
    /// column.
    pub(crate) o_dptr: u32,
    pub(crate) o_dlist: u32,
    pub(crate) pad: [u32; 3],
}

/// The most storage buffers a factor made on the GPU may hold its values in
/// (bindings 3 and 7 of the shader).
pub(crate) const VALUE_BUFFERS: usize = 2;

/// Where the GPU backend makes its Cholesky factors, the shape systems' of
/// `K` and the scale factors' of their matrix
/// (`METRICDEFORM_GPU_FACTORIZATION=host|gpu`; unset, [`Factorization::on`]
/// the adapter: the GPU on a hardware adapter with `SHADER_F64`, the host on
/// a CPU emulation such as lavapipe).
///
/// On an NVIDIA H200 against faer on its 16-core host (BENCHMARKS.md, "Real
/// GPU", two calls on 2026-11-28) the factors made on the GPU made the whole
/// run 1.27-1.39x faster at 108k faces, 1.27-1.43x at 1.2M and 1.10-1.15x at
/// 4.3M, and the host's peak 0.53-0.58x at 1.2M and 0.44-0.47x at 4.3M (the
/// factors never on the host). On lavapipe the GPU's factorization is the
/// host's CPU emulating it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Factorization {
    /// faer on the host (made ahead on other threads where the pipeline
    /// asks), its inverted form uploaded.
    Host,
    /// On the GPU from the matrix's values (`shaders/supernodal_factor.wgsl`),
    /// the symbolic analysis on the host; where the device has `SHADER_F64`
    /// and the factor fits two storage bindings, else on the host.
    Gpu,
}

impl Factorization {
    /// The default on an adapter: [`Factorization::Gpu`] on hardware (not a
    /// CPU emulation) whose shaders have f64 (the factorization's kernels
    /// are f64), else [`Factorization::Host`].
    pub fn on(adapter: &crate::AdapterSummary) -> Factorization {
        Factorization::on_parts(adapter.device_type == "Cpu", adapter.shader_f64)
    }

    /// [`Factorization::on`] an adapter that is a CPU emulation or not, with
    /// f64 shaders or not.
    pub(crate) fn on_parts(cpu: bool, shader_f64: bool) -> Factorization {
        if !cpu && shader_f64 {
            Factorization::Gpu
        } else {
            Factorization::Host
        }
    }

    /// The one `METRICDEFORM_GPU_FACTORIZATION` asks for (`host` or `gpu`),
    /// `None` where it is unset or names neither (a warning).
    pub fn asked() -> Option<Factorization> {
        crate::env_choice(
            "METRICDEFORM_GPU_FACTORIZATION",
            &[("host", Factorization::Host), ("gpu", Factorization::Gpu)],
            "the adapter's default",
        )
    }

    /// What a solver opened now ([`crate::open`]) uses: the one asked for,
    /// else the default [`on`](Factorization::on) the adapter it would open
    /// ([`crate::default_adapter`]; [`Factorization::Host`] where there is
    /// none).
    pub fn from_env() -> Factorization {
        Factorization::asked().unwrap_or_else(|| {
            crate::device::default_adapter().map_or(Factorization::Host, |a| Factorization::on(&a))
        })
    }
}

/// The entry points, in the order of [`Stage`].
const ENTRIES: [(&str, &str); 11] = [
    ("factor scatter", "scatter"),
    ("factor update", "update"),
    ("factor diagonal tile", "diag"),
    ("factor below the tile", "below"),
    ("factor trailing update", "trailing"),
    ("factor inverse off the diagonal", "inv_offdiag"),
    ("factor inverse below", "inv_below"),
    ("factor inverse copy", "inv_copy"),
    ("factor update in tiles", "update_tiled"),
    (
        "factor trailing update, a lane an entry",
        "trailing_entries",
    ),
    (
        "factor inverse off the diagonal, shared sums",
        "inv_offdiag_parts",
    ),
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stage {
    Scatter = 0,
    Update = 1,
    Diag = 2,
    Below = 3,
    Trailing = 4,
    InvOffdiag = 5,
    InvBelow = 6,
    InvCopy = 7,
    UpdateTiled = 8,
    TrailingEntries = 9,
    InvOffdiagParts = 10,
}

/// Loop iterations llvmpipe runs in one invocation, all loops together,
/// before it ends them (Mesa's `LP_MAX_TGSI_LOOP_ITERATIONS`, 65,535), less
/// a margin for the loops the plan's counts leave out (binary searches).
const CPU_LOOP_LIMIT: u64 = 60_000;

/// Columns of a supernode's block column (`W` in the shader): its diagonal
/// tile is factored in one workgroup's memory, the rest of the supernode by
/// all of the GPU.
pub(crate) const BLOCK: usize = 32;

/// Which kernel the stages with two take (the update: a lane a value or
/// tiles; `trailing` and `inv_offdiag`: a lane an entry or shared sums, or
/// tiles): `METRICDEFORM_GPU_FACTOR_KERNELS=tiles|entries` asks for one
/// everywhere (to measure them against each other on a device); unset, each
/// dispatch takes the one with the fewer modelled seconds
/// ([`modelled_seconds`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) enum KernelChoice {
    #[default]
    Model,
    Tiles,
    Entries,
}

impl KernelChoice {
    /// The one `METRICDEFORM_GPU_FACTOR_KERNELS` asks for (a warning where
    /// it names none).
    fn from_env() -> KernelChoice {
        crate::env_choice(
            "METRICDEFORM_GPU_FACTOR_KERNELS",
            &[
                ("model", KernelChoice::Model),
                ("tiles", KernelChoice::Tiles),
                ("entries", KernelChoice::Entries),
            ],
            "the model",
        )
        .unwrap_or_default()
    }

    /// Whether a dispatch takes its tiled kernel, its two kernels' modelled
    /// (bytes, serial steps) being `tiles` and `entries`.
    fn tiles(self, tiles: (u64, u64), entries: (u64, u64)) -> bool {
        match self {
            KernelChoice::Tiles => true,
            KernelChoice::Entries => false,
            KernelChoice::Model => {
                modelled_seconds(tiles.0, tiles.1) < modelled_seconds(entries.0, entries.1)
            }
        }
    }
}

/// A dispatch's modelled seconds on a discrete GPU: the longer of its bytes
/// at [`MODEL_BYTES_PER_S`] and its chain of dependent steps at
/// [`MODEL_STEP_S`] a step.
fn modelled_seconds(bytes: u64, serial: u64) -> f64 {
    (bytes as f64 / MODEL_BYTES_PER_S).max(serial as f64 * MODEL_STEP_S)
}

/// The modelled bytes' rate on an NVIDIA H200 (BENCHMARKS.md, "Real GPU",
/// binaries 57a365a, every sum a lane an entry): homer 1.2M's scale-driven
/// factor took 0.26 s for 771 GB, 4.3M's 2.03 s for 5,658 GB (2.97 and
/// 2.79 TB/s; their chains of dependent steps, 399,970 and 963,926, differ
/// 2.4x where the times differ 7.8x).
const MODEL_BYTES_PER_S: f64 = 2.8e12;

/// A dependent step at its longest: the 1.2M factor's 0.26 s over its
/// 399,970 steps, were it all chain. Taken so, a tiled kernel's longer
/// chain is chosen only where its bytes save more.
const MODEL_STEP_S: f64 = 0.65e-6;

/// The factorization's kernels (f64; the device must have `SHADER_F64`).
pub(crate) struct FactorKernels {
    shader: Shader,
    kernels: [Kernel; 11],
    choice: KernelChoice,
}

impl FactorKernels {
    pub fn new(ctx: &Context) -> Result<Arc<Self>, GpuError> {
        if !ctx.shader_f64 {
            return Err(GpuError::Backend(
                "a Cholesky factorization on the GPU needs SHADER_F64".into(),
            ));
        }
        let shader = Shader::new(ctx, "supernodal_factor.wgsl", SOURCE, &BINDINGS)?;
        let kernels = ENTRIES.map(|(label, entry)| Kernel::new(&shader, label, entry));
        Ok(Arc::new(FactorKernels {
            shader,
            kernels,
            choice: KernelChoice::from_env(),
        }))
    }

    /// [`FactorKernels::new`] taking `choice`, not the environment's.
    #[cfg(test)]
    pub(crate) fn with_choice(ctx: &Context, choice: KernelChoice) -> Arc<Self> {
        let k = FactorKernels::new(ctx).unwrap();
        Arc::new(FactorKernels {
            shader: k.shader.clone(),
            kernels: k.kernels.clone(),
            choice,
        })
    }

    /// Its kernels: a factorization runs all of them.
    pub fn kernels(&self) -> &[Kernel; 11] {
        &self.kernels
    }
}

/// One dispatch of a factorization as planned on the host: its stage, its
/// own parameters (the index offsets are the recording's), its items
/// (workgroups for `diag`, invocations otherwise) and the longest loop of
/// one invocation (an upper bound for `update`).
#[derive(Clone, Copy, Debug)]
struct Planned {
    stage: Stage,
    params: FactorParams,
    items: u64,
    serial: u64,
    /// Its modelled device bytes.
    bytes: u64,
}

/// A factorization's dispatches, planned from the factor's structure alone
/// (no device: its work can be counted for any mesh).
pub(crate) struct FactorizationPlan {
    steps: Vec<Planned>,
    /// Per block column of a level, the supernodes taking part, three u32
    /// each: the supernode, and the items (`below`'s workgroups, entries of
    /// their trailing updates) of the tasks before it in its dispatches;
    /// then the inversion's tasks (`inv_below`'s: the supernode and the
    /// workgroups before it).
    tasks: Vec<u32>,
    /// Each supernode's first value, counting every buffer's.
    gvo: Vec<u32>,
    /// Each supernode's inverse diagonal block in the scratch (`m x m`,
    /// column-major), and the scratch's values.
    xo: Vec<u32>,
    x_len: u64,
    /// `update_tiled`'s lists: per tile column of each tiled supernode, the
    /// start of its descendants in `dlist` (one more at the end), and per
    /// descendant its supernode and its first slot at or past the tile
    /// column (relative to its rows).
    dptr: Vec<u32>,
    dlist: Vec<u32>,
    /// Modelled device bytes by stage (in [`ENTRIES`]' order), and those
    /// the updates, `trailing` and the inversion's sums would read with a
    /// lane an entry everywhere (as before their tiles: each entry reads its
    /// sum's two values a term), for comparison.
    bytes: [u64; 11],
    by_entry: u64,
    /// Levels whose update is tiled, of all.
    tiled_levels: (usize, usize),
}

/// Where the values of `f` go when they all fit one buffer
/// ([`Placement::new`] with no cut). `None` where `f` is not in topological
/// order or its values overflow 32-bit offsets.
pub(crate) fn one_chunk_placement(f: &SupernodalFactor) -> Option<Placement> {
    let cap = u32::MAX as usize;
    let (place, chunks) = Placement::new(f, &f.levels()?, cap).ok()?;
    (chunks.len() == 1).then_some(place)
}

/// The modelled work of factoring a matrix of `nnz_k` stored entries into
/// `f`'s structure on the GPU (its planned dispatches, their kernels as
/// `METRICDEFORM_GPU_FACTOR_KERNELS` says), its values in one buffer:
/// counted from the structure alone, no device needed. `None` where `f` is
/// not in topological order or overflows 32-bit offsets.
pub fn factorization_work(f: &SupernodalFactor, nnz_k: usize) -> Option<KernelWork> {
    let place = one_chunk_placement(f)?;
    let plan = FactorizationPlan::new(f, &place, nnz_k, KernelChoice::from_env())?;
    log::debug!("GPU factorization planned: {}", plan.describe());
    Some(plan.work())
}

/// Serial steps of `diag` on a tile of `w` columns: the tile's load and
/// store (with its inverse's), a few entries per lane, and per column k its
/// pivot and the update of the columns right of it.
fn diag_steps(w: usize) -> u64 {
    let per_lane = |entries: usize| entries.div_ceil(FLAT_WG as usize) as u64;
    let columns: u64 = (0..w).map(|k| 1 + per_lane((w - k - 1) * w)).sum();
    2 * per_lane(w * w) + columns
}

/// Lanes sharing one sum in `inv_offdiag_parts` (`PARTS` in the shader): a
/// workgroup is [`BLOCK`] x `PARTS`.
const PARTS: usize = 8;

/// Serial steps of a sum of `terms` terms shared by `parts` lanes: each
/// lane's share, then the parts summed (by one of them).
fn sum_in_parts(terms: usize, parts: usize) -> u64 {
    (terms.div_ceil(parts) + parts) as u64
}

/// Lanes a row takes in `below` where the widest block of its dispatch has
/// `w` columns: the least power of two not below `w`.
fn below_lanes(w: usize) -> usize {
    w.next_power_of_two().clamp(1, BLOCK)
}

/// Serial steps of `below` where the widest block has `w` columns: the
/// inverse tile's load, a few entries per lane, the row's entry, and the
/// product of the row with a row of the inverse tile.
fn below_steps(w: usize) -> u64 {
    (w * w).div_ceil(FLAT_WG as usize) as u64 + 2 + w as u64
}

/// Columns of a descendant `update_tiled` reads into workgroup memory at a
/// time (`KC` in the shader), and `trailing` of its block.
const PANEL: usize = 16;

/// Tiles of [`BLOCK`] x [`BLOCK`] on or below the diagonal of a region of
/// `rows` x `cols` entries (`rows >= cols`): tile column `J` holds the tile
/// rows from `J` on.
fn lower_tiles(rows: usize, cols: usize) -> u64 {
    let (tr, tc) = (rows.div_ceil(BLOCK) as u64, cols.div_ceil(BLOCK) as u64);
    match tc {
        0 => 0,
        _ => tc * tr - tc * (tc - 1) / 2,
    }
}

/// Serial steps of a tiled kernel's panels for `w` columns: per [`PANEL`]
/// columns, four loads a lane and two barriers; a step a column for the
/// products.
fn panel_steps(w: usize) -> u64 {
    (w.div_ceil(PANEL) * 6 + w) as u64
}

/// Serial steps of `trailing` on a block of `w` columns: its tile found
/// (binary searches), the panels and their products, the four entries
/// stored.
fn trailing_steps(w: usize) -> u64 {
    12 + panel_steps(w)
}

/// The supernode whose columns hold each column; `None` where a supernode's
/// columns run past the matrix.
fn column_owners(f: &SupernodalFactor) -> Option<Vec<u32>> {
    let mut owner = vec![0u32; f.perm.len()];
    for s in 0..f.len() {
        for c in f.begin[s]..f.begin[s + 1] {
            *owner.get_mut(c as usize)? = s as u32;
        }
    }
    Some(owner)
}

/// Descendant `d`'s rows by the tile columns of the supernodes they are
/// columns of: for each run, `each(s, J, p0, na)` (the supernode, its tile
/// column, the run's first place in `d`'s rows and its length), in the
/// order of the rows.
fn tile_column_runs(
    f: &SupernodalFactor,
    owner: &[u32],
    d: usize,
    mut each: impl FnMut(usize, usize, usize, usize),
) {
    let rows = &f.rows[f.row_ptr[d] as usize..f.row_ptr[d + 1] as usize];
    let mut p = 0;
    while p < rows.len() {
        let r = rows[p] as usize;
        let s = owner[r] as usize;
        let c0 = f.begin[s] as usize;
        let j = (r - c0) / BLOCK;
        let end = (c0 + (j + 1) * BLOCK).min(f.begin[s + 1] as usize);
        let mut p1 = p + 1;
        while p1 < rows.len() && (rows[p1] as usize) < end {
            p1 += 1;
        }
        each(s, j, p, p1 - p);
        p = p1;
    }
}

/// Per level, the update's work counted from the structure: its products
/// (`update` reads two values a product, a lane a value), its values, and
/// the bytes `update_tiled` reads (a descendant's rows a tile column, and
/// its rows of the tile column again for each tile row it reaches, at most
/// the tile rows from the column's on).
struct UpdateWork {
    products: Vec<u64>,
    values: Vec<u64>,
    tiled_bytes: Vec<u64>,
    /// `update_tiled`'s serial steps: its longest list's (per descendant
    /// the binary searches and barriers, and its panels as though every
    /// tile reached it), its tile found and stored.
    tiled_serial: Vec<u64>,
}

impl UpdateWork {
    fn new(f: &SupernodalFactor, owner: &[u32], level: &[u32], depth: usize) -> UpdateWork {
        use std::sync::atomic::AtomicU64;
        // Each tile column's list's chain, from first[s] on.
        let mut first = vec![0usize; f.len() + 1];
        for s in 0..f.len() {
            first[s + 1] = first[s] + f.shape(s).0.div_ceil(BLOCK);
        }
        let chain: Vec<AtomicU64> = (0..first[f.len()]).map(|_| AtomicU64::new(0)).collect();
        let zero = || (vec![0u64; depth], vec![0u64; depth]);
        let (products, tiled_bytes) = (0..f.len())
            .into_par_iter()
            .fold(zero, |(mut pr, mut by), d| {
                let (md, qd) = f.shape(d);
                let (md, qd) = (md as u64, qd as u64);
                tile_column_runs(f, owner, d, |s, j, p0, na| {
                    let lv = level[s] as usize;
                    let (p0, na, j) = (p0 as u64, na as u64, j as u64);
                    // Rows p0 .. p0 + na as columns, each with the rows
                    // from it on.
                    pr[lv] += md * (na * (qd - p0) - na * (na - 1) / 2);
                    let (m, q) = f.shape(s);
                    let reached = (qd - p0).min((m + q).div_ceil(BLOCK) as u64 - j);
                    by[lv] += 8 * md * (na * reached + qd - p0);
                    let search = (u64::BITS - (qd - p0).leading_zeros()) as u64;
                    chain[first[s] + j as usize]
                        .fetch_add(search + 4 + panel_steps(md as usize), Ordering::Relaxed);
                });
                (pr, by)
            })
            .reduce(zero, |(mut a, mut b), (c, d)| {
                a.iter_mut().zip(c).for_each(|(x, y)| *x += y);
                b.iter_mut().zip(d).for_each(|(x, y)| *x += y);
                (a, b)
            });
        let mut values = vec![0u64; depth];
        let mut tiled_serial = vec![0u64; depth];
        for s in 0..f.len() {
            let lv = level[s] as usize;
            values[lv] += f.val_ptr[s + 1] - f.val_ptr[s];
            let longest = (first[s]..first[s + 1])
                .map(|l| chain[l].load(Ordering::Relaxed))
                .max()
                .unwrap_or(0);
            tiled_serial[lv] = tiled_serial[lv].max(longest + 12);
        }
        UpdateWork {
            products,
            values,
            tiled_bytes,
            tiled_serial,
        }
    }

    /// Whether level `lv`'s update is tiled, its untiled update's serial
    /// steps being `lane_serial`: as `choice` says; by the model, where the
    /// tiles read at most half the bytes a lane a value does, its sums are
    /// long (at least [`TILED_PRODUCTS`] products a value on average:
    /// shorter sums leave most of a tile's lanes idle) and its modelled
    /// seconds are fewer.
    fn tiled(&self, lv: usize, lane_serial: u64, choice: KernelChoice) -> bool {
        let values = 16 * self.values[lv];
        let tiles = (self.tiled_bytes[lv] + values, self.tiled_serial[lv]);
        let lanes = (16 * self.products[lv] + values, lane_serial);
        match choice {
            KernelChoice::Model => {
                2 * self.tiled_bytes[lv] <= 16 * self.products[lv]
                    && self.products[lv] >= TILED_PRODUCTS * self.values[lv]
                    && choice.tiles(tiles, lanes)
            }
            _ => choice.tiles(tiles, lanes),
        }
    }
}

/// The least products a value, on average over a level, for its update to
/// be tiled ([`UpdateWork::tiled`]).
const TILED_PRODUCTS: u64 = 32;

/// `update_tiled`'s descendant lists: per tile column of each supernode on
/// a tiled level (from `base[s]`, in level order), the descendants holding
/// a row among its columns, in level order (the order `update` sums them
/// in), each with its first row at or past the tile column.
struct UpdateLists {
    base: Vec<u32>,
    dptr: Vec<u32>,
    dlist: Vec<u32>,
}

impl UpdateLists {
    fn new(
        f: &SupernodalFactor,
        owner: &[u32],
        order: &[usize],
        level: &[u32],
        tiled: &[bool],
    ) -> Option<UpdateLists> {
        let mut base = vec![0u32; f.len()];
        let mut lists = 0usize;
        for &s in order.iter().filter(|&&s| tiled[level[s] as usize]) {
            base[s] = u32::try_from(lists).ok()?;
            lists += f.shape(s).0.div_ceil(BLOCK);
        }
        let (base_ref, lists_of) = (&base, |s: usize| tiled[level[s] as usize]);
        let runs: Vec<[u32; 3]> = order
            .par_iter()
            .flat_map_iter(|&d| {
                let mut v = Vec::new();
                tile_column_runs(f, owner, d, |s, j, p0, _| {
                    if lists_of(s) {
                        v.push([base_ref[s] + j as u32, d as u32, p0 as u32]);
                    }
                });
                v
            })
            .collect();
        // A counting sort by list, each list in level order.
        let mut dptr = vec![0u32; lists + 1];
        for r in &runs {
            dptr[r[0] as usize + 1] += 1;
        }
        for i in 0..lists {
            dptr[i + 1] += dptr[i];
        }
        u32::try_from(2 * runs.len()).ok()?;
        let mut next = dptr.clone();
        let mut dlist = vec![0u32; 2 * runs.len()];
        for r in runs {
            let at = &mut next[r[0] as usize];
            dlist[2 * *at as usize] = r[1];
            dlist[2 * *at as usize + 1] = r[2];
            *at += 1;
        }
        Some(UpdateLists { base, dptr, dlist })
    }
}

impl FactorizationPlan {
    /// The dispatches factoring a matrix of `nnz_k` stored entries into
    /// `f`'s structure placed by `place`. `None` where `f` is
    /// not in topological order or a dispatch's items overflow 32 bits.
    pub fn new(
        f: &SupernodalFactor,
        place: &Placement,
        nnz_k: usize,
        choice: KernelChoice,
    ) -> Option<FactorizationPlan> {
        let ns = f.len();
        let gvo = place.global_vo()?;
        let n = f.perm.len();
        let level = f.levels()?;
        let slots = f.rows.len();
        let mut steps = Vec::new();
        let mut tasks: Vec<u32> = Vec::new();
        let base = FactorParams {
            n: u32::try_from(n).ok()?,
            nnz_k: u32::try_from(nnz_k).ok()?,
            slots: u32::try_from(slots).ok()?,
            ..Default::default()
        };
        let mut add = |stage, params, items, serial, bytes| {
            if items > 0 {
                steps.push(Planned {
                    stage,
                    params,
                    items,
                    serial,
                    bytes,
                })
            }
        };
        add(Stage::Scatter, base, nnz_k as u64, 1, 20 * nnz_k as u64);
        // Per column: slots holding it and the descendants' columns behind
        // them (an update's merge and its products).
        let mut held = vec![0u64; n];
        let mut terms = vec![0u64; n];
        for s in 0..ns {
            let (m, _) = f.shape(s);
            for &r in &f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize] {
                held[r as usize] += 1;
                terms[r as usize] += m as u64;
            }
        }
        let size = |s: usize| f.val_ptr[s + 1] - f.val_ptr[s];
        let depth = level.iter().max().map_or(0, |&l| l as usize + 1);
        let counted = std::time::Instant::now();
        let owner = column_owners(f)?;
        let updates = UpdateWork::new(f, &owner, &level, depth);
        let mut by_entry = 0u64;
        // The longest merge and products of one value a lane a value: a
        // column's list (the longest of the supernode's) and a row's; the
        // longest of each level.
        let mut lane_serial = vec![0u64; depth];
        for (s, &lv) in level.iter().enumerate() {
            let own = f.begin[s] as usize..f.begin[s + 1] as usize;
            let col = own.clone().map(|c| held[c] + terms[c]).max().unwrap_or(0);
            let below = &f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize];
            let row = own
                .map(|c| held[c])
                .chain(below.iter().map(|&r| held[r as usize]))
                .max()
                .unwrap_or(0);
            lane_serial[lv as usize] = lane_serial[lv as usize].max(col + row);
        }
        // The tiled supernodes' lists, in level order.
        let tiled: Vec<bool> = (0..depth)
            .map(|lv| updates.tiled(lv, lane_serial[lv], choice))
            .collect();
        let lists = UpdateLists::new(f, &owner, &place.order, &level, &tiled)?;
        drop(owner);
        log::debug!(
            "GPU factorization plan: the update's work and lists in {:.3} s ({} descendants listed)",
            counted.elapsed().as_secs_f64(),
            lists.dlist.len() / 2
        );
        let mut sn0 = 0;
        while sn0 < ns {
            let lv = level[place.order[sn0]];
            let mut sn1 = sn0;
            while sn1 < ns && level[place.order[sn1]] == lv {
                sn1 += 1;
            }
            let sns = &place.order[sn0..sn1];
            let nval: u64 = sns.iter().map(|&s| size(s)).sum();
            let p = FactorParams {
                sn0: sn0 as u32,
                n_sn: (sn1 - sn0) as u32,
                v0: gvo[sns[0]],
                nval: u32::try_from(nval).ok()?,
                ..base
            };
            let lv = lv as usize;
            by_entry += 16 * (updates.products[lv] + nval);
            if tiled[lv] {
                // A workgroup per tile on or below the diagonal of each
                // supernode; its serial steps, those of the longest list.
                let task0 = tasks.len() / 3;
                let mut tiles = 0u64;
                for &s in sns {
                    let (m, q) = f.shape(s);
                    tasks.extend([s as u32, u32::try_from(tiles).ok()?, lists.base[s]]);
                    tiles += lower_tiles(m + q, m);
                }
                let q = FactorParams {
                    task0: task0 as u32,
                    n_task: (tasks.len() / 3 - task0) as u32,
                    nval: u32::try_from(tiles).ok()?,
                    ..base
                };
                let b = updates.tiled_bytes[lv] + 16 * nval;
                add(Stage::UpdateTiled, q, tiles, updates.tiled_serial[lv], b);
            } else {
                let update = lane_serial[lv];
                let b = 16 * (updates.products[lv] + nval);
                add(Stage::Update, p, nval, update, b);
            }
            // Block columns, the level's supernodes at once.
            let widest = sns.iter().map(|&s| f.shape(s).0).max().unwrap_or(0);
            for kb in (0..widest).step_by(BLOCK) {
                let task0 = tasks.len() / 3;
                // `below`'s rows a workgroup: its lanes over the widest
                // block's columns (the widest supernode's).
                let w_most = BLOCK.min(widest - kb);
                let lpr = below_lanes(w_most);
                let rows_per_group = FLAT_WG as usize / lpr;
                // `trailing` a tile a workgroup or a lane an entry: the
                // tiles' and the entries' bytes (a tile's panels read, its
                // entries read and written; a lane an entry reads the
                // block's columns for each entry).
                let (mut tiles, mut entries) = ((0u64, 0u64), (0u64, 0u64));
                for &s in sns {
                    let (m, q) = f.shape(s);
                    if m > kb {
                        let w = BLOCK.min(m - kb);
                        let j0 = kb + w;
                        let n = lower_tiles(m + q - j0, m - j0);
                        let e = ((m + q - j0) * (m - j0)) as u64;
                        tiles.0 += 16 * e + 16 * BLOCK as u64 * w as u64 * n;
                        entries.0 += 16 * e + 16 * w as u64 * e;
                    }
                }
                tiles.1 = trailing_steps(w_most);
                entries.1 = w_most as u64;
                let tiled = choice.tiles(tiles, entries);
                let (mut below, mut trailing) = (0u64, 0u64);
                let (mut diag_bytes, mut below_bytes) = (0u64, 0u64);
                for &s in sns {
                    let (m, q) = f.shape(s);
                    if m <= kb {
                        continue;
                    }
                    let w = BLOCK.min(m - kb);
                    let j0 = kb + w;
                    tasks.extend([
                        s as u32,
                        u32::try_from(below).ok()?,
                        u32::try_from(trailing).ok()?,
                    ]);
                    let groups = (m + q - j0).div_ceil(rows_per_group) as u64;
                    below += groups;
                    trailing += match tiled {
                        true => lower_tiles(m + q - j0, m - j0),
                        false => ((m + q - j0) * (m - j0)) as u64,
                    };
                    // diag: the tile read and written, X written; below:
                    // the rows read and written, X read a workgroup.
                    let w = w as u64;
                    diag_bytes += 24 * w * w;
                    below_bytes += 16 * w * (m + q - j0) as u64 + 8 * w * w * groups;
                }
                by_entry += entries.0;
                let q = FactorParams {
                    task0: task0 as u32,
                    n_task: (tasks.len() / 3 - task0) as u32,
                    kb: kb as u32,
                    ..base
                };
                let items = |v: u64| u32::try_from(v).ok();
                add(
                    Stage::Diag,
                    q,
                    q.n_task as u64,
                    diag_steps(w_most),
                    diag_bytes,
                );
                let p = FactorParams {
                    nval: items(below)?,
                    lpr: lpr as u32,
                    ..q
                };
                add(Stage::Below, p, below, below_steps(w_most), below_bytes);
                let p = FactorParams {
                    nval: items(trailing)?,
                    ..q
                };
                let (stage, (b, serial)) = match tiled {
                    true => (Stage::Trailing, tiles),
                    false => (Stage::TrailingEntries, entries),
                };
                add(stage, p, trailing, serial, b);
            }
            sn0 = sn1;
        }
        // The inversion in tiles (its diagonal tiles made by `diag`): X's
        // tile rows one after the other, then B's tile columns, then X over
        // L_ss.
        let mut xo = vec![0u32; ns];
        let mut x_len = 0u64;
        for (s, o) in xo.iter_mut().enumerate() {
            let (m, _) = f.shape(s);
            *o = u32::try_from(x_len).ok()?;
            x_len += (m * m) as u64;
        }
        let widest = (0..ns).map(|s| f.shape(s).0).max().unwrap_or(0);
        // The supernodes wider than a tile, in order: the only ones with
        // tiles past the first (a pass over them, not over every supernode,
        // per tile column: homer 4.3M's scale factors have 1.19M supernodes
        // and tile columns up to 34).
        let wide: Vec<usize> = (0..ns).filter(|&s| f.shape(s).0 > BLOCK).collect();
        for i in 1..widest.div_ceil(BLOCK) {
            let kb = i * BLOCK;
            let task0 = tasks.len() / 3;
            for &s in wide.iter().filter(|&&s| f.shape(s).0 > kb) {
                tasks.extend([s as u32, 0, 0]);
            }
            let n_task = tasks.len() / 3 - task0;
            let q = FactorParams {
                task0: task0 as u32,
                n_task: n_task as u32,
                kb: kb as u32,
                ..base
            };
            // A workgroup per task and tile left of the diagonal (the panels
            // of its sums, then the diagonal tile's product), or per task
            // and column, its sums shared by PARTS lanes (two values read
            // a term).
            let (mut tiles, mut parts) = ((0u64, 0u64), (0u64, 0u64));
            for &s in wide.iter().filter(|&&s| f.shape(s).0 > kb) {
                let w = BLOCK.min(f.shape(s).0 - kb) as u64;
                // Per tile J: L's rows and X's columns from J's first column
                // to kb, X_II, the tile written.
                let panels: u64 = (0..i).map(|j| (kb - j * BLOCK) as u64).sum();
                let out = i as u64 * 8 * (w * w + BLOCK as u64 * w);
                tiles.0 += 8 * (w + BLOCK as u64) * panels + out;
                let terms = (kb * (kb + 1) / 2) as u64;
                parts.0 += 16 * w * terms + kb as u64 * 8 * w * w + 8 * kb as u64 * w;
            }
            tiles.1 = panel_steps(kb) + 2 * BLOCK as u64 + 8;
            parts.1 = sum_in_parts(kb, PARTS) + BLOCK as u64;
            by_entry += parts.0;
            let (stage, items, (b, serial)) = match choice.tiles(tiles, parts) {
                true => (Stage::InvOffdiag, n_task * i, tiles),
                false => (Stage::InvOffdiagParts, n_task * kb, parts),
            };
            add(stage, q, items as u64, serial, b);
        }
        // B's tile columns: a workgroup per W rows below the diagonal block
        // of each supernode wider than kb (at the first, every supernode;
        // at the next, the wide ones).
        let all: Vec<usize> = (0..ns).collect();
        for j in 0..widest.div_ceil(BLOCK) {
            let kb = j * BLOCK;
            let set = match kb {
                0 => &all,
                _ => &wide,
            };
            let task0 = tasks.len() / 3;
            let (mut groups, mut longest, mut b) = (0u64, 0usize, 0u64);
            for &s in set {
                let (m, q) = f.shape(s);
                if m > kb && q > 0 {
                    tasks.extend([s as u32, u32::try_from(groups).ok()?, 0]);
                    let g = q.div_ceil(BLOCK) as u64;
                    groups += g;
                    longest = longest.max(m - kb);
                    // Per workgroup: its rows' L and X's columns from kb,
                    // its entries written.
                    let (w, span) = (BLOCK.min(m - kb) as u64, (m - kb) as u64);
                    b += g * 8 * (BLOCK as u64 * span + w * span + BLOCK as u64 * w);
                }
            }
            let q = FactorParams {
                task0: task0 as u32,
                n_task: (tasks.len() / 3 - task0) as u32,
                kb: kb as u32,
                nval: u32::try_from(groups).ok()?,
                ..base
            };
            add(Stage::InvBelow, q, groups, panel_steps(longest) + 12, b);
        }
        // X read and written over L; with a lane an entry, B would read two
        // values a term.
        let mut copy = 0u64;
        for s in 0..ns {
            let (m, q) = f.shape(s);
            let (m, q) = (m as u64, q as u64);
            copy += 16 * m * m;
            by_entry += 16 * q * m * (m + 1) / 2;
        }
        add(Stage::InvCopy, base, n as u64, widest as u64, copy);
        let mut bytes = [0u64; 11];
        for st in &steps {
            bytes[st.stage as usize] += st.bytes;
        }
        Some(FactorizationPlan {
            steps,
            tasks,
            gvo,
            xo,
            x_len,
            dptr: lists.dptr,
            dlist: lists.dlist,
            bytes,
            by_entry,
            tiled_levels: (tiled.iter().filter(|&&t| t).count(), depth),
        })
    }

    /// Per stage (in [`ENTRIES`]' order): dispatches and serial steps.
    pub fn stages(&self) -> [(u64, u64); 11] {
        let mut out = [(0, 0); 11];
        for s in &self.steps {
            out[s.stage as usize].0 += 1;
            out[s.stage as usize].1 += s.serial;
        }
        out
    }

    /// The stages' dispatches and serial steps, the tiled levels and the
    /// modelled bytes, in words.
    pub fn describe(&self) -> String {
        let gb = |b: u64| b as f64 / 1e9;
        let stages = self
            .stages()
            .iter()
            .zip(ENTRIES)
            .zip(self.bytes)
            .filter(|((w, _), _)| w.0 > 0)
            .map(|(((d, s), (_, entry)), b)| format!("{entry} {d} x, {s} steps, {:.1} GB", gb(b)))
            .collect::<Vec<_>>()
            .join("; ");
        let (tiled, levels) = self.tiled_levels;
        let sums = [
            Stage::Update,
            Stage::UpdateTiled,
            Stage::Trailing,
            Stage::TrailingEntries,
            Stage::InvOffdiag,
            Stage::InvOffdiagParts,
            Stage::InvBelow,
        ]
        .map(|s| self.bytes[s as usize])
        .iter()
        .sum::<u64>();
        format!(
            "{stages}; update tiled on {tiled} of {levels} levels; {:.1} GB modelled, \
             the updates, trailing and inversion sums {:.1} GB ({:.1} GB with a lane \
             an entry); modelled {:.1} ms",
            gb(self.bytes.iter().sum()),
            gb(sums),
            gb(self.by_entry),
            1e3 * self.modelled_seconds()
        )
    }

    /// Its modelled seconds on a discrete GPU: each dispatch's
    /// ([`modelled_seconds`]), summed.
    pub fn modelled_seconds(&self) -> f64 {
        self.steps
            .iter()
            .map(|s| modelled_seconds(s.bytes, s.serial))
            .sum()
    }

    /// Modelled work of one factorization: its dispatches, the chain of
    /// dependent steps through them, and its device bytes.
    pub fn work(&self) -> KernelWork {
        KernelWork {
            dispatches: self.steps.len() as u64,
            bytes: self.bytes.iter().sum(),
            minimal: 0,
            serial_steps: self.steps.iter().map(|s| s.serial).sum(),
        }
    }
}

/// What a factorization's recording holds apart from the factor it is
/// bound to: shared by the factorizations of one structure
/// ([`GpuFactorization::for_factor`]).
struct Recorded {
    /// The factorization's index (order, `K`'s map, tasks, offsets).
    fidx: wgpu::Buffer,
    /// `K`'s stored values, in `SymCsc` order.
    kv: wgpu::Buffer,
    flag: wgpu::Buffer,
    /// The inverse diagonal blocks' scratch.
    xs: wgpu::Buffer,
    /// Each dispatch's parameters.
    params: Vec<wgpu::Buffer>,
    /// Each dispatch's stage and workgroups.
    steps: Vec<(Stage, (u32, u32))>,
    nnz_k: usize,
    work: KernelWork,
}

/// A numeric factorization of one pattern of `K` into a [`GpuFactor`]'s
/// values, recorded once (per pattern and run) and run once per set of
/// values ([`GpuFactorization::run`]).
pub(crate) struct GpuFactorization {
    kernels: Arc<FactorKernels>,
    /// Each dispatch's bindings (the recording's, and the factor's).
    bgs: Vec<wgpu::BindGroup>,
    /// The factor's values (one or two buffers).
    vals: Vec<wgpu::Buffer>,
    /// Bound at 7: the second values, or a 16-byte stand-in; kept with the
    /// bind groups that name it.
    #[allow(dead_code)]
    second: wgpu::Buffer,
    recorded: Recorded,
    /// Of the dispatches of the run under way: how many are submitted, and
    /// how many a slice submits ([`GpuFactorization::submit_sliced`]).
    submitted: AtomicUsize,
    slice: AtomicUsize,
}

/// Each stored entry of `k` (lower triangle, `SymCsc` order): its place in
/// the values of `f`'s factor as placed by `place` (`P K P^T`'s lower
/// triangle, supernode by supernode). `None` where `k` is not the pattern
/// `f` was analysed for (an entry outside the factor's structure).
pub(crate) fn value_map(f: &SupernodalFactor, place: &Placement, k: &SymCsc) -> Option<Vec<u32>> {
    let n = f.perm.len();
    if k.n != n || k.col_ptr.len() != n + 1 {
        return None;
    }
    let mut inv = vec![0u32; n];
    for (new, &old) in f.perm.iter().enumerate() {
        *inv.get_mut(old as usize)? = new as u32;
    }
    let owner = column_owners(f)?;
    let gvo = place.global_vo()?;
    // A column's entries, each found by a search in its supernode's rows:
    // the columns on rayon's threads, the map in `k`'s order.
    let (inv, owner, gvo) = (&inv, &owner, &gvo);
    (0..n)
        .into_par_iter()
        .flat_map_iter(|j| {
            let entries = k.row_idx.get(k.col_ptr[j]..k.col_ptr[j + 1]);
            entries.into_iter().flatten().map(move |&i| {
                let (a, b) = (*inv.get(i)?, inv[j]);
                let (r, c) = (a.max(b), a.min(b));
                let s = owner[c as usize] as usize;
                let (m, q) = f.shape(s);
                let c0 = f.begin[s];
                let row = match r < c0 + m as u32 {
                    true => (r - c0) as usize,
                    false => {
                        let rows = &f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize];
                        m + rows.binary_search(&r).ok()?
                    }
                };
                let at = gvo[s] as usize + (c - c0) as usize * (m + q) + row;
                u32::try_from(at).ok()
            })
        })
        .collect::<Option<Vec<u32>>>()
        .filter(|map| map.len() == k.row_idx.len())
}

impl GpuFactorization {
    /// Records the factorization of `k`'s pattern into `g` (made by
    /// [`GpuFactor::allocate`] from `f`'s structure, placed as `place`
    /// says). Refused where `g`'s values span over two buffers, or `k` is not
    /// the pattern `f` was analysed for.
    pub fn new(
        ctx: &Context,
        kernels: &Arc<FactorKernels>,
        g: &GpuFactor,
        place: &Placement,
        f: &SupernodalFactor,
        k: &SymCsc,
    ) -> Result<GpuFactorization, GpuError> {
        if g.vals.len() > VALUE_BUFFERS || g.precision != crate::precision::Precision::F64 {
            return Err(GpuError::LimitExceeded {
                what: format!(
                    "a Cholesky factor factored on the GPU ({} values in {} buffers)",
                    g.nnz,
                    g.vals.len()
                ),
                limit_name: "max_storage_buffer_binding_size",
                needed: 8 * g.nnz as u64,
                limit: g.vals.first().map_or(0, |b| b.size()),
            });
        }
        let t = std::time::Instant::now();
        let map = value_map(f, place, k).ok_or_else(|| {
            GpuError::Backend("the matrix is not the pattern of the factor's analysis".into())
        })?;
        let mapped = t.elapsed().as_secs_f64();
        let nnz_k = map.len();
        let plan = FactorizationPlan::new(f, place, nnz_k, kernels.choice)
            .ok_or_else(|| GpuError::Backend("a factor's structure over 32-bit offsets".into()))?;
        log::debug!(
            "GPU factorization planned (K's map {mapped:.3} s, plan {:.3} s): {}",
            t.elapsed().as_secs_f64() - mapped,
            plan.describe()
        );
        let t = std::time::Instant::now();
        // llvmpipe (lavapipe) ends an invocation's loops after 65,535
        // iterations in all: a longer one would leave a wrong factor.
        let longest = plan.steps.iter().map(|s| s.serial).max().unwrap_or(0);
        if ctx.info.device_type == wgpu::DeviceType::Cpu && longest >= CPU_LOOP_LIMIT {
            return Err(GpuError::LimitExceeded {
                what: "a GPU factorization's longest loop on a CPU adapter".into(),
                limit_name: "llvmpipe's loop iterations per invocation",
                needed: longest,
                limit: CPU_LOOP_LIMIT,
            });
        }
        let ns = f.len();
        let (o_map, o_task) = (ns, ns + nnz_k);
        let o_xo = o_task + plan.tasks.len();
        let o_gvo = o_xo + plan.xo.len();
        let o_dptr = o_gvo + plan.gvo.len();
        let o_dlist = o_dptr + plan.dptr.len();
        let fidx_data: Vec<u32> = place
            .order
            .iter()
            .map(|&s| s as u32)
            .chain(map)
            .chain(plan.tasks.iter().copied())
            .chain(plan.xo.iter().copied())
            .chain(plan.gvo.iter().copied())
            .chain(plan.dptr.iter().copied())
            .chain(plan.dlist.iter().copied())
            .collect();
        if fidx_data.len() > u32::MAX as usize {
            return Err(GpuError::Backend(
                "a factorization's index over 32-bit offsets".into(),
            ));
        }
        let fidx = ctx.storage_init("factorization index", &fidx_data)?;
        drop(fidx_data);
        let kv = ctx.storage("K values for the GPU factorization", 8 * nnz_k as u64)?;
        let flag = ctx.storage("factorization flag", 4)?;
        let xs = ctx.storage("inverse diagonal blocks (scratch)", 8 * plan.x_len)?;
        // The second buffer's values from c1 on, where there is one.
        let c1 = match (g.vals.get(1), place.starts.get(1)) {
            (Some(_), Some(&c1)) => c1 as u32,
            _ => u32::MAX,
        };
        let o = g.offsets;
        let mut params = Vec::with_capacity(plan.steps.len());
        let mut steps = Vec::with_capacity(plan.steps.len());
        for st in &plan.steps {
            let p = FactorParams {
                o_sn: o[0],
                o_rows: o[1],
                o_tptr: o[3],
                o_tpos: o[4],
                o_owner: o[6],
                o_slot_owner: o[7],
                o_order: 0,
                o_map: o_map as u32,
                o_task: o_task as u32,
                o_xo: o_xo as u32,
                o_gvo: o_gvo as u32,
                o_dptr: o_dptr as u32,
                o_dlist: o_dlist as u32,
                c1,
                ..st.params
            };
            params.push(ctx.uniform_of("factorization params", &p)?);
            let groups = match st.stage {
                Stage::Diag
                | Stage::Below
                | Stage::Trailing
                | Stage::InvOffdiag
                | Stage::InvBelow
                | Stage::UpdateTiled
                | Stage::InvOffdiagParts => st.items,
                _ => st.items.div_ceil(FLAT_WG as u64),
            };
            steps.push((st.stage, ctx.dims(ENTRIES[st.stage as usize].0, groups)?));
        }
        let indexed = t.elapsed().as_secs_f64();
        let bound = GpuFactorization::bound(
            ctx,
            kernels,
            Recorded {
                fidx,
                kv,
                flag,
                xs,
                params,
                steps,
                nnz_k,
                work: plan.work(),
            },
            g,
        );
        log::debug!(
            "GPU factorization recorded: index and parameters {indexed:.3} s, bindings {:.3} s",
            t.elapsed().as_secs_f64() - indexed
        );
        bound
    }

    /// This recording for `g`, a factor of the same structure (made by
    /// [`GpuFactor::twin`] from the one it was recorded for): its buffers
    /// and dispatches shared, its bind groups made again for `g`'s values.
    /// No index, map or plan is made or sent again, and `K`'s values, the
    /// flag and the scratch are this recording's (a factorization of `g`
    /// runs after this one's has finished: one queue).
    pub fn for_factor(&self, ctx: &Context, g: &GpuFactor) -> Result<GpuFactorization, GpuError> {
        if g.vals.len() != self.vals.len()
            || g.vals
                .iter()
                .zip(&self.vals)
                .any(|(a, b)| a.size() != b.size())
        {
            return Err(GpuError::Backend(
                "a factorization recorded for a factor of another structure".into(),
            ));
        }
        let r = &self.recorded;
        let recorded = Recorded {
            fidx: r.fidx.clone(),
            kv: r.kv.clone(),
            flag: r.flag.clone(),
            xs: r.xs.clone(),
            params: r.params.clone(),
            steps: r.steps.clone(),
            nnz_k: r.nnz_k,
            work: r.work,
        };
        GpuFactorization::bound(ctx, &self.kernels, recorded, g)
    }

    /// `recorded`'s dispatches bound to `g`'s index and values.
    fn bound(
        ctx: &Context,
        kernels: &Arc<FactorKernels>,
        recorded: Recorded,
        g: &GpuFactor,
    ) -> Result<GpuFactorization, GpuError> {
        let vals = g.vals.clone();
        let one = match vals.get(1) {
            Some(b) => b.clone(),
            None => ctx.storage("factorization's second values (none)", 16)?,
        };
        let r = &recorded;
        let bgs = r
            .params
            .iter()
            .map(|buf| {
                kernels.shader.bind(
                    ctx,
                    &[
                        (0, buf),
                        (1, &g.idx),
                        (2, &r.fidx),
                        (3, &vals[0]),
                        (4, &r.kv),
                        (5, &r.flag),
                        (6, &r.xs),
                        (7, &one),
                    ],
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        let steps = recorded.steps.len();
        Ok(GpuFactorization {
            kernels: kernels.clone(),
            bgs,
            vals,
            second: one,
            recorded,
            submitted: AtomicUsize::new(steps),
            slice: AtomicUsize::new(steps),
        })
    }

    /// Modelled work of one factorization ([`FactorizationPlan::work`]).
    pub fn work(&self) -> KernelWork {
        self.recorded.work
    }

    /// Stored entries of the matrices it factors.
    pub fn nnz_k(&self) -> usize {
        self.recorded.nnz_k
    }

    /// Factor `values` (the stored values of the pattern it was recorded
    /// for, in `SymCsc` order) into the factor's buffer: `K`'s values go up,
    /// every dispatch is recorded in one pass and submitted, and the pivot
    /// flag comes back (one wait). [`GpuError::NotPositiveDefinite`] where a
    /// pivot was not positive.
    #[cfg(test)]
    pub fn run(&self, ctx: &Context, values: &[f64]) -> Result<(), GpuError> {
        self.submit_sliced(ctx, values, true, 1)?;
        self.finish(ctx, true)
    }

    /// [`GpuFactorization::run`]'s submission alone, the host going on at
    /// once, in `slices` submissions of about as many dispatches each, in
    /// their order: the first now, with `K`'s values;
    /// each next by [`GpuFactorization::submit_next`], the rest by
    /// [`GpuFactorization::finish`]. The queue runs them in order, so the
    /// factor is the one submission's, to the bit; in between, other work
    /// on the queue runs after the slices before it. `timed` holds for one
    /// slice only (a pass's times are of one pass: read back by `finish`; a
    /// pass submitted ahead is not timed, another timed pass in between
    /// would overwrite its times).
    pub fn submit_sliced(
        &self,
        ctx: &Context,
        values: &[f64],
        timed: bool,
        slices: usize,
    ) -> Result<(), GpuError> {
        let r = &self.recorded;
        if values.len() != r.nnz_k {
            return Err(GpuError::Backend(format!(
                "{} values for a pattern of {} entries",
                values.len(),
                r.nnz_k
            )));
        }
        ctx.write_buffer(&r.kv, 0, bytemuck::cast_slice(values));
        ctx.write_buffer(&r.flag, 0, bytemuck::bytes_of(&u32::MAX));
        let slices = slices.max(1);
        self.slice
            .store(r.steps.len().div_ceil(slices).max(1), Ordering::Relaxed);
        self.submitted.store(0, Ordering::Relaxed);
        self.submit_steps(ctx, timed && slices == 1)
    }

    /// The next slice of a [`GpuFactorization::submit_sliced`] run, where
    /// one is left; whether one was.
    pub fn submit_next(&self, ctx: &Context) -> Result<bool, GpuError> {
        if self.submitted.load(Ordering::Relaxed) >= self.recorded.steps.len() {
            return Ok(false);
        }
        self.submit_steps(ctx, false)?;
        Ok(true)
    }

    /// Slices submitted of the run under way, and slices in all.
    pub fn slices_submitted(&self) -> (usize, usize) {
        let slice = self.slice.load(Ordering::Relaxed).max(1);
        let steps = self.recorded.steps.len();
        (
            self.submitted.load(Ordering::Relaxed).div_ceil(slice),
            steps.div_ceil(slice),
        )
    }

    /// One slice: the dispatches from the submitted ones on (the first
    /// slice clears the factor and the scratch first), in one pass and one
    /// submission.
    fn submit_steps(&self, ctx: &Context, timed: bool) -> Result<(), GpuError> {
        let r = &self.recorded;
        let from = self.submitted.load(Ordering::Relaxed);
        let to = (from + self.slice.load(Ordering::Relaxed)).min(r.steps.len());
        let pipelines = self
            .kernels
            .kernels()
            .iter()
            .map(|k| k.pipeline(ctx, 1))
            .collect::<Result<Vec<_>, _>>()?;
        let mut enc = ctx.encoder("Cholesky factorization");
        if from == 0 {
            for b in &self.vals {
                enc.clear_buffer(b, 0, None);
            }
            enc.clear_buffer(&r.xs, 0, None);
        }
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("Cholesky factorization"),
                timestamp_writes: if timed { ctx.pass_timestamps() } else { None },
            });
            for ((stage, dims), bg) in r.steps[from..to].iter().zip(&self.bgs[from..to]) {
                dispatch(&mut pass, &pipelines[*stage as usize], bg, *dims);
            }
        }
        // Its work is a set-up's, logged with it (`GpuSolver`'s set-up
        // line), not counted with the PCG iterations' kernels; its pass
        // time counts with the run's GPU seconds.
        if timed {
            ctx.resolve_pass_time(&mut enc);
        }
        ctx.submit(Some(enc));
        self.submitted.store(to, Ordering::Relaxed);
        Ok(())
    }

    /// Waits for the submitted factorization (its slices not yet submitted
    /// submitted first) and reads its pivot flag (and its pass's times
    /// where `timed`): one wait.
    /// [`GpuError::NotPositiveDefinite`] where a pivot was not positive.
    pub fn finish(&self, ctx: &Context, timed: bool) -> Result<(), GpuError> {
        // The slices not yet submitted, at once.
        if self.submitted.load(Ordering::Relaxed) < self.recorded.steps.len() {
            self.slice
                .store(self.recorded.steps.len(), Ordering::Relaxed);
            self.submit_steps(ctx, false)?;
        }
        let mut parts: Vec<(&wgpu::Buffer, u64)> = vec![(&self.recorded.flag, 4)];
        let timed = timed && ctx.pass_time_buffer().is_some();
        if timed {
            parts.extend(ctx.pass_time_buffer());
        }
        let mut read = ctx.read_parts(&parts, &mut None, None)?;
        if timed {
            let times = read.pop().unwrap_or_default();
            ctx.count_pass_time(&times);
            ctx.recycle(times);
        }
        let bytes = read.into_iter().next().unwrap_or_default();
        let flag: Option<u32> = bytes.get(..4).map(bytemuck::pod_read_unaligned);
        ctx.recycle(bytes);
        match flag {
            Some(u32::MAX) => Ok(()),
            Some(c) => {
                log::debug!("GPU Cholesky factorization: pivot of column {c} not positive");
                Err(GpuError::NotPositiveDefinite)
            }
            None => Err(GpuError::Backend("factorization flag not read".into())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use solver_cpu::{CholeskySolver, FillOrdering, SpdSolver, SystemKind};

    /// A test solver whose device has `SHADER_F64` (the factorization's
    /// kernels are f64); `None` skips the test.
    fn f64_solver() -> Option<crate::GpuSolver> {
        crate::test_solver().filter(|s| s.ctx.shader_f64)
    }

    /// The default factorization: the GPU on hardware with f64 shaders, the
    /// host on a CPU emulation or without f64; a solver opened on the test
    /// adapter takes the default of that adapter unless one is asked for.
    #[test]
    fn factorization_default_follows_the_adapter() {
        let adapter = |device_type: &str, shader_f64| crate::AdapterSummary {
            name: "test".into(),
            backend: "Vulkan".into(),
            device_type: device_type.into(),
            driver: String::new(),
            driver_info: String::new(),
            shader_f64,
            timestamp_query: false,
        };
        assert_eq!(
            Factorization::on(&adapter("DiscreteGpu", true)),
            Factorization::Gpu
        );
        assert_eq!(
            Factorization::on(&adapter("IntegratedGpu", true)),
            Factorization::Gpu
        );
        assert_eq!(
            Factorization::on(&adapter("DiscreteGpu", false)),
            Factorization::Host
        );
        assert_eq!(
            Factorization::on(&adapter("Cpu", true)),
            Factorization::Host
        );
        let Some(s) = crate::test_solver() else {
            return;
        };
        if Factorization::asked().is_none() {
            let a = crate::default_adapter().expect("the test solver's adapter");
            assert_eq!(s.factorization(), Factorization::on(&a));
            assert_eq!(Factorization::from_env(), Factorization::on(&a));
        }
    }

    /// A grid's second neighbourhood (the pattern of a squared Laplacian, as
    /// the shape `K`'s two rings), diagonally dominant: `nx x ny` unknowns.
    fn two_ring_grid(nx: usize, ny: usize) -> SymCsc {
        let id = |i: usize, j: usize| i * ny + j;
        let mut pairs = Vec::new();
        for i in 0..nx {
            for j in 0..ny {
                for (di, dj) in [(0, 0), (0, 1), (0, 2), (1, -1), (1, 0), (1, 1), (2, 0)] {
                    let (a, b) = (i as i64 + di, j as i64 + dj);
                    if a < nx as i64 && b >= 0 && b < ny as i64 {
                        pairs.push((id(a as usize, b as usize), id(i, j)));
                    }
                }
            }
        }
        let mut k = SymCsc::from_pattern(nx * ny, pairs);
        let mut diag = vec![0.5; k.n];
        for j in 0..k.n {
            for s in k.col_ptr[j]..k.col_ptr[j + 1] {
                let r = k.row_idx[s];
                if r != j {
                    let v = -1.0 / (1.0 + ((r * 31 + j * 17) % 5) as f64);
                    k.values[s] = v;
                    diag[r] -= v;
                    diag[j] -= v;
                }
            }
        }
        for (j, d) in diag.into_iter().enumerate() {
            k.values[k.col_ptr[j]] = d;
        }
        k
    }

    /// A dense, diagonally dominant matrix: one supernode of `n` columns,
    /// wider than a workgroup.
    fn dense(n: usize) -> SymCsc {
        let mut k = SymCsc::from_pattern(n, (0..n).flat_map(|j| (j..n).map(move |i| (i, j))));
        for j in 0..n {
            for p in k.col_ptr[j]..k.col_ptr[j + 1] {
                let i = k.row_idx[p];
                k.values[p] = match i == j {
                    true => n as f64,
                    false => 1.0 / (1.0 + ((i * 7 + j) % 5) as f64),
                };
            }
        }
        k
    }

    /// The host's factor of `k` (supernodal or simplicial), its diagonal
    /// blocks inverted.
    /// `f`'s factor allocated on the device (its values in buffers of at
    /// most `limit` bytes), its placement, and the factorization of `k`'s
    /// values into it recorded.
    fn recorded(
        ctx: &Context,
        kernels: &Arc<FactorKernels>,
        f: &SupernodalFactor,
        k: &SymCsc,
        limit: u64,
    ) -> (GpuFactor, Placement, GpuFactorization) {
        let (g, place) = GpuFactor::allocate(ctx, f, limit).unwrap();
        let fac = GpuFactorization::new(ctx, kernels, &g, &place, f, k).unwrap();
        (g, place, fac)
    }

    fn host(k: &SymCsc, supernodal: bool) -> SupernodalFactor {
        let mut c = CholeskySolver::new();
        c.supernodal = supernodal;
        c.set_fill_ordering(FillOrdering::NestedDissection);
        c.prepare(k).unwrap();
        let mut f = c.take_supernodal_factor().unwrap();
        f.invert_diagonal_blocks();
        f
    }

    /// The GPU's factor of `k` on `f`'s structure, its values in `f`'s
    /// order; and the factorization's recorded work.
    fn gpu(
        ctx: &Context,
        f: &SupernodalFactor,
        k: &SymCsc,
        choice: KernelChoice,
    ) -> (Vec<f64>, KernelWork) {
        let kernels = FactorKernels::with_choice(ctx, choice);
        let (g, place, fac) = recorded(ctx, &kernels, f, k, crate::matrix::binding_limit(ctx));
        fac.run(ctx, &k.values).unwrap();
        let got: Vec<f64> = ctx.read(&g.vals[0], g.nnz, &mut None, None).unwrap();
        let mut out = vec![0.0; g.nnz];
        for s in 0..f.len() {
            let (a, b) = (f.val_ptr[s] as usize, f.val_ptr[s + 1] as usize);
            let vo = place.vo[s] as usize;
            out[a..b].copy_from_slice(&got[vo..vo + b - a]);
        }
        (out, fac.work())
    }

    /// The GPU factors and inverts as the host does (faer's factor, then
    /// `invert_diagonal_blocks`), to rounding, on supernodal and simplicial
    /// structures; the work recorded is the plan's, made from
    /// the structure alone.
    #[test]
    fn gpu_factor_is_the_hosts() {
        let Some(s) = f64_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let cases = [(1, 1), (3, 2), (40, 30), (90, 70), (0, 300), (0, 600)];
        for (nx, ny) in cases {
            let k = match nx {
                0 => dense(ny),
                _ => two_ring_grid(nx, ny),
            };
            for supernodal in [true, false] {
                let f = host(&k, supernodal);
                let scale = f.values64.iter().map(|v| v.abs()).fold(0.0, f64::max);
                // Each kernel of the stages with two: tiles everywhere, a
                // lane an entry everywhere, and the model's mix.
                for choice in [
                    KernelChoice::Tiles,
                    KernelChoice::Entries,
                    KernelChoice::Model,
                ] {
                    let (got, work) = gpu(ctx, &f, &k, choice);
                    // The diagonal blocks' upper triangles are not the
                    // factor's (the host leaves them as they were, the GPU
                    // clears them).
                    let mut err = 0.0f64;
                    for b in 0..f.len() {
                        let (m, q) = f.shape(b);
                        let v = f.val_ptr[b] as usize;
                        for j in 0..m {
                            for i in j..m + q {
                                let at = v + j * (m + q) + i;
                                err = err.max((got[at] - f.values64[at]).abs());
                            }
                            for i in 0..j {
                                assert_eq!(got[v + j * (m + q) + i], 0.0);
                            }
                        }
                    }
                    assert!(
                        err <= 1e-11 * scale,
                        "{nx} x {ny}, supernodal {supernodal}, {choice:?}: {err:e} against {scale:e}"
                    );
                    let place = one_chunk_placement(&f).unwrap();
                    let plan = FactorizationPlan::new(&f, &place, k.row_idx.len(), choice).unwrap();
                    assert_eq!(work, plan.work());
                    if choice == KernelChoice::Model {
                        assert_eq!(Some(work), factorization_work(&f, k.row_idx.len()));
                    }
                    // Each choice's kernels, where the structure has them.
                    let used = |st: Stage| plan.stages()[st as usize].0 > 0;
                    let (tiles, entries) = (
                        choice == KernelChoice::Tiles,
                        choice == KernelChoice::Entries,
                    );
                    assert!(
                        !(tiles
                            && (used(Stage::Update)
                                || used(Stage::TrailingEntries)
                                || used(Stage::InvOffdiagParts)))
                    );
                    assert!(
                        !(entries
                            && (used(Stage::UpdateTiled)
                                || used(Stage::Trailing)
                                || used(Stage::InvOffdiag)))
                    );
                    if tiles {
                        assert!(used(Stage::UpdateTiled));
                    }
                    if f.len() == 1 && f.shape(0).0 > 2 * BLOCK {
                        assert!(used(Stage::Trailing) || used(Stage::TrailingEntries));
                        assert!(used(Stage::InvOffdiag) || used(Stage::InvOffdiagParts));
                    }
                }
                let levels = f.levels().unwrap().iter().max().map_or(0, |&l| l + 1);
                if nx * ny > 100 {
                    assert!(f.len() > 1 && levels > 1, "{} supernodes", f.len());
                }
                if nx == 0 && supernodal {
                    assert_eq!(f.len(), 1);
                }
            }
        }
    }

    /// A factorization submitted in slices, another submission between two
    /// of them and the rest left to `finish`, makes the one submission's
    /// factor, to the bit; the slices are counted as submitted.
    #[test]
    fn a_factorization_in_slices_is_the_one_submissions() {
        let Some(s) = f64_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = two_ring_grid(40, 30);
        let f = host(&k, true);
        let kernels = FactorKernels::new(ctx).unwrap();
        let limit = crate::matrix::binding_limit(ctx);
        let read = |g: &GpuFactor| ctx.read::<f64>(&g.vals[0], g.nnz, &mut None, None).unwrap();
        let (g, _, fac) = recorded(ctx, &kernels, &f, &k, limit);
        fac.run(ctx, &k.values).unwrap();
        let whole = read(&g);
        let steps = fac.recorded.steps.len();
        assert!(steps >= 8, "{steps} dispatches");
        let (g2, _, sliced) = recorded(ctx, &kernels, &f, &k, limit);
        sliced.submit_sliced(ctx, &k.values, false, 4).unwrap();
        assert_eq!(sliced.slices_submitted(), (1, 4));
        assert!(sliced.submit_next(ctx).unwrap());
        // Another submission on the queue between two slices.
        let other = ctx
            .storage_init("another submission's buffer", &[7.0f64; 64])
            .unwrap();
        let mut enc = ctx.encoder("another submission");
        enc.clear_buffer(&other, 0, None);
        ctx.submit(Some(enc));
        assert!(sliced.submit_next(ctx).unwrap());
        assert_eq!(sliced.slices_submitted(), (3, 4));
        sliced.finish(ctx, false).unwrap();
        assert_eq!(sliced.slices_submitted(), (1, 1));
        assert!(!sliced.submit_next(ctx).unwrap());
        assert!(
            read(&g2) == whole,
            "the sliced factor differs from the whole one's"
        );
        assert!(whole.iter().any(|&v| v != 0.0));
    }

    /// A factor whose values are cut over two buffers (a binding of a third
    /// of them) factors as in one, to the bit; over three it is refused.
    #[test]
    fn values_over_two_buffers_factor_as_one() {
        let Some(s) = f64_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = two_ring_grid(60, 50);
        let f = host(&k, true);
        let kernels = FactorKernels::new(ctx).unwrap();
        let bytes = 8 * f.nnz() as u64;
        let mut out = Vec::new();
        for limit in [crate::matrix::binding_limit(ctx), bytes * 3 / 5] {
            let (g, _, fac) = recorded(ctx, &kernels, &f, &k, limit);
            fac.run(ctx, &k.values).unwrap();
            let mut got = Vec::new();
            for b in &g.vals {
                got.extend(
                    ctx.read::<f64>(b, b.size() as usize / 8, &mut None, None)
                        .unwrap(),
                );
            }
            got.truncate(f.nnz());
            out.push((g.vals.len(), got));
        }
        assert_eq!((out[0].0, out[1].0), (1, 2));
        assert!(out[0].1 == out[1].1, "two buffers differ from one");
        // Over two, refused before any buffer is made.
        assert!(matches!(
            GpuFactor::allocate(ctx, &f, bytes / 4),
            Err(GpuError::LimitExceeded { .. })
        ));
    }

    /// A recording bound to a twin of its factor (the index shared, the
    /// values new) factors another matrix of the pattern as a recording
    /// made for it does, to the bit, and leaves the first factor as it was.
    #[test]
    fn a_recording_bound_to_a_twin_factors_as_a_new_one() {
        let Some(s) = f64_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = two_ring_grid(40, 30);
        let mut k2 = k.clone();
        for j in 0..k2.n {
            k2.values[k2.col_ptr[j]] *= 1.5;
        }
        let f = host(&k, true);
        let kernels = FactorKernels::new(ctx).unwrap();
        let limit = crate::matrix::binding_limit(ctx);
        let read =
            |g: &GpuFactor| -> Vec<f64> { ctx.read(&g.vals[0], g.nnz, &mut None, None).unwrap() };
        let (g, _, fac) = recorded(ctx, &kernels, &f, &k, limit);
        fac.run(ctx, &k.values).unwrap();
        let first = read(&g);
        let twin = g.twin(ctx).unwrap();
        fac.for_factor(ctx, &twin)
            .unwrap()
            .run(ctx, &k2.values)
            .unwrap();
        let (fresh, place) = GpuFactor::allocate(ctx, &f, limit).unwrap();
        GpuFactorization::new(ctx, &kernels, &fresh, &place, &f, &k2)
            .unwrap()
            .run(ctx, &k2.values)
            .unwrap();
        let (a, b) = (read(&twin), read(&fresh));
        assert!(a == b, "the twin's factor differs from a new recording's");
        assert!(a != first, "the second matrix's factor is the first's");
        assert!(read(&g) == first, "the first factor changed");
        // A factor of another structure is refused.
        let other = host(&two_ring_grid(20, 20), true);
        let (h, _) = GpuFactor::allocate(ctx, &other, limit).unwrap();
        assert!(fac.for_factor(ctx, &h).is_err());
    }

    /// A pivot that is not positive is an error naming none of the values
    /// written; the same recording then factors good values.
    #[test]
    fn a_pivot_not_positive_is_refused() {
        let Some(s) = f64_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = two_ring_grid(20, 15);
        let f = host(&k, true);
        let kernels = FactorKernels::new(ctx).unwrap();
        let (g, place, fac) = recorded(ctx, &kernels, &f, &k, crate::matrix::binding_limit(ctx));
        let mut bad = k.values.clone();
        bad[k.col_ptr[k.n / 2]] = -1.0;
        assert_eq!(fac.run(ctx, &bad), Err(GpuError::NotPositiveDefinite));
        assert!(fac.run(ctx, &k.values).is_ok());
        assert!(matches!(
            fac.run(ctx, &k.values[1..]),
            Err(GpuError::Backend(_))
        ));
        // A matrix of another pattern is refused.
        let other = two_ring_grid(15, 20);
        assert!(GpuFactorization::new(ctx, &kernels, &g, &place, &f, &other).is_err());
    }

    /// The scale factors' own factor (of the scalar matrix a solver
    /// prepares) is made on the GPU where asked for. Where the device
    /// refuses it (its values over two buffers) the host makes it, and the
    /// GPU is not asked again for that kind; the solves are the same.
    #[test]
    fn a_refused_factorization_is_made_on_the_host_once() {
        let Some(s) = f64_solver() else {
            return;
        };
        let k = two_ring_grid(60, 50);
        let bytes = 8 * host(&k, true).nnz() as u64;
        drop(s);
        let b: Vec<f64> = (0..k.n).map(|i| ((i * 13) % 7) as f64 - 3.0).collect();
        let mut solutions = Vec::new();
        for (limit, refused) in [(None, false), (Some(bytes * 2 / 5), true)] {
            let mut s = crate::open_with(crate::OpenOptions {
                adjust_limits: limit.map(|l| -> crate::device::LimitsHook {
                    Box::new(move |lim: &mut wgpu::Limits| lim.max_storage_buffer_binding_size = l)
                }),
                ..Default::default()
            })
            .unwrap();
            s.set_factorization(Factorization::Gpu);
            s.set_system_kind(SystemKind::ScaleFactors);
            assert!(s.factors_on_gpu(SystemKind::ScaleFactors));
            let up = s.ctx.traffic().to_device;
            s.prepare(&k).unwrap();
            let up = s.ctx.traffic().to_device - up;
            assert!(s.chol.is_some(), "limit {limit:?}");
            assert_eq!(s.gpu_factor_refused, [false, refused], "limit {limit:?}");
            assert_eq!(s.factors_on_gpu(SystemKind::ScaleFactors), !refused);
            // Made on the host, the factor's values went up; made on the
            // GPU, the matrix's values (and its index) only.
            assert_eq!(up >= bytes, refused, "{up} bytes up, the factor {bytes}");
            let mut x = b.clone();
            s.solve_in_place(&mut x, 1).unwrap();
            solutions.push(x);
        }
        let mut r = vec![0.0; k.n];
        k.mul_vec(&solutions[1], &mut r);
        let residual = r
            .iter()
            .zip(&b)
            .map(|(a, c)| (a - c).abs())
            .fold(0.0, f64::max);
        assert!(residual < 1e-8, "residual {residual:e}");
        let apart = solutions[0]
            .iter()
            .zip(&solutions[1])
            .map(|(a, c)| (a - c).abs())
            .fold(0.0, f64::max);
        assert!(
            apart < 1e-8,
            "GPU-made and host-made factors' solves {apart:e} apart"
        );
    }

    #[test]
    fn diag_steps_count_the_tile() {
        // One column: load, pivot, store (no column right of it).
        assert_eq!(diag_steps(1), 2 + 1);
        // A full tile: four entries a lane in the load and the store; per
        // column its pivot, then the 32 - k - 1 columns right of it, 8 a
        // round of the workgroup's lanes.
        let right: u64 = (0..32).map(|k: u64| (31 - k).div_ceil(8)).sum();
        assert_eq!(right, 8 + 2 * 8 + 3 * 8 + 4 * 7);
        assert_eq!(diag_steps(32), 8 + 32 + right);
    }

    /// The update's counts and `update_tiled`'s lists, against the sums
    /// taken entry by entry: each value's descendants holding both its rows
    /// (`update`'s merge), their columns summed per level; and per tile
    /// column of a supernode, every descendant holding one of its columns,
    /// in level order, with its first row at or past the tile column.
    #[test]
    fn update_work_and_lists_are_the_entries_sums() {
        for (nx, ny) in [(40, 30), (90, 70)] {
            let f = host(&two_ring_grid(nx, ny), true);
            let ns = f.len();
            let level = f.levels().unwrap();
            let depth = *level.iter().max().unwrap() as usize + 1;
            let place = one_chunk_placement(&f).unwrap();
            let rank: Vec<usize> = {
                let mut r = vec![0; ns];
                place.order.iter().enumerate().for_each(|(i, &s)| r[s] = i);
                r
            };
            // Each row's holders, in level order.
            let mut holders: Vec<Vec<usize>> = vec![Vec::new(); f.perm.len()];
            for &d in &place.order {
                for &r in &f.rows[f.row_ptr[d] as usize..f.row_ptr[d + 1] as usize] {
                    holders[r as usize].push(d);
                }
            }
            let mut products = vec![0u64; depth];
            for s in 0..ns {
                let (m, q) = f.shape(s);
                let c0 = f.begin[s] as usize;
                let below = &f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize];
                for j in 0..m {
                    for i in j..m + q {
                        let g = if i < m { c0 + i } else { below[i - m] as usize };
                        for d in holders[c0 + j].iter().filter(|d| holders[g].contains(d)) {
                            products[level[s] as usize] += f.shape(*d).0 as u64;
                        }
                    }
                }
            }
            let owner = column_owners(&f).unwrap();
            let work = UpdateWork::new(&f, &owner, &level, depth);
            assert_eq!(work.products, products, "{nx} x {ny}");
            assert!(products.iter().sum::<u64>() > 0);
            // Every level tiled, so every supernode has its lists.
            let tiled = vec![true; depth];
            let lists = UpdateLists::new(&f, &owner, &place.order, &level, &tiled).unwrap();
            for s in 0..ns {
                let (m, _) = f.shape(s);
                let c0 = f.begin[s] as usize;
                for t in 0..m.div_ceil(BLOCK) {
                    let cols = c0 + t * BLOCK..c0 + m.min((t + 1) * BLOCK);
                    let mut want: Vec<usize> = cols
                        .clone()
                        .flat_map(|c| holders[c].iter().copied())
                        .collect();
                    want.sort_by_key(|&d| rank[d]);
                    want.dedup();
                    let l = lists.base[s] as usize + t;
                    let got =
                        &lists.dlist[2 * lists.dptr[l] as usize..2 * lists.dptr[l + 1] as usize];
                    let ds: Vec<usize> = got.chunks_exact(2).map(|e| e[0] as usize).collect();
                    assert_eq!(ds, want, "{nx} x {ny}: supernode {s}, tile column {t}");
                    for e in got.chunks_exact(2) {
                        let rows = &f.rows[f.row_ptr[e[0] as usize] as usize..];
                        let first = e[1] as usize;
                        assert!(cols.contains(&(rows[first] as usize)));
                        assert!(first == 0 || (rows[first - 1] as usize) < cols.start);
                    }
                }
            }
        }
    }
}
