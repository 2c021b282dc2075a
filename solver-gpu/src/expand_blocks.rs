//! Drives `shaders/expand_blocks.wgsl`: a new symmetric 3x3 block matrix of a
//! prepared pattern goes up as its lower triangle in f64 (72 bytes per lower
//! block, no conversion on the host) and is expanded on the GPU into the
//! block product's chunks: both triangles, held rows and columns the
//! identity, f32 high parts and, where the mixed-precision product exists,
//! low parts (`hi + lo` = `v` to 2^-48).
//!
//! Bindings (group 0): 0 `C` uniform ([`ExpandParams`], one per chunk); 1
//! `lower0` (read, f64); 2 `map` (read, u32 per block,
//! [`LowerParts::device_map`] of [`HostMatrix::map`]); 3 `hi` (read-write,
//! the chunk's values); 4 `lo` (read-write, its low parts or a placeholder);
//! 5-7 `lower1`-`lower3`. Dispatch: `ceil(blocks / 256)` workgroups per
//! chunk, 2-D. Needs `SHADER_F64`; without it the host writes the f32 values
//! itself.
//!
//! The lower blocks are cut into up to [`LOWER_PARTS`] buffers of one
//! storage binding each ([`LowerParts`]; homer 1.2M's, 432 MB, take four of
//! lavapipe's 128 MiB): the block map names a block's part and its offset
//! there, and the kernels that read them (here and `refine_product.wgsl`)
//! bind all four. Past four the host sums the blocks.
//!
//! A shape matrix `K (x) I3 + sum_i R_i^T C_i R_i` goes up as less still:
//! `K`'s values and the `C_i` (8 bytes a lower entry and 48 a ring), and
//! `shaders/sum_shape_blocks.wgsl` sums its lower blocks first ([`ShapeSum`];
//! bindings in the shader's header), one dispatch per part of them. Both
//! kernels go in one submission. A
//! constant term the matrices name, E_m's `S Mt^-1 S`
//! ([`IsoRingSym3::laplacian_square`]), goes up once per model and is added
//! to every later matrix's `K` there.

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
#[cfg(doc)]
use crate::matrix::HostMatrix;
use crate::matrix::{self, Chunk, RingSlots};
use crate::GpuError;
use solver_cpu::{IsoRingSym3, ShapeOperatorModel, SparseRows};
use std::sync::Arc;

pub(crate) const SOURCE: &str = include_str!("../../shaders/expand_blocks.wgsl");
pub(crate) const SUM_SOURCE: &str = include_str!("../../shaders/sum_shape_blocks.wgsl");

const SUM_BINDINGS: [(u32, Bind); 9] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
    (8, Bind::Read),
];

const BINDINGS: [(u32, Bind); 8] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
    (4, Bind::ReadWrite),
    (5, Bind::Read),
    (6, Bind::Read),
    (7, Bind::Read),
];

/// Most buffers the f64 lower blocks may be cut into (the expansion and the
/// refinement's exact product bind each); past them the host sums the
/// blocks and the expansion does not run.
pub(crate) const LOWER_PARTS: usize = 4;

/// Bits of a device `map` entry ([`LowerParts::device_map`]) holding the
/// offset of its lower block in its part; the two above hold the part.
const PART_SHIFT: u32 = 29;

/// The f64 lower blocks of a pattern on the GPU (9 per block, row-major, in
/// the order of the lower CSC input), in up to [`LOWER_PARTS`] buffers of at
/// most one storage binding: part `k` holds blocks `k * part_blocks ..`.
/// The expansion and the refinement's exact product find a block through
/// the device `map`, whose entries name its part and its offset there.
#[derive(Clone)]
pub(crate) struct LowerParts {
    pub buffers: Vec<wgpu::Buffer>,
    pub part_blocks: usize,
    pub blocks: usize,
}

impl LowerParts {
    /// Parts and blocks per part for `blocks` lower blocks within `limit`
    /// bytes a binding: `None` past [`LOWER_PARTS`].
    pub fn layout(blocks: usize, limit: u64) -> Option<(usize, usize)> {
        let cap = ((limit / 72) as usize).min((1 << PART_SHIFT) - 2);
        if cap == 0 {
            return None;
        }
        let parts = blocks.div_ceil(cap).max(1);
        (parts <= LOWER_PARTS).then(|| (parts, blocks.div_ceil(parts).max(1)))
    }

    /// The buffers for `blocks` lower blocks, cut for `limit`.
    pub fn new(ctx: &Context, blocks: usize, limit: u64) -> Result<LowerParts, GpuError> {
        let (parts, part_blocks) =
            Self::layout(blocks, limit).ok_or_else(|| GpuError::LimitExceeded {
                what: format!("the f64 lower blocks ({blocks}) in {LOWER_PARTS} bindings"),
                limit_name: "max_storage_buffer_binding_size",
                needed: 72 * blocks as u64,
                limit: LOWER_PARTS as u64 * limit,
            })?;
        let buffers = (0..parts)
            .map(|k| {
                let n = Self::range_of(k, part_blocks, blocks).len();
                ctx.storage(
                    &format!("lower-triangle f64 values (part {k}, {n} blocks)"),
                    (72 * n.max(1)) as u64,
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(LowerParts {
            buffers,
            part_blocks,
            blocks,
        })
    }

    fn range_of(k: usize, part_blocks: usize, blocks: usize) -> std::ops::Range<usize> {
        (k * part_blocks).min(blocks)..((k + 1) * part_blocks).min(blocks)
    }

    /// The lower blocks of part `k`.
    pub fn range(&self, k: usize) -> std::ops::Range<usize> {
        Self::range_of(k, self.part_blocks, self.blocks)
    }

    /// The block map as the kernels read it: a lower block's index becomes
    /// its part (bits 29-30) and its offset in that part; the transpose bit
    /// and the zero and identity entries are kept.
    pub fn device_map(&self, map: &[u32]) -> Vec<u32> {
        map.iter()
            .map(|&m| match m {
                ZERO | IDENTITY => m,
                m => {
                    let src = (m & !TRANSPOSE) as usize;
                    let k = src / self.part_blocks;
                    let at = (src - k * self.part_blocks) as u32;
                    (m & TRANSPOSE) | ((k as u32) << PART_SHIFT) | at
                }
            })
            .collect()
    }

    /// Part `k`'s buffer, or the first for the parts it lacks (a binding
    /// the kernels never read).
    pub fn part(&self, k: usize) -> &wgpu::Buffer {
        self.buffers.get(k).unwrap_or(&self.buffers[0])
    }

    /// Write the host's lower blocks.
    pub fn write(&self, ctx: &Context, lower: &[[f64; 9]]) {
        for (k, b) in self.buffers.iter().enumerate() {
            ctx.write_buffer_par(b, bytemuck::cast_slice(&lower[self.range(k)]));
        }
    }
}

/// `map` entries of [`HostMatrix::map`] (as in the shader).
pub(crate) const ZERO: u32 = u32::MAX;
pub(crate) const IDENTITY: u32 = u32::MAX - 1;
pub(crate) const TRANSPOSE: u32 = 1 << 31;

/// Parameters of one chunk, as `ExpandParams` in `expand_blocks.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ExpandParams {
    pub(crate) block0: u32,
    pub(crate) blocks: u32,
    pub(crate) split: u32,
    pub(crate) pad: u32,
}

/// Clones share the kernels' compiled pipelines and layouts.
#[derive(Clone)]
pub(crate) struct ExpandBlocks {
    shader: Shader,
    kernel: Kernel,
    sum_shader: Shader,
    sum_kernel: Kernel,
}

/// The recorded expansion into one matrix's chunks.
pub(crate) struct Expansion {
    /// The lower triangle's f64 values, written by the host (or summed by
    /// [`ShapeSum`]) per matrix.
    pub lower: LowerParts,
    /// Per block of both triangles, its lower block's part and offset (the
    /// shader's `map`, [`LowerParts::device_map`]); the refinement's exact
    /// product reads it too ([`crate::refine`]).
    pub map: wgpu::Buffer,
    steps: Vec<(wgpu::BindGroup, (u32, u32))>,
    work: KernelWork,
    /// Kept alive for the bind groups.
    #[allow(dead_code)]
    keep: Vec<wgpu::Buffer>,
}

impl ExpandBlocks {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "expand_blocks.wgsl", SOURCE, &BINDINGS)?;
        let sum_shader = Shader::new(ctx, "sum_shape_blocks.wgsl", SUM_SOURCE, &SUM_BINDINGS)?;
        Ok(ExpandBlocks {
            kernel: Kernel::new(&shader, "expand_blocks", "expand_blocks"),
            shader,
            sum_kernel: Kernel::new(&sum_shader, "sum_shape_blocks", "sum_shape_blocks"),
            sum_shader,
        })
    }

    /// The expansion's and the shape sum's kernels (one column each).
    pub fn kernels(&self) -> [&Kernel; 2] {
        [&self.kernel, &self.sum_kernel]
    }

    /// The expansion of the lower blocks in `lower` through `map` into
    /// `chunks` (their values) and, when given, `lo` (one buffer per chunk).
    pub fn expansion(
        &self,
        ctx: &Context,
        lower: &LowerParts,
        map: &[u32],
        chunks: &[Chunk],
        lo: Option<&[wgpu::Buffer]>,
    ) -> Result<Expansion, GpuError> {
        let lower = lower.clone();
        let map_buf = ctx.storage_init(
            "block map (full block to lower block)",
            &lower.device_map(map),
        )?;
        let placeholder = ctx.storage("expansion placeholder", 4)?;
        let mut steps = Vec::with_capacity(chunks.len());
        let mut keep = vec![map_buf.clone(), placeholder.clone()];
        for (i, c) in chunks.iter().enumerate() {
            let blocks = c.blocks.len();
            let params = ctx.uniform_of(
                "expand_blocks params",
                &ExpandParams {
                    block0: c.blocks.start as u32,
                    blocks: blocks as u32,
                    split: u32::from(lo.is_some()),
                    pad: 0,
                },
            )?;
            let lo_buf = lo.map_or(&placeholder, |l| &l[i]);
            let bg = self.shader.bind(
                ctx,
                &[
                    (0, &params),
                    (1, lower.part(0)),
                    (2, &map_buf),
                    (3, &c.vals),
                    (4, lo_buf),
                    (5, lower.part(1)),
                    (6, lower.part(2)),
                    (7, lower.part(3)),
                ],
            )?;
            steps.push((
                bg,
                ctx.dims("expand_blocks", (blocks as u64).div_ceil(FLAT_WG as u64))?,
            ));
            keep.push(params);
        }
        // Each block's map entry and its source once, its parts written.
        let full = map.len() as u64;
        let parts = if lo.is_some() { 2 } else { 1 };
        let bytes = 4 * full + 72 * lower.blocks as u64 + 36 * parts * full;
        Ok(Expansion {
            lower,
            map: map_buf.clone(),
            steps,
            work: KernelWork::other(bytes),
            keep,
        })
    }

    /// Write `lower` (f64, 9 per lower block) and expand it: one submission.
    pub fn run(&self, ctx: &Context, e: &Expansion, lower: &[[f64; 9]]) -> Result<(), GpuError> {
        e.lower.write(ctx, lower);
        self.submit(ctx, e, None)
    }

    /// Write the shape matrix `a`'s `K` values and `C_i`, sum its lower
    /// blocks ([`ShapeSum`]) and expand them: one submission.
    pub fn run_shape(
        &self,
        ctx: &Context,
        e: &Expansion,
        sum: &ShapeSum,
        a: &IsoRingSym3,
    ) -> Result<(), GpuError> {
        debug_assert!(sum.adds(a.laplacian_square.as_ref()));
        ctx.write_buffer_par(&sum.iso, bytemuck::cast_slice(&a.iso.values));
        ctx.write_buffer_par(&sum.ring_c, bytemuck::cast_slice(&a.ring_c));
        self.submit(ctx, e, Some(sum))
    }

    fn submit(&self, ctx: &Context, e: &Expansion, sum: Option<&ShapeSum>) -> Result<(), GpuError> {
        let pipeline = self.kernel.pipeline(ctx, 1)?;
        let sum_pipeline = match sum {
            Some(_) => Some(self.sum_kernel.pipeline(ctx, 1)?),
            None => None,
        };
        let mut enc = ctx.encoder("expand_blocks");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("expand_blocks"),
                timestamp_writes: None,
            });
            if let (Some(s), Some(p)) = (sum, &sum_pipeline) {
                for (bind, dims) in &s.parts {
                    dispatch(&mut pass, p, bind, *dims);
                }
                ctx.count_kernels(s.work());
            }
            for (bg, dims) in &e.steps {
                dispatch(&mut pass, &pipeline, bg, *dims);
            }
        }
        ctx.count_kernels(e.work);
        ctx.submit(Some(enc));
        Ok(())
    }
}

/// What `sum_shape_blocks.wgsl` needs beyond a matrix's values, made once
/// per pattern and rings: per lower block, its ring pairs `(p, q)` in ring
/// order, each packed with its ring `i` and its positions in row `i` (or as
/// the ring and the weight `R_ip R_iq`: [`PairBuffers`]); the buffers
/// each matrix's `K` values and `C_i` are written to; and the values of
/// the constant term the matrices name, if any (once per model). The sum
/// runs once per part of the lower blocks ([`LowerParts`]), each part's
/// pairs in buffers of their own.
pub(crate) struct ShapeSum {
    /// The rings it was made for (kept to recognise them).
    rings: Arc<SparseRows>,
    iso: wgpu::Buffer,
    ring_c: wgpu::Buffer,
    /// The Laplacian square term's value per lower entry, of `square_of`.
    square: wgpu::Buffer,
    square_of: Option<Arc<ShapeOperatorModel>>,
    /// Per part: its parameters (without the term's flag), their buffer,
    /// its bind group and dispatch size.
    params: Vec<(SumParams, wgpu::Buffer)>,
    pub(crate) parts: Vec<(wgpu::BindGroup, (u32, u32))>,
    nnz: usize,
    /// Bytes of a sum without the constant term.
    bytes: u64,
    /// Kept alive for the bind groups.
    #[allow(dead_code)]
    keep: Vec<wgpu::Buffer>,
}

/// Parameters of `sum_shape_blocks.wgsl`, one part of the lower blocks.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct SumParams {
    /// Lower blocks of the part.
    pub(crate) slots: u32,
    /// 1 where the constant term's values are added, else 0.
    pub(crate) square: u32,
    /// Its first lower block, and the first of its blocks' ring pairs.
    pub(crate) block0: u32,
    pub(crate) pair0: u32,
    /// The bits of each position in a packed ring pair
    /// ([`RingSlots::by_block_packed`]); 0 where the pairs go with their
    /// rings and weights apart.
    pub(crate) bits: u32,
    pub(crate) pad0: u32,
    pub(crate) pad1: u32,
    pub(crate) pad2: u32,
}

impl ShapeSum {
    /// Whether the sum for `a` fits the storage bindings of `limit` bytes:
    /// its lower blocks in at most [`LOWER_PARTS`] parts, each part's ring
    /// pairs in one binding, and `K`'s values (and the term's), the `C_i`
    /// and the pairs' starts in one each.
    pub fn fits(a: &IsoRingSym3, slots: &RingSlots, limit: u64) -> bool {
        Self::fits_pattern((&a.rings, a.iso.row_idx.len(), slots), limit)
    }

    /// [`Self::fits`] for `rings` over a pattern of `l` lower blocks.
    pub fn fits_pattern((rings, l, slots): (&SparseRows, usize, &RingSlots), limit: u64) -> bool {
        let r = rings.len();
        let Some((parts, part_blocks)) = LowerParts::layout(l, limit) else {
            return false;
        };
        let whole = [8 * l as u64, 48 * r as u64, 4 * (l as u64 + 1)];
        // Packed, a pair's 4 bytes and the rows' weights; else its weight's 8.
        let (pair, weights) = match matrix::pack_bits(rings) {
            Some(_) => (4, 8 * (r + rings.w.len()) as u64),
            None => (8, 0),
        };
        whole.iter().all(|&x| x <= limit)
            && weights <= limit
            && slots
                .pairs_per_part(part_blocks, parts)
                .iter()
                .all(|&p| pair * p as u64 <= limit)
    }

    /// Whether this was made for `rings`.
    pub fn of(&self, rings: &Arc<SparseRows>) -> bool {
        Arc::ptr_eq(&self.rings, rings)
    }

    /// Whether it adds the term of `model` (by identity), or none for `None`.
    pub fn adds(&self, model: Option<&Arc<ShapeOperatorModel>>) -> bool {
        match (&self.square_of, model) {
            (Some(a), Some(b)) => Arc::ptr_eq(a, b),
            (None, None) => true,
            _ => false,
        }
    }

    /// From now on, add the term of `model` with its `values` per lower
    /// entry ([`crate::matrix::laplacian_square_values`]), or none; an error
    /// where a model comes without one value per lower entry.
    pub fn set_square(
        &mut self,
        ctx: &Context,
        model: Option<Arc<ShapeOperatorModel>>,
        values: Option<&[f64]>,
    ) -> Result<(), GpuError> {
        self.square_of = None;
        if model.is_some() {
            let v = values.filter(|v| v.len() == self.nnz).ok_or_else(|| {
                GpuError::Backend(format!(
                    "shape sum: the constant term needs {} values, got {}",
                    self.nnz,
                    values.map_or(0, <[f64]>::len)
                ))
            })?;
            ctx.write_buffer(&self.square, 0, bytemuck::cast_slice(v));
        }
        for (p, buf) in &self.params {
            let p = SumParams {
                square: model.is_some() as u32,
                ..*p
            };
            ctx.write_buffer(buf, 0, bytemuck::bytes_of(&p));
        }
        self.square_of = model;
        Ok(())
    }

    /// What one sum reads and writes: K once (and the constant term's
    /// values where added), each block's pairs (packed, or ring and weight)
    /// and its C_i once (packed: and its row's start and two weights), the
    /// lower blocks written.
    fn work(&self) -> KernelWork {
        let square = if self.square_of.is_some() {
            8 * self.nnz as u64
        } else {
            0
        };
        KernelWork {
            dispatches: self.parts.len() as u64,
            ..KernelWork::other(self.bytes + square)
        }
    }

    /// The sum of `a`'s pattern and rings (pairs' slots `slots`) into
    /// `lower` (the pattern's lower blocks), one dispatch per part; its
    /// pairs' buffers `pairs` where they went up ahead (for this pattern
    /// and `lower`'s parts), else sent up here.
    pub fn new(
        k: &ExpandBlocks,
        ctx: &Context,
        (a, slots): (&IsoRingSym3, &RingSlots),
        lower: &LowerParts,
        pairs: Option<PairBuffers>,
    ) -> Result<ShapeSum, GpuError> {
        let pattern = (&a.rings, a.iso.row_idx.len(), slots);
        Self::of_pattern(k, ctx, pattern, lower, pairs)
    }

    /// [`Self::new`] for `rings` over a pattern of `nnz` lower blocks:
    /// the sum reads no value of a matrix until it runs.
    pub fn of_pattern(
        k: &ExpandBlocks,
        ctx: &Context,
        (rings, nnz, slots): (&Arc<SparseRows>, usize, &RingSlots),
        lower: &LowerParts,
        pairs: Option<PairBuffers>,
    ) -> Result<ShapeSum, GpuError> {
        let pairs = match pairs {
            Some(p) if p.blocks == nnz && p.parts.len() == lower.buffers.len() => p,
            _ => PairBuffers::upload(
                ctx,
                (rings, nnz, slots),
                (lower.part_blocks, lower.buffers.len()),
            )?,
        };
        let iso = ctx.storage("shape sum: K values (f64)", 8 * nnz.max(1) as u64)?;
        let ring_c = ctx.storage(
            "shape sum: ring matrices C_i (f64)",
            48 * rings.len().max(1) as u64,
        )?;
        let square = ctx.storage(
            "shape sum: constant term's values (f64)",
            8 * nnz.max(1) as u64,
        )?;
        let start_buf = pairs.start;
        let (bits, row_start, weights) = match pairs.rows {
            Some((bits, row_start, weights)) => (bits, Some(row_start), Some(weights)),
            None => (0, None, None),
        };
        // Unpacked, the rows' starts are not read: a placeholder.
        let row_start = match row_start {
            Some(b) => b,
            None => ctx.storage("shape sum: rows' weights' starts (unread)", 4)?,
        };
        let mut keep = vec![start_buf.clone(), row_start.clone()];
        let mut params = Vec::new();
        let mut parts = Vec::new();
        for (part, (out, (ring_buf, f_buf, pair0))) in
            lower.buffers.iter().zip(pairs.parts).enumerate()
        {
            let blocks = lower.range(part);
            let p = SumParams {
                slots: blocks.len() as u32,
                square: 0,
                block0: blocks.start as u32,
                pair0,
                bits,
                ..SumParams::default()
            };
            // Packed, every part weighs its pairs from the rows' weights.
            let f_buf = f_buf
                .or_else(|| weights.clone())
                .ok_or_else(|| GpuError::Backend("shape sum: pairs without weights".into()))?;
            let p_buf = ctx.uniform_of("sum_shape_blocks params", &p)?;
            let bind = k.sum_shader.bind(
                ctx,
                &[
                    (0, &p_buf),
                    (1, &iso),
                    (2, &ring_c),
                    (3, &start_buf),
                    (4, &ring_buf),
                    (5, &f_buf),
                    (6, out),
                    (7, &square),
                    (8, &row_start),
                ],
            )?;
            let dims = ctx.dims(
                "sum_shape_blocks",
                (blocks.len() as u64).div_ceil(FLAT_WG as u64),
            )?;
            parts.push((bind, dims));
            params.push((p, p_buf));
            keep.extend([ring_buf, f_buf]);
        }
        let pair_bytes = match bits {
            0 => 4 + 8 + 48,
            _ => 4 + 4 + 16 + 48,
        };
        let bytes = 8 * nnz as u64
            + 4 * (nnz as u64 + 1)
            + pairs.pairs as u64 * pair_bytes
            + 72 * nnz as u64;
        Ok(ShapeSum {
            rings: rings.clone(),
            iso,
            ring_c,
            square,
            square_of: None,
            params,
            parts,
            nnz,
            bytes,
            keep,
        })
    }
}

/// The ring pairs of a shape pattern gathered by lower block, on the GPU
/// (`sum_shape_blocks.wgsl`'s `start`, and per part of the lower blocks its
/// pairs): made once per pattern and rings, on a thread beside the solver's
/// caller where it can ([`PairBuffers::upload`]). Each pair is packed in 4
/// bytes with its ring and its positions in the ring's row, weighed on the
/// GPU from the rows' weights ([`RingSlots::by_block_packed`]), where the
/// rows are short enough; else it goes as its ring and weight, 12 bytes
/// ([`RingSlots::by_block`]). Homer 1.2M's 16.8M pairs: 67 MB packed
/// (and 34 MB of rows' weights) against 202 MB.
pub(crate) struct PairBuffers {
    start: wgpu::Buffer,
    /// Per part: its pairs (packed, or their rings), their weights (none
    /// where packed), and its first pair.
    parts: Vec<(wgpu::Buffer, Option<wgpu::Buffer>, u32)>,
    /// Where the pairs are packed: the bits of a position, and the rows'
    /// weights' starts and the weights ([`matrix::ring_weights`]).
    rows: Option<(u32, wgpu::Buffer, wgpu::Buffer)>,
    /// Lower blocks and pairs in all.
    blocks: usize,
    pairs: usize,
}

impl PairBuffers {
    /// The pairs of `rings` (their slots `slots` in a pattern of `blocks`
    /// lower blocks) gathered by lower block and sent up, cut as lower parts
    /// of `part_blocks` blocks, `parts` of them; packed where
    /// [`matrix::pack_bits`] allows.
    pub fn upload(
        ctx: &Context,
        (rings, blocks, slots): (&SparseRows, usize, &RingSlots),
        (part_blocks, parts): (usize, usize),
    ) -> Result<PairBuffers, GpuError> {
        Self::upload_packed(ctx, (rings, blocks, slots), (part_blocks, parts), true)
    }

    /// [`Self::upload`], packed only where `pack` (tests send both forms).
    pub(crate) fn upload_packed(
        ctx: &Context,
        (rings, blocks, slots): (&SparseRows, usize, &RingSlots),
        (part_blocks, parts): (usize, usize),
        pack: bool,
    ) -> Result<PairBuffers, GpuError> {
        let (start, pair, f, rows) = match matrix::pack_bits(rings).filter(|_| pack) {
            Some(bits) => {
                let (start, packed) = slots.by_block_packed(rings, blocks, bits);
                let (row_start, weights) = matrix::ring_weights(rings);
                let rows = (
                    bits,
                    ctx.storage_init("shape sum: rows' weights' starts", &row_start)?,
                    ctx.storage_init("shape sum: rows' weights (f64)", &weights)?,
                );
                (start, packed, Vec::new(), Some(rows))
            }
            None => {
                let (start, ring, f) = slots.by_block(rings, blocks);
                (start, ring, f, None)
            }
        };
        let start_buf = ctx.storage_init("shape sum: ring pairs per lower block", &start)?;
        let parts = (0..parts)
            .map(|part| {
                let b = LowerParts::range_of(part, part_blocks, blocks);
                let pairs = start[b.start] as usize..start[b.end] as usize;
                // A part without pairs binds one placeholder entry.
                let part_of = |what: &str, all: &[u8], size: usize| {
                    let bytes = match pairs.is_empty() {
                        true => &[0u8; 8][..size],
                        false => &all[pairs.start * size..pairs.end * size],
                    };
                    ctx.storage_init(&format!("shape sum: {what} (part {part})"), bytes)
                };
                let what = match rows {
                    Some(_) => "ring pairs, packed",
                    None => "ring of each pair",
                };
                let ring_buf = part_of(what, bytemuck::cast_slice(&pair), 4)?;
                let f_buf = match rows {
                    Some(_) => None,
                    None => Some(part_of(
                        "weight of each pair (f64)",
                        bytemuck::cast_slice(&f),
                        8,
                    )?),
                };
                Ok((ring_buf, f_buf, pairs.start as u32))
            })
            .collect::<Result<Vec<_>, GpuError>>()?;
        Ok(PairBuffers {
            start: start_buf,
            parts,
            rows,
            blocks,
            pairs: pair.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::{
        dispatch, matrix, ExpandBlocks, LowerParts, PairBuffers, RingSlots, ShapeSum, IDENTITY,
        PART_SHIFT, TRANSPOSE, ZERO,
    };
    use crate::matrix::{high_part, low_part, HostMatrix};
    use crate::MixedPrecision;
    use solver_cpu::{BlockSym3, SpdSolver};
    use std::sync::Arc;

    /// A block matrix on a ring of `n` vertices (neighbours 1 and 2 apart),
    /// SPD diagonal blocks, values depending on `seed`.
    fn ring(n: usize, seed: f64) -> BlockSym3 {
        let pairs = (0..n).flat_map(|i| [(i, (i + 1) % n), (i, (i + 2) % n)]);
        let mut a = BlockSym3::from_pattern(n, pairs);
        for j in 0..n {
            for k in a.col_ptr[j]..a.col_ptr[j + 1] {
                let i = a.row_idx[k];
                let b = &mut a.blocks[k];
                for (q, v) in b.iter_mut().enumerate() {
                    // Values with bits below f32's, so the low parts matter.
                    *v = 0.01 * ((seed + (7 * k + q) as f64) * 0.731).sin() / 3.0;
                }
                if i == j {
                    for q in [0, 4, 8] {
                        b[q] += 4.0 + seed;
                    }
                    // Symmetric diagonal blocks.
                    for (r, c) in [(0, 1), (0, 2), (1, 2)] {
                        b[3 * c + r] = b[3 * r + c];
                    }
                }
            }
        }
        a
    }

    /// A solver on the adapter, always in mixed precision; `None` (the test
    /// passes) without an adapter or without `SHADER_F64`.
    fn mixed_solver() -> Option<crate::GpuSolver> {
        let mut s = crate::test_solver()?;
        s.set_mixed_precision(MixedPrecision::Always);
        s.ctx.shader_f64.then_some(s)
    }

    /// The same with storage bindings of `limit` bytes: the lower blocks of
    /// the tests' matrices then take several parts.
    fn mixed_solver_with_limit(limit: u64) -> Option<crate::GpuSolver> {
        crate::test_solver()?;
        let mut s = crate::open_with(crate::OpenOptions {
            adjust_limits: Some(Box::new(move |l| l.max_storage_buffer_binding_size = limit)),
            ..Default::default()
        })
        .unwrap();
        s.set_mixed_precision(MixedPrecision::Always);
        s.ctx.shader_f64.then_some(s)
    }

    /// Lower blocks over one binding take several parts, each of the most
    /// blocks a binding holds but the last; the device map names each
    /// block's part and offset.
    #[test]
    fn lower_parts_cut_at_the_binding() {
        assert_eq!(LowerParts::layout(600, 72 * 600), Some((1, 600)));
        assert_eq!(LowerParts::layout(600, 72 * 600 - 1), Some((2, 300)));
        assert_eq!(LowerParts::layout(600, 15_000), Some((3, 200)));
        assert_eq!(LowerParts::layout(600, 72 * 150), Some((4, 150)));
        assert_eq!(LowerParts::layout(600, 72 * 149), None);
        assert_eq!(LowerParts::layout(600, 71), None);
        let Some(s) = crate::test_solver() else {
            return;
        };
        let parts = LowerParts::new(&s.ctx, 600, 15_000).unwrap();
        assert_eq!(parts.buffers.len(), 3);
        assert_eq!(parts.range(2), 400..600);
        let map = [0, 199, 200 | TRANSPOSE, 599, ZERO, IDENTITY];
        let want = [
            0,
            199,
            TRANSPOSE | (1 << PART_SHIFT),
            (2 << PART_SHIFT) | 199,
            ZERO,
            IDENTITY,
        ];
        assert_eq!(parts.device_map(&map), want);
    }

    #[test]
    fn expanded_values_are_the_hosts_high_and_low_parts() {
        let Some(mut s) = mixed_solver() else {
            return;
        };
        let n = 40;
        let mut fixed = vec![false; n];
        fixed[7] = true;
        let a = ring(n, 0.0);
        s.prepare_blocks(&a, &fixed).unwrap();
        // A solve builds the mixed-precision matrix (its low parts).
        let mut x = vec![1.0; 3 * n];
        s.solve_in_place(&mut x, 1).unwrap();
        assert!(s.last_solve_mixed());
        // New values of the pattern: expanded on the GPU (the first time
        // also uploads the block map), then again.
        s.prepare_blocks(&ring(n, 0.25), &fixed).unwrap();
        assert!(
            s.expansion.is_some(),
            "the values went through the expansion"
        );
        let b = ring(n, 0.5);
        let up0 = s.ctx.traffic().to_device;
        s.prepare_blocks(&b, &fixed).unwrap();
        let up = s.ctx.traffic().to_device - up0;
        // The lower f64 values and the inverse diagonals, nothing per block of
        // both triangles: 72 bytes a lower block, 36 + 24 a block row.
        assert_eq!(up, (72 * b.blocks.len() + 60 * n) as u64);
        let mut want = HostMatrix::pattern(n, 3, &b.col_ptr, &b.row_idx).unwrap();
        want.fill_blocks(&b, &fixed);
        check_parts(&s, &want);
        // The held vertex's row is the identity, its column zero elsewhere.
        let want_vals = want.full_values();
        let r = want.row_ptr[7] as usize..want.row_ptr[8] as usize;
        assert!(r.clone().all(|k| {
            let blk = &want_vals[9 * k..9 * k + 9];
            match want.col_idx[k] {
                7 => blk == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                _ => blk.iter().all(|&v| v == 0.0),
            }
        }));
        // And the solve with the expanded matrix is the host's.
        check_solve(&mut s, &want);
    }

    /// A ring's graph Laplacian (neighbours 1 and 2 apart) with weights of
    /// full f64 mantissas, times I3, plus a small diagonal `eps_i`: SPD, and
    /// for a smooth right-hand side the solution is large (about 1 / eps)
    /// against `b`, so 48-bit values (relative error 2^-48 an entry) leave a
    /// residual far above f64's.
    fn screened_ring(n: usize, seed: f64) -> BlockSym3 {
        let pairs = (0..n).flat_map(|i| [(i, (i + 1) % n), (i, (i + 2) % n)]);
        let mut a = BlockSym3::from_pattern(n, pairs);
        let mut diag = vec![0.0; n];
        for j in 0..n {
            for k in a.col_ptr[j]..a.col_ptr[j + 1] {
                let i = a.row_idx[k];
                if i != j {
                    let w = 1.0 + 0.3 * ((seed + k as f64) * 0.7).sin();
                    diag[i] += w;
                    diag[j] += w;
                    for q in [0, 4, 8] {
                        a.blocks[k][q] = -w;
                    }
                }
            }
        }
        for (j, d) in diag.iter().enumerate() {
            for k in a.col_ptr[j]..a.col_ptr[j + 1] {
                if a.row_idx[k] == j {
                    let eps = 1e-3 * (1.0 + 0.5 * ((seed + j as f64) * 1.3).sin());
                    for q in [0, 4, 8] {
                        a.blocks[k][q] = d + eps;
                    }
                }
            }
        }
        a
    }

    /// The mixed-precision rounds of a block matrix whose f64 lower blocks
    /// are on the GPU form their residuals there with those exact values
    /// (`refine_product.wgsl`), not the product's 48-bit parts: on a matrix
    /// where 48 bits leave a residual far above f64's the result is as
    /// accurate as asked against the host's matrix, and the host formed no
    /// residual. The pattern's first matrix, written by the host, is refined
    /// on the host.
    #[test]
    fn block_residuals_are_formed_on_the_gpu_with_the_exact_values() {
        let Some(s) = mixed_solver() else {
            return;
        };
        block_residuals_case(s, 300, 1);
        // Lower blocks in three parts (20,833 blocks of 72 bytes a binding).
        let s = mixed_solver_with_limit(1_500_000).unwrap();
        block_residuals_case(s, 15_000, 3);
    }

    fn block_residuals_case(mut s: crate::GpuSolver, n: usize, parts: usize) {
        let fixed = vec![false; n];
        s.prepare_blocks(&screened_ring(n, 0.0), &fixed).unwrap();
        let tol = 5e-12;
        s.set_tolerance(tol);
        let b: Vec<f64> = (0..2 * 3 * n)
            .map(|i| 1.0 + 0.1 * (0.01 * i as f64).sin())
            .collect();
        let mut x = vec![0.0; b.len()];
        let host = s.host_residuals;
        s.solve_with_guess(&b, &mut x, 2).unwrap();
        assert!(s.host_residuals > host, "the host wrote the first matrix");
        for seed in [0.25, 0.5] {
            let a = screened_ring(n, seed);
            s.prepare_blocks(&a, &fixed).unwrap();
            let host = s.host_residuals;
            x.fill(0.0);
            s.solve_with_guess(&b, &mut x, 2).unwrap();
            assert_eq!(s.host_residuals, host, "residuals on the GPU");
            assert!(s.last_solve_mixed());
            let mut want = HostMatrix::pattern(n, 3, &a.col_ptr, &a.row_idx).unwrap();
            want.fill_blocks(&a, &fixed);
            check_gpu_floor(&s, 2, &want, &format!("seed {seed}"));
            let e = &s.expansion.as_ref().unwrap().0;
            assert_eq!(e.lower.buffers.len(), parts);
            // The round's last product A x (left in the PCG's `Ap`) is the
            // exact matrix's: within f64 rounding of the host's, where the
            // 48-bit parts are off by up to 2^-48 an entry.
            let ap = &s.mixed.as_ref().unwrap().ws.ap;
            let gpu_ax: Vec<f64> = s.ctx.read(ap, x.len(), &mut None, None).unwrap();
            let mut abs = a.clone();
            abs.blocks.iter_mut().flatten().for_each(|v| *v = v.abs());
            let mut worst = 0.0f64;
            for c in 0..2 {
                let col = c * 3 * n..(c + 1) * 3 * n;
                let (mut ax, mut bound) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
                a.mul_vec(&x[col.clone()], &mut ax);
                let xa: Vec<f64> = x[col.clone()].iter().map(|v| v.abs()).collect();
                abs.mul_vec(&xa, &mut bound);
                for i in 0..3 * n {
                    worst = worst.max((gpu_ax[col.start + i] - ax[i]).abs() / bound[i]);
                }
            }
            eprintln!("seed {seed}: product error {worst:e} of |A| |x|");
            assert!(worst < 4e-16, "seed {seed}: {worst:e} of |A| |x|");
            for c in 0..2 {
                let col = c * 3 * n..(c + 1) * 3 * n;
                let mut ax = vec![0.0; 3 * n];
                a.mul_vec(&x[col.clone()], &mut ax);
                let rr: f64 = b[col.clone()]
                    .iter()
                    .zip(&ax)
                    .map(|(u, v)| (u - v) * (u - v))
                    .sum();
                let bb: f64 = b[col.clone()].iter().map(|v| v * v).sum();
                let xx: f64 = x[col].iter().map(|v| v * v).sum();
                assert!(xx.sqrt() > 300.0 * bb.sqrt(), "a large solution");
                let rel = (rr / bb).sqrt();
                eprintln!("seed {seed}, column {c}: {rel:e}");
                assert!(rel <= tol, "seed {seed}, column {c}: {rel:e}");
            }
        }
    }

    /// A warm start above the tolerance is solved, not taken as it is, where
    /// the rounding floor `eps ||A|| ||x|| / ||b||` is above the start's
    /// residual (one stiff vertex, as in homer 1.2M's fine-tune matrix, whose
    /// row sums reach 1.6e14): the floor ends the rounds only once a column
    /// has run one. Both ways of forming the residuals: on the host (the
    /// pattern's first matrix) and on the GPU (a later one).
    #[test]
    fn a_warm_start_under_the_rounding_floor_is_still_solved() {
        let Some(mut s) = mixed_solver() else {
            return;
        };
        let n = 300;
        let fixed = vec![false; n];
        let mut a = screened_ring(n, 0.0);
        for k in a.col_ptr[5]..a.col_ptr[6] {
            if a.row_idx[k] == 5 {
                for q in [0, 4, 8] {
                    a.blocks[k][q] *= 1e6;
                }
            }
        }
        let b: Vec<f64> = (0..3 * n)
            .map(|i| 1.0 + 0.1 * (0.01 * i as f64).sin())
            .collect();
        let mut exact = b.clone();
        let mut direct = solver_cpu::CholeskySolver::new();
        direct.prepare_blocks(&a, &fixed).unwrap();
        direct.solve_in_place(&mut exact, 1).unwrap();
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let err = |x: &[f64]| {
            let d: Vec<f64> = x.iter().zip(&exact).map(|(u, v)| u - v).collect();
            norm(&d) / norm(&exact)
        };
        let start: Vec<f64> = exact
            .iter()
            .enumerate()
            .map(|(i, v)| v * (1.0 + 1e-8 * (0.005 * i as f64).sin()))
            .collect();
        let tol = 1e-12;
        s.set_tolerance(tol);
        for round in 0..2 {
            // The second time the same values go up again: the GPU forms
            // the residuals.
            s.prepare_blocks(&a, &fixed).unwrap();
            let h = s.host.as_ref().unwrap();
            let mut r = vec![0.0; 3 * n];
            h.residual(&b, &start, &mut r, 1);
            let rel = norm(&r) / norm(&b);
            let floor = f64::EPSILON * h.norm_inf() * norm(&start) / norm(&b);
            assert!(tol < rel && rel < floor, "{tol:e} < {rel:e} < {floor:e}");
            let mut x = start.clone();
            let info = s.solve_with_guess(&b, &mut x, 1).unwrap();
            assert!(s.last_solve_mixed());
            assert!(info.iterations > 0, "round {round}: taken as it was");
            assert!(
                err(&x) < 1e-2 * err(&start),
                "round {round}: {:e} from {:e}",
                err(&x),
                err(&start)
            );
        }
    }

    /// The GPU's block values (high and low parts) are `want`'s.
    fn check_parts(s: &crate::GpuSolver, want: &HostMatrix) {
        let want_vals = want.full_values();
        let gpu = s.gpu.as_ref().unwrap();
        let (chunks, _) = gpu.block_parts().unwrap();
        let mixed = s.mixed.as_ref().unwrap();
        let (_, lo) = mixed.matrix.block_parts().unwrap();
        let lo = lo.unwrap();
        let mut staging = None;
        let mut checked = 0;
        for (c, lo_buf) in chunks.iter().zip(lo) {
            let count = 9 * c.blocks.len();
            let hi: Vec<f32> = s.ctx.read(&c.vals, count, &mut staging, None).unwrap();
            let lo: Vec<f32> = s.ctx.read(lo_buf, count, &mut staging, None).unwrap();
            let v = &want_vals[9 * c.blocks.start..9 * c.blocks.end];
            for ((&v, &h), &l) in v.iter().zip(&hi).zip(&lo) {
                // f32 conversions may round either way in WGSL: one ulp.
                let ulp = |x: f32| (x.abs() * f32::EPSILON).max(f32::MIN_POSITIVE) as f64;
                assert!(
                    (h as f64 - high_part(v) as f64).abs() <= ulp(h),
                    "{h} vs {v}"
                );
                let sum = h as f64 + l as f64;
                assert!(
                    (sum - v).abs() <= 2f64.powi(-46) * v.abs(),
                    "{h} + {l} vs {v}"
                );
                if v != 0.0 && h as f64 == high_part(v) as f64 {
                    assert!((l - low_part(v)).abs() <= l.abs() * f32::EPSILON);
                }
                checked += 1;
            }
        }
        assert_eq!(checked, want_vals.len());
    }

    /// A solve with the prepared matrix has `want`'s residual below 1e-9.
    /// The rounding floor `eps ||A||_inf` that the last solve of `ncols`
    /// columns refined on the GPU ran with (read back with its sums).
    fn gpu_floor(s: &crate::GpuSolver, ncols: usize) -> f64 {
        let m = s.mixed.as_ref().unwrap();
        let v: Vec<f64> = s
            .ctx
            .read(&m.refine.norms, 3 * ncols + 1, &mut None, None)
            .unwrap();
        v[3 * ncols]
    }

    /// A block matrix refined on the GPU has its rounding floor found there,
    /// from its exact values: `eps` times the host's `||A||_inf` of the same
    /// blocks to the bit (`want`: the host's matrix), the host walking none
    /// of its own values for it (`bound`: the host's own bound where it
    /// keeps a shape form, which the exact norm may not exceed).
    fn check_gpu_floor(s: &crate::GpuSolver, ncols: usize, want: &HostMatrix, what: &str) {
        let floor = gpu_floor(s, ncols);
        let h = s.host.as_ref().unwrap();
        assert!(!h.norm_found(), "{what}: the host found ||A||_inf");
        let exact = f64::EPSILON * want.norm_inf();
        assert!(exact > 0.0);
        assert_eq!(
            floor.to_bits(),
            exact.to_bits(),
            "{what}: {floor:e} against {exact:e}"
        );
        if h.shape_form().is_some() {
            let bound = f64::EPSILON * h.norm_inf();
            assert!(
                floor <= bound,
                "{what}: {floor:e} above the bound {bound:e}"
            );
        }
    }

    fn check_solve(s: &mut crate::GpuSolver, want: &HostMatrix) {
        let n = want.rows;
        let mut y = vec![1.0; 3 * n];
        s.solve_in_place(&mut y, 1).unwrap();
        let mut r = vec![0.0; 3 * n];
        want.residual(&vec![1.0; 3 * n], &y, &mut r, 1);
        let rel = r.iter().map(|v| v * v).sum::<f64>().sqrt() / (3.0 * n as f64).sqrt();
        assert!(rel < 1e-9, "relative residual {rel:e}");
    }

    /// A shape matrix is summed on the GPU, the first of its pattern too:
    /// then the host sends `K`'s values and the `C_i` (8 bytes a lower entry,
    /// 48 a ring), keeps the matrix in its own
    /// form, and the blocks the GPU holds are the host's sum (high and low
    /// parts); the solve's residual is the host-summed matrix's. Once the
    /// kind's factor is made, the solver adds a Laplacian square term the
    /// matrices name: its values go up once, and the blocks and solves are
    /// still the host's sum's. Taken back, the matrix is gone from the
    /// solver until the next one. The ring pairs go up on a thread beside
    /// the caller (`PairBuffers`), or with the sum where that is off: the
    /// same blocks either way.
    #[test]
    fn shape_blocks_summed_on_the_gpu_are_the_hosts() {
        for ahead in [true, false] {
            let Some(mut s) = mixed_solver() else {
                return;
            };
            s.beside_uploads = ahead;
            shape_sum_case(s, 40, 1);
            // Lower blocks in three parts (the sum one dispatch each, with
            // its own pairs), read back through them by the expansion.
            let mut s = mixed_solver_with_limit(15_000).unwrap();
            s.beside_uploads = ahead;
            shape_sum_case(s, 200, 3);
        }
    }

    /// The shape sum's lower blocks are the same bits with the ring pairs
    /// packed (weighed on the GPU from the rows' weights) as with each
    /// pair's weight sent up, in one part and in three; and they are the
    /// host's sum of the pairs by block to rounding.
    #[test]
    fn packed_ring_pairs_sum_the_same_blocks_as_weighed_ones() {
        if mixed_solver().is_none() {
            return;
        }
        for (n, limit) in [(40, None), (200, Some(15_000))] {
            let s = match limit {
                Some(l) => mixed_solver_with_limit(l).unwrap(),
                None => mixed_solver().unwrap(),
            };
            let ctx = &s.ctx;
            let a = crate::matrix::shape_strip(n, 0.3);
            let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
            let slots = RingSlots::new(&a.rings, col_ptr, row_idx, None).unwrap();
            let nnz = row_idx.len();
            let k = ExpandBlocks::new(ctx).unwrap();
            let lower = LowerParts::new(ctx, nnz, matrix::binding_limit(ctx)).unwrap();
            assert_eq!(lower.buffers.len(), if limit.is_some() { 3 } else { 1 });
            let mut sums = Vec::new();
            for pack in [true, false] {
                let layout = (lower.part_blocks, lower.buffers.len());
                let up0 = ctx.traffic().to_device;
                let pairs =
                    PairBuffers::upload_packed(ctx, (&a.rings, nnz, &slots), layout, pack).unwrap();
                let up = ctx.traffic().to_device - up0;
                assert_eq!(pairs.rows.is_some(), pack);
                // Packed: 4 bytes a pair and the rows' weights and starts
                // (a ring's weights: its diagonal and 2 neighbours); else 12.
                let pair_bytes = (4 * (n + 1) + 8 * 3 * n + 4 * pairs.pairs) as u64;
                let want_up = 4 * (nnz as u64 + 1)
                    + match pack {
                        true => pair_bytes,
                        false => 12 * pairs.pairs as u64,
                    };
                assert_eq!(up, want_up, "pack {pack}");
                let sum = ShapeSum::new(&k, ctx, (&a, &slots), &lower, Some(pairs)).unwrap();
                ctx.write_buffer(&sum.iso, 0, bytemuck::cast_slice(&a.iso.values));
                ctx.write_buffer(&sum.ring_c, 0, bytemuck::cast_slice(&a.ring_c));
                let pipeline = k.sum_kernel.pipeline(ctx, 1).unwrap();
                let mut enc = ctx.encoder("sum");
                {
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    for (bind, dims) in &sum.parts {
                        dispatch(&mut pass, &pipeline, bind, *dims);
                    }
                }
                ctx.submit(Some(enc));
                let mut staging = None;
                let got: Vec<f64> = (0..lower.buffers.len())
                    .flat_map(|part| {
                        let count = 9 * lower.range(part).len();
                        ctx.read::<f64>(lower.part(part), count, &mut staging, None)
                            .unwrap()
                    })
                    .collect();
                sums.push(got);
            }
            assert_eq!(sums[0], sums[1], "n {n}: packed and weighed differ");
            // The host's sum of each block's pairs, in their order.
            let (start, ring, f) = slots.by_block(&a.rings, nnz);
            for b in 0..nnz {
                let kv = a.iso.values[b];
                let mut m = [kv, 0.0, 0.0, 0.0, kv, 0.0, 0.0, 0.0, kv];
                for t in start[b] as usize..start[b + 1] as usize {
                    let c = a.ring_c[ring[t] as usize];
                    let full = [c[0], c[3], c[4], c[3], c[1], c[5], c[4], c[5], c[2]];
                    for q in 0..9 {
                        m[q] += f[t] * full[q];
                    }
                }
                for q in 0..9 {
                    let g = sums[0][9 * b + q];
                    assert!(
                        (g - m[q]).abs() <= 1e-15 * (1.0 + m[q].abs()),
                        "{g} vs {}",
                        m[q]
                    );
                }
            }
        }
    }

    /// A shape pattern's expansion is set up once in a run: the first
    /// matrix's mixed-precision matrix is made before it (its low parts
    /// expanded with the high ones), a new kind's factor makes new steps
    /// only and a solve of more columns new vectors only, over the same
    /// matrix. Every solve's residual is still the host-summed matrix's.
    #[test]
    fn a_shape_patterns_expansion_is_set_up_once() {
        let Some(mut s) = mixed_solver() else {
            return;
        };
        let (fixed, rings) = held_and_rings(60);
        shape_steps(&mut s, &fixed, &rings);
        assert_eq!(s.setups, 2, "one factor per kind");
        assert_eq!(s.mixed_builds, 1, "one mixed-precision matrix");
        assert_eq!(s.expansions, 1, "one expansion");
        assert_eq!(s.patterns_taken_ahead, 0);
    }

    /// A shape pattern set up ahead of its first matrix, on a thread
    /// beside the caller (`start_pattern_ahead`: the blocks' pattern and
    /// map, the mixed-precision matrix's low parts, the expansion and the
    /// shape sum), is taken up by that matrix: still one expansion and one
    /// mixed-precision matrix in the run, the caller's first matrix sends
    /// less than without it (at least the block map and column indices
    /// fewer), and every solve's residual is the host-summed matrix's. A
    /// pattern set up for other held vertices or other rings is not taken
    /// up: the matrix sets up its own, with the same solves.
    #[test]
    fn a_shape_pattern_set_up_ahead_is_taken_up_by_its_first_matrix() {
        let n = 60;
        let (fixed, rings) = held_and_rings(n);
        let mut other_held = fixed.clone();
        other_held[8] = true;
        let other_rings = crate::matrix::shape_strip(n, 0.0).rings;
        let cases = [
            ("ahead", Some((&fixed, &rings))),
            ("other held vertices", Some((&other_held, &rings))),
            ("other rings", Some((&fixed, &other_rings))),
            ("none", None),
        ];
        let mut first = Vec::new();
        for (case, ahead) in cases {
            let Some(mut s) = mixed_solver() else {
                return;
            };
            s.beside_uploads = true;
            if let Some((held, rings)) = ahead {
                let mut a = crate::matrix::shape_strip(n, 0.0);
                a.rings = rings.clone();
                s.prepare_shape_pattern(&a, held);
            }
            let caller = shape_steps(&mut s, &fixed, &rings);
            let taken = usize::from(case == "ahead");
            assert_eq!(s.patterns_taken_ahead, taken, "{case}");
            assert_eq!(s.setups, 2, "{case}: one factor per kind");
            assert_eq!(s.mixed_builds, 1, "{case}: one mixed-precision matrix");
            assert_eq!(s.expansions, 1, "{case}: one expansion");
            first.push(caller[0]);
        }
        // Each full block's map entry and column index: 8 bytes.
        let full = 2 * crate::matrix::shape_strip(n, 0.0).iso.row_idx.len() - n;
        assert!(
            first[0] + 8 * full as u64 <= first[3],
            "the first matrix's bytes from the caller: {first:?}"
        );
    }

    /// Held vertex 7 of `n`, and the rings of the tests' strip.
    fn held_and_rings(n: usize) -> (Vec<bool>, Arc<solver_cpu::SparseRows>) {
        let mut fixed = vec![false; n];
        fixed[7] = true;
        (fixed, crate::matrix::shape_strip(n, 0.0).rings)
    }

    /// Two scale-driven matrices of the strip with `rings` solved, then two
    /// of the fine-tune of 4 and 3 columns, each solve's residual the
    /// host-summed matrix's; the bytes each matrix's preparation sent from
    /// the caller's thread.
    fn shape_steps(
        s: &mut crate::GpuSolver,
        fixed: &[bool],
        rings: &Arc<solver_cpu::SparseRows>,
    ) -> Vec<u64> {
        use solver_cpu::SystemKind::{FineTune, ScaleDriven};
        let n = fixed.len();
        let steps = [
            (ScaleDriven, 0.0, 1),
            (ScaleDriven, 0.25, 1),
            (FineTune, 0.5, 4),
            (FineTune, 0.75, 3),
        ];
        let caller = |s: &crate::GpuSolver| {
            let t = s.ctx.traffic();
            t.to_device - t.beside_to_device
        };
        let mut sent = Vec::new();
        for (kind, seed, ncols) in steps {
            s.set_system_kind(kind);
            let mut a = crate::matrix::shape_strip(n, seed);
            a.rings = rings.clone();
            let mut want = HostMatrix::pattern(n, 3, &a.iso.col_ptr, &a.iso.row_idx).unwrap();
            let slots =
                crate::matrix::RingSlots::new(&a.rings, &a.iso.col_ptr, &a.iso.row_idx, None)
                    .unwrap();
            want.fill_shape(&a, &slots, fixed).unwrap();
            let before = caller(s);
            assert!(s.prepare_shape_owned(a, fixed).unwrap().is_none());
            sent.push(caller(s) - before);
            let b: Vec<f64> = (0..3 * n * ncols)
                .map(|i| 1.0 + (i / (3 * n)) as f64 + 0.01 * (i % 7) as f64)
                .collect();
            let mut y = b.clone();
            s.solve_in_place(&mut y, ncols).unwrap();
            assert!(s.last_solve_mixed(), "{kind:?}, seed {seed}");
            // What the GPU holds the host does not keep: the expansion's
            // block map and, each kind factored, the inverse diagonal's
            // scratch and the diagonal blocks (which only the inverse
            // diagonal of the pattern's first matrix read).
            let h = s.host.as_ref().unwrap();
            assert!(!h.map_held(), "{kind:?}, seed {seed}");
            assert!(!h.diagonal_held(), "{kind:?}, seed {seed}");
            assert_eq!(s.minv_scratch.capacity(), 0, "{kind:?}, seed {seed}");
            let mut r = vec![0.0; 3 * n * ncols];
            want.residual(&b, &y, &mut r, ncols);
            for c in 0..ncols {
                let col = |v: &[f64]| {
                    v[c * 3 * n..(c + 1) * 3 * n]
                        .iter()
                        .map(|v| v * v)
                        .sum::<f64>()
                };
                let rel = (col(&r) / col(&b)).sqrt();
                assert!(rel < 1e-9, "{kind:?}, seed {seed}, column {c}: {rel:e}");
            }
        }
        sent
    }

    /// Uploads go up beside the caller by default from
    /// `BESIDE_UPLOADS_FROM_THREADS` of rayon's threads on, not below (where
    /// the extra threads slowed the main thread's own work on two cores).
    #[test]
    fn uploads_go_up_beside_the_caller_on_hosts_with_threads_to_spare() {
        let from = crate::solver::BESIDE_UPLOADS_FROM_THREADS;
        for (threads, ahead) in [(from - 1, false), (from, true)] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let Some(s) = pool.install(mixed_solver) else {
                return;
            };
            assert_eq!(s.beside_uploads, ahead, "{threads} threads");
        }
    }

    fn shape_sum_case(mut s: crate::GpuSolver, n: usize, parts: usize) {
        let ahead = s.beside_uploads;
        let mut fixed = vec![false; n];
        fixed[7] = true;
        let rings = crate::matrix::shape_strip(n, 0.0).rings;
        let mut square = None;
        let mut last = None;
        for seed in [0.0, 0.25, 0.5, 0.75] {
            // The rings of a run are one (the input's Laplacian).
            let mut a = crate::matrix::shape_strip(n, seed);
            a.rings = rings.clone();
            // The solver says when it adds the term: once the kind's
            // factor is made and it sums the blocks.
            assert_eq!(s.adds_laplacian_square(), seed > 0.0, "seed {seed}");
            if seed >= 0.5 {
                let m = square.get_or_insert_with(|| crate::matrix::square_model(&a));
                a.laplacian_square = Some(Arc::clone(m));
            }
            let nnz = a.iso.row_idx.len();
            let up0 = s.ctx.traffic().to_device;
            let mut want = HostMatrix::pattern(n, 3, &a.iso.col_ptr, &a.iso.row_idx).unwrap();
            let slots =
                crate::matrix::RingSlots::new(&a.rings, &a.iso.col_ptr, &a.iso.row_idx, None)
                    .unwrap();
            want.fill_shape(&a, &slots, &fixed).unwrap();
            // K is read apart (factored) for the kind's first matrix only.
            assert_eq!(s.wants_isotropic_part(), seed == 0.0, "seed {seed}");
            let pairs = slots.by_block(&a.rings, nnz).2.len();
            let beside0 = s.ctx.traffic().beside_to_device;
            let kept = s.prepare_shape_owned(a, &fixed).unwrap();
            let beside = s.ctx.traffic().beside_to_device - beside0;
            // The pairs' starts and, per part, the pairs packed, with the
            // rows' starts and weights (each ring's diagonal and 2
            // neighbours), from the thread beside the caller.
            let pairs_up = match ahead && seed == 0.0 {
                true => 4 * (nnz + 1) + 4 * pairs + 4 * (n + 1) + 8 * 3 * n,
                false => 0,
            };
            assert_eq!(beside as usize, pairs_up, "seed {seed}");
            assert_eq!(s.pairs_taken_ahead, usize::from(ahead), "seed {seed}");
            assert!(!s.wants_isotropic_part(), "the kind's factor is made");
            assert!(kept.is_none(), "kept in its form by the solver");
            let up = s.ctx.traffic().to_device - up0;
            // After the first (the pattern, the pairs, their starts and
            // weights), the values go up as K's values and the C_i, nothing
            // else: not the inverse diagonals, which the kind's Cholesky
            // preconditioner does not read, and not the mixed-precision
            // matrix's expansion (made at its build); the term's values (and
            // the sum's parameters) once.
            let each = 8 * nnz + 48 * n;
            let square_once = if seed == 0.5 { 8 * nnz + 32 * parts } else { 0 };
            if seed > 0.0 {
                assert_eq!(up, (each + square_once) as u64, "seed {seed}");
            }
            assert_eq!(s.shape_sum.as_ref().unwrap().1.parts.len(), parts);
            // (The first matrix's upload made the mixed-precision matrix.)
            check_solve(&mut s, &want);
            assert!(s.last_solve_mixed());
            check_gpu_floor(&s, 1, &want, &format!("seed {seed}"));
            check_parts(&s, &want);
            let h = s.host.as_ref().unwrap();
            assert!(!h.lower_summed_on_host(), "seed {seed}: summed on the host");
            last = Some(want);
        }
        // A new kind's first matrix is factored: its K must be whole again.
        s.set_system_kind(solver_cpu::SystemKind::FineTune);
        assert!(s.wants_isotropic_part());
        s.set_system_kind(solver_cpu::SystemKind::ScaleDriven);
        assert!(!s.wants_isotropic_part());
        // A new mixed-precision matrix (a new kind's factor makes one) has
        // its low parts summed and expanded on the GPU too.
        let want = last.unwrap();
        s.mixed = None;
        check_solve(&mut s, &want);
        check_parts(&s, &want);
        let h = s.host.as_ref().unwrap();
        assert!(!h.lower_summed_on_host(), "no blocks summed on the host");
        let a = s.take_shape_matrix().expect("the kept matrix");
        assert_eq!(a.iso.values, crate::matrix::shape_strip(n, 0.75).iso.values);
        assert!(a.laplacian_square.is_some());
        let mut x = vec![1.0; 3 * n];
        assert!(matches!(
            s.solve_in_place(&mut x, 1),
            Err(solver_cpu::SolverError::NotPrepared)
        ));
    }
}
