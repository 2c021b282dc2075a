//! The wgpu context: instance, adapter choice, device and queue, plus the helpers
//! every kernel module uses (pipelines, buffers with limit checks, 2-D dispatch
//! sizes, read-back, turning device errors into [`GpuError`]).

use crate::GpuError;
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

/// Uniform parameters shared by every shader (each declares the same struct).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct Params {
    /// Rows handled one per invocation (block rows for the 3x3 systems).
    pub rows: u32,
    /// Columns (right-hand sides) in this batch, at most [`crate::CMAX`].
    pub ncols: u32,
    /// Length of one column (`rows * bs`).
    pub n: u32,
    /// Workgroups that own rows: `ceil(rows / ROW_WG)`.
    pub groups: u32,
    /// Block size: 3 (vertex systems) or 1 (scalar).
    pub bs: u32,
    pub pad: [u32; 3],
}

/// Invocations per workgroup of the row kernels (SpMV, update, dot partials,
/// block-Jacobi); must match `WG` in the shaders.
pub(crate) const ROW_WG: u32 = 128;
/// Invocations of the single-workgroup finishing passes and of the element-wise
/// kernels; must match `FWG` in the shaders.
pub(crate) const FLAT_WG: u32 = 256;

/// Summary of one adapter, for `metricdeform adapters`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AdapterSummary {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub driver_info: String,
    /// Whether the adapter offers `SHADER_F64` (the solver's kernels do not
    /// need it; the f64 variants of the precision comparison do).
    pub shader_f64: bool,
    /// Whether the adapter offers `TIMESTAMP_QUERY`: the PCG's passes are
    /// then timed on the device (the report's `gpu_seconds`).
    pub timestamp_query: bool,
}

/// Adjusts the limits requested from the adapter.
pub type LimitsHook = Box<dyn Fn(&mut wgpu::Limits)>;

/// How to open the device (tests lower limits through `adjust_limits`).
#[derive(Default)]
pub struct OpenOptions {
    /// Case-insensitive substring of the adapter name; `None` = the
    /// `WGPU_ADAPTER_NAME` environment variable, else wgpu's high-performance default.
    pub adapter_name: Option<String>,
    /// Called with the adapter's limits before the device is requested.
    pub adjust_limits: Option<LimitsHook>,
}

pub(crate) struct Context {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// `SHADER_F64` was requested (the adapter has it): the f64 kernel
    /// variants of [`crate::precision`] compile.
    pub shader_f64: bool,
    /// First uncaptured device error since the last check.
    errors: Arc<Mutex<Option<GpuError>>>,
    /// Set by the device-lost callback.
    lost: Arc<Mutex<Option<String>>>,
    /// Host-device traffic and waits since the device was opened.
    traffic: Traffic,
    /// Timestamps around the PCG's passes, where the adapter has them.
    timer: Option<PassTimer>,
    /// Byte vectors of earlier read-backs handed back ([`Context::recycle`])
    /// for later ones to fill again: a solve's `x` is not read into fresh
    /// memory, page-faulted in, each time.
    read_pool: Mutex<Vec<Vec<u8>>>,
}

/// Read-back vectors kept for reuse at most ([`Context::recycle`]).
const READ_POOL: usize = 8;

/// Timestamp queries written at the start and end of a compute pass
/// (`TIMESTAMP_QUERY`), resolved into a buffer that the pass's read-back
/// brings home with the PCG's column states: seconds the device spent on
/// the pass, measured on the device, at no extra wait.
struct PassTimer {
    set: wgpu::QuerySet,
    /// Two u64 ticks (`QUERY_RESOLVE | COPY_SRC`).
    resolved: wgpu::Buffer,
    /// Nanoseconds per tick (`Queue::get_timestamp_period`).
    period_ns: f64,
}

impl PassTimer {
    /// Two timestamp queries and their resolve buffer on `device`.
    fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> PassTimer {
        PassTimer {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("pass timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: 2,
            }),
            resolved: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pass timestamps resolved"),
                size: 16,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            period_ns: queue.get_timestamp_period() as f64,
        }
    }
}

/// Running counts of what crosses between host and device: every write and
/// read-back goes through [`Context::write_buffer`] and [`Context::read`], every wait through [`Context::wait`].
#[derive(Default)]
struct Traffic {
    to_device: AtomicU64,
    from_device: AtomicU64,
    waits: AtomicU64,
    wait_nanos: AtomicU64,
    submits: AtomicU64,
    submit_nanos: AtomicU64,
    dispatches: AtomicU64,
    bytes_accessed: AtomicU64,
    bytes_minimal: AtomicU64,
    serial_steps: AtomicU64,
    timed_passes: AtomicU64,
    timed_nanos: AtomicU64,
    compiles: AtomicU64,
    compile_nanos: AtomicU64,
    compiles_ahead: AtomicU64,
    compile_ahead_nanos: AtomicU64,
    /// What threads working beside the caller
    /// ([`Context::beside_the_caller`]) submitted and waited for.
    beside_submits: AtomicU64,
    beside_waits: AtomicU64,
    beside_nanos: AtomicU64,
    beside_to_device: AtomicU64,
}

thread_local! {
    /// Whether this thread works for a solver beside the thread that calls
    /// it ([`Context::beside_the_caller`]).
    static BESIDE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Modelled device work of recorded kernels, what a discrete GPU pays for:
/// dispatches, and bytes moved between its memory and its cores. `bytes`
/// counts what each kernel reads and writes as stored (every stored matrix
/// entry once, every vector entry once: repeated gathers of a
/// vector are taken to hit the cache); `minimal` counts the operator
/// applications among them (products, smoothing steps, transfers, coarse
/// solves, scalings) with each matrix in its least storage at its precision
/// (one value per entry and one u32 column per stored block) and their
/// vectors once, and nothing for the PCG's vector updates and dot products.
/// `serial_steps` counts the latency that no width of GPU hides: the chain of
/// dependent steps through the dispatches, which run one after another, each
/// dispatch's longest loop of one invocation. It is counted for the Cholesky
/// solves (`supernodal.wgsl`), whose dot products run to thousands of
/// terms at the top of the elimination tree; the other kernels' loops (a
/// block row's tens of blocks, a reduction's tree) are left at 0.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct KernelWork {
    pub dispatches: u64,
    pub bytes: u64,
    pub minimal: u64,
    pub serial_steps: u64,
}

impl KernelWork {
    /// One dispatch of an operator application stored at `bytes` whose
    /// least storage is `minimal`.
    pub fn operator(bytes: u64, minimal: u64) -> KernelWork {
        KernelWork {
            dispatches: 1,
            bytes,
            minimal,
            serial_steps: 0,
        }
    }

    /// One dispatch of a kernel that is not an operator application.
    pub fn other(bytes: u64) -> KernelWork {
        KernelWork {
            dispatches: 1,
            bytes,
            minimal: 0,
            serial_steps: 0,
        }
    }

    /// `k` times this work.
    pub fn times(self, k: u64) -> KernelWork {
        KernelWork {
            dispatches: self.dispatches * k,
            bytes: self.bytes * k,
            minimal: self.minimal * k,
            serial_steps: self.serial_steps * k,
        }
    }
}

impl std::ops::Add for KernelWork {
    type Output = KernelWork;
    fn add(self, o: KernelWork) -> KernelWork {
        KernelWork {
            dispatches: self.dispatches + o.dispatches,
            bytes: self.bytes + o.bytes,
            minimal: self.minimal + o.minimal,
            serial_steps: self.serial_steps + o.serial_steps,
        }
    }
}

impl std::iter::Sum for KernelWork {
    fn sum<I: Iterator<Item = KernelWork>>(it: I) -> KernelWork {
        it.fold(KernelWork::default(), |a, b| a + b)
    }
}

/// A reading of [`Traffic`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TrafficCounts {
    /// Bytes written from the host to the device.
    pub to_device: u64,
    /// Bytes read back to the host.
    pub from_device: u64,
    /// Times the host waited for the queue to drain.
    pub waits: u64,
    /// Seconds spent in those waits.
    pub wait_seconds: f64,
    /// Command buffers handed to the queue ([`Context::submit`]), and the
    /// host seconds the submissions took. On a discrete GPU a submission
    /// hands work over and returns; a CPU emulation (lavapipe) may run the
    /// work inside it, so there these seconds are the emulated GPU's.
    pub submits: u64,
    pub submit_seconds: f64,
    /// Kernels submitted, with their modelled bytes ([`KernelWork`]).
    pub kernels: KernelWork,
    /// Compute passes timed with timestamp queries (0 where the adapter has
    /// no `TIMESTAMP_QUERY`) and the device seconds between their start and
    /// end timestamps.
    pub timed_passes: u64,
    pub timed_seconds: f64,
    /// Compute pipelines made where they were first needed (one per kernel
    /// and column count), and the host seconds they took: a driver compiles
    /// each, from its shader cache where it has one.
    pub compiles: u64,
    pub compile_seconds: f64,
    /// Pipelines compiled ahead of their use on another thread
    /// ([`Kernel::compile_ahead`]), and that thread's seconds.
    pub compiles_ahead: u64,
    pub compile_ahead_seconds: f64,
    /// Submissions and waits made on threads beside the solver's caller
    /// ([`Context::beside_the_caller`]: a factor made ahead, uploaded on
    /// its own thread), and the seconds they took there. They hold up none
    /// of the caller's work: `submits`, `waits` and their seconds leave
    /// them out.
    pub beside_submits: u64,
    pub beside_waits: u64,
    pub beside_seconds: f64,
    /// Of `to_device`, the bytes written on threads beside the caller.
    pub beside_to_device: u64,
}

/// The mapped staging buffers of [`Context::storage_from_pieces`], kept
/// for the windows of the uploads it serves (none before the first): two,
/// filled in turn, so that one is filled while the GPU copies the other
/// out, and each is asked to be mapped again as soon as its copy is
/// submitted.
#[derive(Default)]
pub(crate) struct Staging {
    buffers: [Option<StagingBuffer>; 2],
    /// The buffer the next window fills.
    next: usize,
}

/// One of [`Staging`]'s buffers and the state of its mapping.
struct StagingBuffer {
    buffer: wgpu::Buffer,
    /// [`MAPPED`], [`MAPPING`] (its copy submitted, the map asked for) or
    /// [`MAP_FAILED`], set by the map's callback.
    state: Arc<AtomicU8>,
}

const MAPPED: u8 = 0;
const MAPPING: u8 = 1;
const MAP_FAILED: u8 = 2;

/// Most bytes of one window of [`Context::storage_from_pieces`]: each of
/// [`Staging`]'s two buffers holds one. The staging memory is the host's on
/// a discrete GPU, and fresh pages cost their faults (2.2 GB/s on the
/// development machine, against 19 GB/s into pages already touched): two
/// of 64 MiB are half the one of 256 MiB before, and a window waits only
/// where its buffer's last copy is still under way.
pub(crate) const STAGING_WINDOW: u64 = 64 << 20;

/// Vulkan (Linux, Windows), Metal (macOS) and DX12 (Windows): the backends
/// with compute shaders and the storage limits the kernels need.
const BACKENDS: wgpu::Backends = wgpu::Backends::VULKAN
    .union(wgpu::Backends::METAL)
    .union(wgpu::Backends::DX12);

/// The process's one wgpu instance, made on first use and never dropped.
///
/// NVIDIA's Linux Vulkan driver is not safe against instances made and dropped
/// on several threads at once (gfx-rs/wgpu#5930): the conformance suite, 16
/// threads each opening its own context, died of SIGSEGV in three runs out
/// of four on an H100 (driver 580.159.04), at an address in no library's
/// symbols with no frame of ours on that thread's stack; one test at a time
/// it passed. With one instance for the process, the driver's libraries stay
/// loaded and no instance is made concurrently; adapters and devices are still
/// opened and dropped per context. `WGPU_BACKEND` and the other variables
/// `with_env` reads are read once, at first use.
fn instance() -> wgpu::Instance {
    static INSTANCE: OnceLock<wgpu::Instance> = OnceLock::new();
    INSTANCE
        .get_or_init(|| {
            let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
            desc.backends = BACKENDS;
            wgpu::Instance::new(desc.with_env())
        })
        .clone()
}

/// Bytes [`fill_window`] gives one of rayon's tasks: a mapped window is
/// written by every thread at once. Filled by one thread, a factor went up
/// at 1.8 GB/s on the H200 (985 MB in 0.545 s at homer 1.2M, its index
/// sections' making included), and one thread filled fresh staging pages
/// at 2.2 GB/s on the development machine.
const FILL_TASK: usize = 4 << 20;

/// A run of a mapped window, written by one task of [`fill_window`].
struct WindowPart<'a>(wgpu::WriteOnly<'a, [u8]>);

// SAFETY: a `WriteOnly<'a, [u8]>` is an exclusive, write-only borrow of its
// bytes, as `&'a mut [u8]` is, which is `Send`. wgpu-types 30 declares
// `Send` for `WriteOnly<'_, T>` with `T: Send` and an implicit `T: Sized`,
// which leaves slices out; nothing in the type ties it to its thread.
unsafe impl Send for WindowPart<'_> {}

/// `segments`, concatenated, into `window` (of their total length): in
/// tasks of [`FILL_TASK`] bytes on rayon's threads, each writing its own
/// run of the window.
fn fill_window(window: wgpu::WriteOnly<'_, [u8]>, segments: &[&[u8]]) {
    fill_window_in(window, segments, FILL_TASK)
}

/// [`fill_window`] in tasks of `task` bytes (the last one shorter).
fn fill_window_in(window: wgpu::WriteOnly<'_, [u8]>, segments: &[&[u8]], task: usize) {
    use rayon::prelude::*;
    let mut tasks: Vec<(WindowPart<'_>, Vec<&[u8]>)> = Vec::new();
    let mut rest = window;
    let mut run: Vec<&[u8]> = Vec::new();
    let mut run_len = 0usize;
    for seg in segments {
        let mut seg: &[u8] = seg;
        while !seg.is_empty() {
            let take = (task - run_len).min(seg.len());
            run.push(&seg[..take]);
            run_len += take;
            seg = &seg[take..];
            if run_len == task {
                let (head, tail) = rest.split_at(run_len);
                tasks.push((WindowPart(head), std::mem::take(&mut run)));
                rest = tail;
                run_len = 0;
            }
        }
    }
    if run_len > 0 {
        tasks.push((WindowPart(rest), run));
    }
    fn write((WindowPart(mut w), run): (WindowPart<'_>, Vec<&[u8]>)) {
        let mut o = 0;
        for seg in run {
            w.slice(o..o + seg.len()).copy_from_slice(seg);
            o += seg.len();
        }
    }
    match tasks.len() {
        0 | 1 => tasks.into_iter().for_each(write),
        _ => tasks.into_par_iter().for_each(write),
    }
}

impl AdapterSummary {
    /// From wgpu's adapter info and the features of the adapter (or of the
    /// device opened on it).
    pub(crate) fn of(i: &wgpu::AdapterInfo, features: wgpu::Features) -> AdapterSummary {
        AdapterSummary {
            name: i.name.clone(),
            backend: format!("{:?}", i.backend),
            device_type: format!("{:?}", i.device_type),
            driver: i.driver.clone(),
            driver_info: i.driver_info.clone(),
            shader_f64: features.contains(wgpu::Features::SHADER_F64),
            timestamp_query: features.contains(wgpu::Features::TIMESTAMP_QUERY),
        }
    }
}

fn summary(a: &wgpu::Adapter) -> AdapterSummary {
    AdapterSummary::of(&a.get_info(), a.features())
}

pub(crate) fn list_adapters() -> Vec<AdapterSummary> {
    let inst = instance();
    pollster::block_on(inst.enumerate_adapters(BACKENDS))
        .iter()
        .map(summary)
        .collect()
}

fn choose_adapter(inst: &wgpu::Instance, name: Option<&str>) -> Result<wgpu::Adapter, GpuError> {
    if let Some(want) = name {
        let want_lc = want.to_lowercase();
        let all = pollster::block_on(inst.enumerate_adapters(BACKENDS));
        let names: Vec<String> = all.iter().map(|a| a.get_info().name).collect();
        return all
            .into_iter()
            .find(|a| a.get_info().name.to_lowercase().contains(&want_lc))
            .ok_or_else(|| {
                GpuError::NoAdapter(format!(
                    "no adapter name contains '{want}' (WGPU_ADAPTER_NAME); adapters: [{}]",
                    names.join(", ")
                ))
            });
    }
    pollster::block_on(inst.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        ..Default::default()
    }))
    .map_err(|e| GpuError::NoAdapter(format!("wgpu found no Vulkan adapter ({e})")))
}

/// The adapter `open()` uses, once known: found by [`default_adapter`] or
/// by a device opened with no adapter name ([`Context::open`]).
static DEFAULT_ADAPTER: OnceLock<AdapterSummary> = OnceLock::new();

/// The adapter `open()` would use, without opening a device: found once a
/// process (wgpu's request took 0.3 s on the H200's host, on the way to the
/// scale factors' set-up, which asks where its factor is made), then kept.
pub(crate) fn default_adapter() -> Result<AdapterSummary, GpuError> {
    if let Some(known) = DEFAULT_ADAPTER.get() {
        return Ok(known.clone());
    }
    let inst = instance();
    let name = std::env::var("WGPU_ADAPTER_NAME")
        .ok()
        .filter(|s| !s.is_empty());
    let found = choose_adapter(&inst, name.as_deref()).map(|a| summary(&a))?;
    Ok(DEFAULT_ADAPTER.get_or_init(|| found).clone())
}

impl Context {
    pub fn open(opts: &OpenOptions) -> Result<Context, GpuError> {
        let inst = instance();
        let env = std::env::var("WGPU_ADAPTER_NAME")
            .ok()
            .filter(|s| !s.is_empty());
        let adapter = choose_adapter(&inst, opts.adapter_name.as_deref().or(env.as_deref()))?;
        if opts.adapter_name.is_none() {
            DEFAULT_ADAPTER.get_or_init(|| summary(&adapter));
        }
        let info = adapter.get_info();
        let mut limits = adapter.limits();
        if let Some(f) = &opts.adjust_limits {
            f(&mut limits);
        }
        check_min(&limits)?;
        let f64_feature = adapter.features() & wgpu::Features::SHADER_F64;
        let timestamps = adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("metricdeform pcg"),
            required_features: f64_feature | timestamps,
            required_limits: limits.clone(),
            memory_hints: wgpu::MemoryHints::Performance,
            ..Default::default()
        }))
        .map_err(|e| GpuError::RequestDevice(format!("{}: {e}", info.name)))?;
        let errors: Arc<Mutex<Option<GpuError>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut slot = sink.lock().unwrap();
            if slot.is_none() {
                *slot = Some(from_wgpu(e));
            }
        }));
        let lost: Arc<Mutex<Option<String>>> = Arc::default();
        let lost_sink = lost.clone();
        device.set_device_lost_callback(move |reason, msg| {
            *lost_sink.lock().unwrap() = Some(format!("{reason:?}: {msg}"));
        });
        log::info!(
            "GPU solver on {} ({:?}, {:?}, {})",
            info.name,
            info.backend,
            info.device_type,
            info.driver
        );
        let timer = (!timestamps.is_empty()).then(|| PassTimer::new(&device, &queue));
        Ok(Context {
            device,
            queue,
            info,
            limits,
            shader_f64: !f64_feature.is_empty(),
            errors,
            lost,
            traffic: Traffic::default(),
            timer,
            read_pool: Mutex::new(Vec::new()),
        })
    }

    /// Another context on this one's device and queue, with its own
    /// counts of traffic, waits and kernels (from zero), its own pass
    /// timer and read-back vectors; device errors and loss are reported to
    /// both. For a second solver of the same run (the scale factors' beside
    /// the shape systems'): one device, not two, each with its driver's
    /// host memory. A wait on either waits for the queue's work, both
    /// contexts' (as a wait beside the caller does already).
    pub fn sibling(&self) -> Context {
        Context {
            device: self.device.clone(),
            queue: self.queue.clone(),
            info: self.info.clone(),
            limits: self.limits.clone(),
            shader_f64: self.shader_f64,
            errors: self.errors.clone(),
            lost: self.lost.clone(),
            traffic: Traffic::default(),
            timer: self
                .timer
                .as_ref()
                .map(|_| PassTimer::new(&self.device, &self.queue)),
            read_pool: Mutex::new(Vec::new()),
        }
    }

    /// Host-device traffic and waits so far.
    pub fn traffic(&self) -> TrafficCounts {
        let t = &self.traffic;
        TrafficCounts {
            to_device: t.to_device.load(Ordering::Relaxed),
            from_device: t.from_device.load(Ordering::Relaxed),
            waits: t.waits.load(Ordering::Relaxed),
            wait_seconds: t.wait_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
            submits: t.submits.load(Ordering::Relaxed),
            submit_seconds: t.submit_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
            kernels: KernelWork {
                dispatches: t.dispatches.load(Ordering::Relaxed),
                bytes: t.bytes_accessed.load(Ordering::Relaxed),
                minimal: t.bytes_minimal.load(Ordering::Relaxed),
                serial_steps: t.serial_steps.load(Ordering::Relaxed),
            },
            timed_passes: t.timed_passes.load(Ordering::Relaxed),
            timed_seconds: t.timed_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
            compiles: t.compiles.load(Ordering::Relaxed),
            compile_seconds: t.compile_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
            compiles_ahead: t.compiles_ahead.load(Ordering::Relaxed),
            compile_ahead_seconds: t.compile_ahead_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
            beside_submits: t.beside_submits.load(Ordering::Relaxed),
            beside_waits: t.beside_waits.load(Ordering::Relaxed),
            beside_seconds: t.beside_nanos.load(Ordering::Relaxed) as f64 * 1e-9,
            beside_to_device: t.beside_to_device.load(Ordering::Relaxed),
        }
    }

    /// Runs `f` (on a thread of its own) with its submissions and waits
    /// counted as work beside the solver's caller
    /// ([`TrafficCounts::beside_submits`]), not the caller's.
    pub fn beside_the_caller<R>(&self, f: impl FnOnce() -> R) -> R {
        let was = BESIDE.with(|b| b.replace(true));
        let r = f();
        BESIDE.with(|b| b.set(was));
        r
    }

    /// `f` on a new thread named `name`, run [`Self::beside_the_caller`]
    /// of this context (an upload that the caller's thread need not wait
    /// for until it takes the result).
    pub fn spawn_beside<R: Send + 'static>(
        self: &Arc<Self>,
        name: String,
        f: impl FnOnce() -> R + Send + 'static,
    ) -> std::io::Result<std::thread::JoinHandle<R>> {
        let ctx = self.clone();
        std::thread::Builder::new()
            .name(name)
            .spawn(move || ctx.beside_the_caller(f))
    }

    /// Counts `bytes` written to the device (on a thread beside the caller:
    /// counted there too).
    fn count_to_device(&self, bytes: u64) {
        let t = &self.traffic;
        t.to_device.fetch_add(bytes, Ordering::Relaxed);
        if BESIDE.with(|b| b.get()) {
            t.beside_to_device.fetch_add(bytes, Ordering::Relaxed);
        }
    }

    /// Counts a submission (`wait`: a wait) that took `nanos`, the caller's
    /// or, on a thread beside it, apart.
    fn count_queue(&self, wait: bool, nanos: u64) {
        let t = &self.traffic;
        let (count, time) = match (BESIDE.with(|b| b.get()), wait) {
            (true, true) => (&t.beside_waits, &t.beside_nanos),
            (true, false) => (&t.beside_submits, &t.beside_nanos),
            (false, true) => (&t.waits, &t.wait_nanos),
            (false, false) => (&t.submits, &t.submit_nanos),
        };
        count.fetch_add(1, Ordering::Relaxed);
        time.fetch_add(nanos, Ordering::Relaxed);
    }

    /// Counts a pipeline made since `since`, `ahead` of its use.
    fn count_compile(&self, since: std::time::Instant, ahead: bool) {
        let t = &self.traffic;
        let (count, nanos) = match ahead {
            true => (&t.compiles_ahead, &t.compile_ahead_nanos),
            false => (&t.compiles, &t.compile_nanos),
        };
        count.fetch_add(1, Ordering::Relaxed);
        nanos.fetch_add(since.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }

    /// Timestamp writes for a compute pass to be timed, where the adapter
    /// has timestamp queries: pass it as the descriptor's `timestamp_writes`,
    /// then [`Context::resolve_pass_time`] after the pass and read
    /// [`Context::pass_time_buffer`] back with the pass's results.
    pub fn pass_timestamps(&self) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        self.timer
            .as_ref()
            .map(|t| wgpu::ComputePassTimestampWrites {
                query_set: &t.set,
                beginning_of_pass_write_index: Some(0),
                end_of_pass_write_index: Some(1),
            })
    }

    /// Records the resolution of the timed pass's timestamps.
    pub fn resolve_pass_time(&self, enc: &mut wgpu::CommandEncoder) {
        if let Some(t) = &self.timer {
            enc.resolve_query_set(&t.set, 0..2, &t.resolved, 0);
        }
    }

    /// The buffer holding the resolved timestamps (16 bytes), to read back.
    pub fn pass_time_buffer(&self) -> Option<(&wgpu::Buffer, u64)> {
        self.timer.as_ref().map(|t| (&t.resolved, 16))
    }

    /// Counts the pass time in the read-back `bytes` of
    /// [`Context::pass_time_buffer`] (two u64 ticks). Ticks that go backwards
    /// (a device that reset its counter) count nothing.
    pub fn count_pass_time(&self, bytes: &[u8]) {
        let (Some(t), Some(b)) = (&self.timer, bytes.get(..16)) else {
            return;
        };
        let ticks: [u64; 2] = bytemuck::pod_read_unaligned(b);
        let nanos = ticks[1].saturating_sub(ticks[0]) as f64 * t.period_ns;
        self.traffic.timed_passes.fetch_add(1, Ordering::Relaxed);
        self.traffic
            .timed_nanos
            .fetch_add(nanos as u64, Ordering::Relaxed);
    }

    /// Count kernels recorded for submission ([`KernelWork`]).
    pub fn count_kernels(&self, w: KernelWork) {
        let t = &self.traffic;
        t.dispatches.fetch_add(w.dispatches, Ordering::Relaxed);
        t.bytes_accessed.fetch_add(w.bytes, Ordering::Relaxed);
        t.bytes_minimal.fetch_add(w.minimal, Ordering::Relaxed);
        t.serial_steps.fetch_add(w.serial_steps, Ordering::Relaxed);
    }

    /// `queue.write_buffer`, counted.
    pub fn write_buffer(&self, buffer: &wgpu::Buffer, offset: u64, data: &[u8]) {
        self.count_to_device(data.len() as u64);
        self.queue.write_buffer(buffer, offset, data);
    }

    /// `queue.write_buffer_with`, counted as [`Self::write_buffer`]: `fill`
    /// writes the `len` bytes (from `buffer`'s start) straight into the
    /// queue's staging memory, with no vector of them on the host. Nothing
    /// for no bytes, or where the write is invalid (the device's error
    /// scope reports it, as for `write_buffer`).
    pub fn write_buffer_with(
        &self,
        buffer: &wgpu::Buffer,
        len: u64,
        fill: impl FnOnce(wgpu::WriteOnly<'_, [u8]>),
    ) {
        let Some(size) = wgpu::BufferSize::new(len) else {
            return;
        };
        self.count_to_device(len);
        if let Some(mut view) = self.queue.write_buffer_with(buffer, 0, size) {
            fill(view.slice(..));
        }
    }

    /// [`Self::write_buffer`] of `data` from `buffer`'s start, the queue's
    /// staging memory filled on rayon's threads ([`fill_window`], tasks of
    /// [`FILL_TASK`] bytes) where `data` is more than one task: a new matrix's
    /// values (homer 1.2M's shape sum: 63 MB of `K` and `C_i` an outer
    /// iteration) went into fresh staging pages on the calling thread, at
    /// 1.8 GB/s on the H200's host for a factor. No staging is kept between
    /// writes (`storage_from_pieces`'s windows stay mapped for a run).
    pub fn write_buffer_par(&self, buffer: &wgpu::Buffer, data: &[u8]) {
        if data.len() <= FILL_TASK {
            self.write_buffer(buffer, 0, data);
            return;
        }
        self.write_buffer_with(buffer, data.len() as u64, |view| fill_window(view, &[data]));
    }

    /// The first device error (uncaptured) or loss since the last call.
    pub fn check(&self) -> Result<(), GpuError> {
        if let Some(why) = self.lost.lock().unwrap().clone() {
            return Err(GpuError::DeviceLost(why));
        }
        match self.errors.lock().unwrap().take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Size check of one storage buffer against the binding and buffer limits.
    pub fn check_storage(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let l = &self.limits;
        if bytes > l.max_storage_buffer_binding_size {
            return Err(GpuError::LimitExceeded {
                what: what.to_string(),
                limit_name: "max_storage_buffer_binding_size",
                needed: bytes,
                limit: l.max_storage_buffer_binding_size,
            });
        }
        if bytes > l.max_buffer_size {
            return Err(GpuError::LimitExceeded {
                what: what.to_string(),
                limit_name: "max_buffer_size",
                needed: bytes,
                limit: l.max_buffer_size,
            });
        }
        Ok(())
    }

    /// A storage buffer of at least `bytes` (rounded up to 4, at least 16),
    /// checked against the limits; allocation failures become typed errors.
    pub fn storage(&self, what: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        let size = bytes.max(16).div_ceil(4) * 4;
        self.check_storage(what, size)?;
        self.create(&wgpu::BufferDescriptor {
            label: Some(what),
            size,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_DST
                | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    }

    /// A storage buffer holding `data`.
    pub fn storage_init<T: bytemuck::Pod>(
        &self,
        what: &str,
        data: &[T],
    ) -> Result<wgpu::Buffer, GpuError> {
        let b = self.storage(what, std::mem::size_of_val(data) as u64)?;
        if !data.is_empty() {
            self.write_buffer(&b, 0, bytemuck::cast_slice(data));
        }
        Ok(b)
    }

    /// A storage buffer holding the concatenation of `pieces` (`bytes` in
    /// all, a multiple of 4), copied straight into mapped staging buffers in
    /// windows of at most [`STAGING_WINDOW`] bytes, each filled by rayon's
    /// threads at once ([`fill_window`]): no host copy of the whole is
    /// made, and the host holds two windows of staging (each copied to the
    /// buffer by its own submission; a buffer is filled again once its
    /// copy is done: a factor of 3.5 GB would otherwise double the host's
    /// peak). `staging`'s two buffers serve every window, of this upload and
    /// of the others it is passed to (a Cholesky factor's index sections
    /// and value chunks): a fresh one per window (wgpu's
    /// `write_buffer_with`, before) was fresh memory to fault in each time,
    /// 15 % of the main thread's samples in homer 1.2M's GPU run on
    /// lavapipe, most of the factor uploads' time.
    pub fn storage_from_pieces<'a>(
        &self,
        staging: &mut Staging,
        what: &str,
        bytes: u64,
        pieces: impl IntoIterator<Item = &'a [u8]>,
    ) -> Result<wgpu::Buffer, GpuError> {
        self.storage_from_pieces_in(staging, what, bytes, pieces, STAGING_WINDOW)
    }

    /// [`Self::storage_from_pieces`] with windows of `window` bytes (a
    /// multiple of 4).
    fn storage_from_pieces_in<'a>(
        &self,
        staging: &mut Staging,
        what: &str,
        bytes: u64,
        pieces: impl IntoIterator<Item = &'a [u8]>,
        window_bytes: u64,
    ) -> Result<wgpu::Buffer, GpuError> {
        let b = self.storage(what, bytes)?;
        let mut pieces = pieces.into_iter();
        // The part of the current piece not yet written.
        let mut rest: &[u8] = &[];
        let mut at = 0u64;
        let mut segments: Vec<&[u8]> = Vec::new();
        while at < bytes {
            let len = window_bytes.min(bytes - at);
            // The window's bytes, as slices of the pieces, before any is
            // written: too few pieces are an error with nothing sent up.
            segments.clear();
            let mut need = len as usize;
            while need > 0 {
                if rest.is_empty() {
                    rest = pieces.next().ok_or_else(|| {
                        GpuError::Backend(format!(
                            "{what}: {} bytes of pieces for {bytes}",
                            at + len - need as u64
                        ))
                    })?;
                    continue;
                }
                let take = need.min(rest.len());
                segments.push(&rest[..take]);
                rest = &rest[take..];
                need -= take;
            }
            let st = self.staging_window(staging, len)?;
            {
                let mut view = st
                    .buffer
                    .get_mapped_range_mut(0..len)
                    .map_err(|e| GpuError::Backend(format!("{what}: staging: {e}")))?;
                fill_window(view.slice(..), &segments);
            }
            st.buffer.unmap();
            let mut enc = self.encoder("upload");
            enc.copy_buffer_to_buffer(&st.buffer, 0, &b, at, len);
            self.submit(Some(enc));
            // Mapped again once the copy is done: by the time the buffer's
            // turn comes back, most often without a wait.
            st.state.store(MAPPING, Ordering::Release);
            let state = st.state.clone();
            st.buffer.map_async(wgpu::MapMode::Write, .., move |r| {
                state.store(
                    if r.is_ok() { MAPPED } else { MAP_FAILED },
                    Ordering::Release,
                );
            });
            self.count_to_device(len);
            at += len;
        }
        if !rest.is_empty() || pieces.any(|p| !p.is_empty()) {
            return Err(GpuError::Backend(format!(
                "{what}: pieces longer than {bytes} bytes"
            )));
        }
        Ok(b)
    }

    /// `staging`'s next buffer, mapped and of at least `len` bytes: made
    /// (mapped) where it has none or a smaller one. One whose last window's
    /// copy is still under way is waited for (one host wait), after a poll
    /// that does not block has let a finished copy's mapping complete.
    fn staging_window<'s>(
        &self,
        staging: &'s mut Staging,
        len: u64,
    ) -> Result<&'s StagingBuffer, GpuError> {
        let i = staging.next;
        staging.next = 1 - i;
        let slot = &mut staging.buffers[i];
        if slot.as_ref().is_none_or(|b| b.buffer.size() < len) {
            *slot = None;
            let buffer = self.create(&wgpu::BufferDescriptor {
                label: Some("upload staging"),
                size: len,
                usage: wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: true,
            })?;
            *slot = Some(StagingBuffer {
                buffer,
                state: Arc::new(AtomicU8::new(MAPPED)),
            });
        }
        let st = slot.as_ref().unwrap();
        if st.state.load(Ordering::Acquire) == MAPPING {
            let _ = self.device.poll(wgpu::PollType::Poll);
        }
        if st.state.load(Ordering::Acquire) == MAPPING {
            self.wait()?;
        }
        match st.state.load(Ordering::Acquire) {
            MAPPED => Ok(st),
            _ => Err(GpuError::Backend("map upload staging: not mapped".into())),
        }
    }

    pub fn uniform(&self, what: &str, p: &Params) -> Result<wgpu::Buffer, GpuError> {
        self.uniform_of(what, p)
    }

    /// A uniform buffer holding `p` (any parameter struct).
    pub fn uniform_of<T: bytemuck::Pod>(
        &self,
        what: &str,
        p: &T,
    ) -> Result<wgpu::Buffer, GpuError> {
        let b = self.create(&wgpu::BufferDescriptor {
            label: Some(what),
            size: std::mem::size_of::<T>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })?;
        self.write_buffer(&b, 0, bytemuck::bytes_of(p));
        Ok(b)
    }

    fn create(&self, desc: &wgpu::BufferDescriptor) -> Result<wgpu::Buffer, GpuError> {
        self.allocate(|| self.device.create_buffer(desc))
    }

    /// Run one allocation inside out-of-memory and validation error scopes:
    /// either failure becomes a typed error instead of an uncaptured one.
    fn allocate<T>(&self, make: impl FnOnce() -> T) -> Result<T, GpuError> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let val = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let made = make();
        if let Some(e) = pollster::block_on(val.pop()) {
            drop(oom);
            return Err(from_wgpu(e));
        }
        if let Some(e) = pollster::block_on(oom.pop()) {
            return Err(from_wgpu(e));
        }
        Ok(made)
    }

    pub fn shader(&self, label: &str, source: &str) -> Result<wgpu::ShaderModule, GpuError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        // SAFETY: runtime checks are off for our own kernels only (never user
        // code). Every index they form is bounded by the `Params` the host writes
        // from the same sizes it allocated with, and every loop has a bound fixed
        // by those sizes; `Ctx::storage` checks each buffer against the limits.
        // Left on, naga wraps every array access in a clamp and every loop in a
        // counter: 15.7 against 11.0 ms per block SpMV at 50k rows on llvmpipe.
        let m = unsafe {
            self.device.create_shader_module_trusted(
                wgpu::ShaderModuleDescriptor {
                    label: Some(label),
                    source: wgpu::ShaderSource::Wgsl(source.into()),
                },
                wgpu::ShaderRuntimeChecks::unchecked(),
            )
        };
        match pollster::block_on(scope.pop()) {
            Some(e) => Err(GpuError::Backend(format!("shader {label}: {e}"))),
            None => Ok(m),
        }
    }

    /// Bind group with `(binding, buffer)` entries for `layout`.
    pub fn bind(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        entries: &[(u32, &wgpu::Buffer)],
    ) -> Result<wgpu::BindGroup, GpuError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let e: Vec<wgpu::BindGroupEntry> = entries
            .iter()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: *i,
                resource: b.as_entire_binding(),
            })
            .collect();
        let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout,
            entries: &e,
        });
        match pollster::block_on(scope.pop()) {
            Some(e) => Err(GpuError::Backend(format!("bind group {label}: {e}"))),
            None => Ok(bg),
        }
    }

    /// 2-D dispatch for `groups` workgroups: x = min(groups, max per dimension),
    /// y = ceil(groups / x). The shaders rebuild the linear index and skip overrun.
    pub fn dims(&self, what: &str, groups: u64) -> Result<(u32, u32), GpuError> {
        let max = self.limits.max_compute_workgroups_per_dimension as u64;
        let x = groups.clamp(1, max);
        let y = groups.div_ceil(x).max(1);
        if y > max {
            return Err(GpuError::LimitExceeded {
                what: format!("{what}: {groups} workgroups"),
                limit_name: "max_compute_workgroups_per_dimension",
                needed: y,
                limit: max,
            });
        }
        Ok((x as u32, y as u32))
    }

    /// Hand `enc`'s commands (none: only the queue's pending writes) to the
    /// queue, counting the submission and its host seconds.
    pub fn submit(&self, enc: Option<wgpu::CommandEncoder>) {
        let t = std::time::Instant::now();
        match enc {
            Some(enc) => self.queue.submit([enc.finish()]),
            None => self.queue.submit(std::iter::empty()),
        };
        self.count_queue(false, t.elapsed().as_nanos() as u64);
    }

    /// Submit and wait for the queue to drain.
    pub fn submit_wait(&self, enc: wgpu::CommandEncoder) -> Result<(), GpuError> {
        self.submit(Some(enc));
        self.wait()
    }

    pub fn wait(&self) -> Result<(), GpuError> {
        let t = std::time::Instant::now();
        let polled = self.device.poll(wgpu::PollType::wait_indefinitely());
        self.count_queue(true, t.elapsed().as_nanos() as u64);
        polled.map_err(|e| GpuError::Backend(format!("poll: {e}")))?;
        self.check()
    }

    pub fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// Copy `count` values of `src` (from 0) into the host, via a staging buffer
    /// that is kept in `staging` and reused while large enough.
    pub fn read<T: bytemuck::Pod>(
        &self,
        src: &wgpu::Buffer,
        count: usize,
        staging: &mut Option<wgpu::Buffer>,
        enc: Option<wgpu::CommandEncoder>,
    ) -> Result<Vec<T>, GpuError> {
        let bytes = (count * std::mem::size_of::<T>()) as u64;
        let mut parts = self.read_parts(&[(src, bytes)], staging, enc)?;
        let part = parts.pop().unwrap_or_default();
        let out = bytemuck::pod_collect_to_vec(&part);
        self.recycle(part);
        Ok(out)
    }

    /// Hands a read-back's bytes ([`Self::read_parts`]) back for a later
    /// read to fill: the largest few are kept.
    pub fn recycle(&self, bytes: Vec<u8>) {
        if bytes.capacity() == 0 {
            return;
        }
        let mut pool = self.read_pool.lock().unwrap_or_else(|e| e.into_inner());
        pool.push(bytes);
        if pool.len() > READ_POOL {
            pool.sort_unstable_by_key(|v| std::cmp::Reverse(v.capacity()));
            pool.truncate(READ_POOL);
        }
    }

    /// An empty vector for `bytes` bytes: the smallest kept one that holds
    /// them, else a new one.
    fn pooled(&self, bytes: usize) -> Vec<u8> {
        let mut pool = self.read_pool.lock().unwrap_or_else(|e| e.into_inner());
        let best = (0..pool.len())
            .filter(|&i| pool[i].capacity() >= bytes)
            .min_by_key(|&i| pool[i].capacity());
        match best {
            Some(i) => {
                let mut v = pool.swap_remove(i);
                v.clear();
                v
            }
            None => Vec::with_capacity(bytes),
        }
    }

    /// Copy the first `bytes` bytes of each buffer into the host in one
    /// submission and one wait (one staging buffer, kept in `staging` and
    /// reused while large enough); the bytes of each, in order, in vectors
    /// of earlier reads where they were handed back ([`Self::recycle`]).
    pub fn read_parts(
        &self,
        parts: &[(&wgpu::Buffer, u64)],
        staging: &mut Option<wgpu::Buffer>,
        enc: Option<wgpu::CommandEncoder>,
    ) -> Result<Vec<Vec<u8>>, GpuError> {
        // Each part at an 8-byte aligned offset, its copy padded to 4 bytes.
        let mut offsets = Vec::with_capacity(parts.len());
        let mut total = 0u64;
        for &(_, bytes) in parts {
            offsets.push(total);
            total += bytes.div_ceil(8) * 8;
        }
        if total == 0 {
            if let Some(enc) = enc {
                self.submit_wait(enc)?;
            }
            return Ok(vec![Vec::new(); parts.len()]);
        }
        if staging.as_ref().is_none_or(|s| s.size() < total) {
            if total > self.limits.max_buffer_size {
                return Err(GpuError::LimitExceeded {
                    what: "read-back staging buffer".into(),
                    limit_name: "max_buffer_size",
                    needed: total,
                    limit: self.limits.max_buffer_size,
                });
            }
            *staging = Some(self.create(&wgpu::BufferDescriptor {
                label: Some("staging"),
                size: total,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })?);
        }
        let st = staging.as_ref().unwrap();
        let mut enc = enc.unwrap_or_else(|| self.encoder("read"));
        let mut moved = 0u64;
        for (&(src, bytes), &at) in parts.iter().zip(&offsets) {
            let padded = bytes.div_ceil(4) * 4;
            if padded > 0 {
                enc.copy_buffer_to_buffer(src, 0, st, at, padded);
            }
            moved += padded;
        }
        self.submit(Some(enc));
        let (tx, rx) = std::sync::mpsc::channel();
        st.map_async(wgpu::MapMode::Read, 0..total, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .map_err(|_| GpuError::Backend("buffer map callback dropped".into()))?
            .map_err(|e| GpuError::Backend(format!("map read-back buffer: {e}")))?;
        let out = {
            let view = st
                .get_mapped_range(0..total)
                .map_err(|e| GpuError::Backend(format!("mapped range: {e}")))?;
            parts
                .iter()
                .zip(&offsets)
                .map(|(&(_, bytes), &at)| {
                    let mut v = self.pooled(bytes as usize);
                    v.extend_from_slice(&view[at as usize..(at + bytes) as usize]);
                    v
                })
                .collect()
        };
        st.unmap();
        self.traffic.from_device.fetch_add(moved, Ordering::Relaxed);
        Ok(out)
    }
}

/// Limits every kernel relies on, checked before the device is requested.
fn check_min(l: &wgpu::Limits) -> Result<(), GpuError> {
    let need: [(&'static str, u64, u64); 4] = [
        (
            "max_storage_buffers_per_shader_stage",
            8,
            l.max_storage_buffers_per_shader_stage as u64,
        ),
        (
            "max_compute_invocations_per_workgroup",
            FLAT_WG as u64,
            l.max_compute_invocations_per_workgroup as u64,
        ),
        (
            "max_compute_workgroup_size_x",
            FLAT_WG as u64,
            l.max_compute_workgroup_size_x as u64,
        ),
        (
            "max_compute_workgroup_storage_size",
            8192,
            l.max_compute_workgroup_storage_size as u64,
        ),
    ];
    for (name, needed, limit) in need {
        if limit < needed {
            return Err(GpuError::LimitExceeded {
                what: "the PCG kernels".into(),
                limit_name: name,
                needed,
                limit,
            });
        }
    }
    Ok(())
}

pub(crate) fn from_wgpu(e: wgpu::Error) -> GpuError {
    match e {
        wgpu::Error::OutOfMemory { source } => GpuError::OutOfMemory(source.to_string()),
        other => GpuError::Backend(other.to_string()),
    }
}

/// How a binding is declared in the shader.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Bind {
    Uniform,
    Read,
    ReadWrite,
}

/// A shader module with the explicit bind group layout (group 0) that all its
/// entry points and all their column-count variants share.
#[derive(Clone)]
pub(crate) struct Shader {
    pub label: &'static str,
    pub module: wgpu::ShaderModule,
    pub layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
}

impl Shader {
    pub fn new(
        ctx: &Context,
        label: &'static str,
        source: &str,
        bindings: &[(u32, Bind)],
    ) -> Result<Shader, GpuError> {
        let module = ctx.shader(label, source)?;
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let entries: Vec<wgpu::BindGroupLayoutEntry> = bindings
            .iter()
            .map(|&(binding, kind)| wgpu::BindGroupLayoutEntry {
                binding,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: match kind {
                        Bind::Uniform => wgpu::BufferBindingType::Uniform,
                        Bind::ReadWrite => wgpu::BufferBindingType::Storage { read_only: false },
                        Bind::Read => wgpu::BufferBindingType::Storage { read_only: true },
                    },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            })
            .collect();
        let layout = ctx
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries: &entries,
            });
        let pipeline_layout = ctx
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(format!("layout of {label}: {e}")));
        }
        Ok(Shader {
            label,
            module,
            layout,
            pipeline_layout,
        })
    }

    /// Bind group 0 with `(binding, buffer)` entries (every binding of the layout).
    pub fn bind(
        &self,
        ctx: &Context,
        entries: &[(u32, &wgpu::Buffer)],
    ) -> Result<wgpu::BindGroup, GpuError> {
        ctx.bind(self.label, &self.layout, entries)
    }
}

/// One entry point of a shader; its pipelines are specialised by the number of
/// columns (the `NCOLS` override) and compiled on first use, or ahead of it
/// on another thread ([`Kernel::compile_ahead`]). Clones share the compiled
/// pipelines.
#[derive(Clone)]
pub(crate) struct Kernel {
    pub label: &'static str,
    entry: &'static str,
    module: wgpu::ShaderModule,
    pipeline_layout: wgpu::PipelineLayout,
    /// Further pipeline-overridable constants (besides `NCOLS`).
    consts: Vec<(&'static str, f64)>,
    /// One slot per column count, each locked alone: a compilation ahead
    /// of one count does not hold up the use of another.
    variants: Arc<[Mutex<Option<wgpu::ComputePipeline>>]>,
}

impl Kernel {
    pub fn new(shader: &Shader, label: &'static str, entry: &'static str) -> Kernel {
        Kernel::with_constants(shader, label, entry, &[])
    }

    /// A kernel whose pipelines also set the overridable constants `consts`.
    pub fn with_constants(
        shader: &Shader,
        label: &'static str,
        entry: &'static str,
        consts: &[(&'static str, f64)],
    ) -> Kernel {
        Kernel {
            label,
            entry,
            module: shader.module.clone(),
            pipeline_layout: shader.pipeline_layout.clone(),
            consts: consts.to_vec(),
            variants: (0..crate::CMAX).map(|_| Mutex::new(None)).collect(),
        }
    }

    /// The pipeline for `ncols` columns (1..=CMAX): compiled now unless it
    /// was before (or is being compiled ahead: then when that ends).
    pub fn pipeline(&self, ctx: &Context, ncols: usize) -> Result<wgpu::ComputePipeline, GpuError> {
        self.compiled(ctx, ncols, false)
    }

    /// Compiles the pipeline for `ncols` columns ahead of its use, on the
    /// calling thread (counted apart from the compilations at use).
    pub fn compile_ahead(&self, ctx: &Context, ncols: usize) -> Result<(), GpuError> {
        self.compiled(ctx, ncols, true).map(|_| ())
    }

    fn compiled(
        &self,
        ctx: &Context,
        ncols: usize,
        ahead: bool,
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        assert!((1..=crate::CMAX).contains(&ncols));
        // Held while compiling: a use waits for the compilation ahead of it
        // instead of compiling the same pipeline again.
        let mut v = self.variants[ncols - 1]
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(p) = v.as_ref() {
            return Ok(p.clone());
        }
        let mut constants = vec![("NCOLS", ncols as f64)];
        constants.extend_from_slice(&self.consts);
        let t = std::time::Instant::now();
        // Error scopes are the calling thread's (wgpu's are thread-local).
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let p = ctx
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(self.label),
                layout: Some(&self.pipeline_layout),
                module: &self.module,
                entry_point: Some(self.entry),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    // Every workgroup-memory slot is written before it is read.
                    zero_initialize_workgroup_memory: false,
                },
                cache: None,
            });
        let popped = pollster::block_on(scope.pop());
        ctx.count_compile(t, ahead);
        log::trace!(
            "pipeline {} x{ncols} compiled{} in {:.4} s",
            self.label,
            if ahead { " ahead" } else { "" },
            t.elapsed().as_secs_f64()
        );
        if let Some(e) = popped {
            return Err(GpuError::Backend(format!("pipeline {}: {e}", self.label)));
        }
        *v = Some(p.clone());
        Ok(p)
    }
}

/// Record one dispatch.
pub(crate) fn dispatch(
    pass: &mut wgpu::ComputePass,
    pipeline: &wgpu::ComputePipeline,
    bg: &wgpu::BindGroup,
    dims: (u32, u32),
) {
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bg, &[]);
    pass.dispatch_workgroups(dims.0, dims.1, 1);
}

#[cfg(test)]
mod tests {
    /// Pieces of odd lengths, across windows far smaller than the buffer,
    /// land in order; the two staging buffers are filled in turn, the
    /// first two windows with no wait and each later one with at most one;
    /// too few or too many bytes are errors, not a short buffer.
    #[test]
    fn storage_from_pieces_writes_across_windows() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let data: Vec<u8> = (0..4000u32).map(|i| (i * 7 % 251) as u8).collect();
        let cuts = [0, 3, 4, 130, 131, 1000, 2999, 3001, 4000];
        let pieces: Vec<&[u8]> = cuts.windows(2).map(|w| &data[w[0]..w[1]]).collect();
        let waits = ctx.traffic().waits;
        let mut staging = super::Staging::default();
        let b = ctx
            .storage_from_pieces_in(&mut staging, "test", 4000, pieces.iter().copied(), 64)
            .unwrap();
        // 63 windows of 64 bytes.
        let windows = 4000u64.div_ceil(64);
        let waited = ctx.traffic().waits - waits;
        assert!(
            waited <= windows - 2,
            "{waited} waits for {windows} windows"
        );
        let back: Vec<u8> = ctx.read(&b, 4000, &mut None, None).unwrap();
        assert_eq!(back, data);
        // The same staging buffers serve a second upload: the same bytes.
        let buffers = |st: &super::Staging| -> Vec<Option<wgpu::Buffer>> {
            st.buffers
                .iter()
                .map(|b| b.as_ref().map(|b| b.buffer.clone()))
                .collect()
        };
        let first = buffers(&staging);
        let again = ctx
            .storage_from_pieces_in(&mut staging, "test", 4000, pieces.iter().copied(), 64)
            .unwrap();
        assert!(
            first.iter().all(Option::is_some) && buffers(&staging) == first,
            "the same buffers"
        );
        let back: Vec<u8> = ctx.read(&again, 4000, &mut None, None).unwrap();
        assert_eq!(back, data);
        let fresh = super::Staging::default;
        let short =
            ctx.storage_from_pieces_in(&mut fresh(), "test", 4000, pieces[..3].iter().copied(), 64);
        assert!(short.is_err());
        let long = ctx.storage_from_pieces_in(&mut fresh(), "test", 8, pieces.iter().copied(), 64);
        assert!(long.is_err());
    }

    /// A window is the pieces' bytes in order on any number of threads,
    /// with tasks that cut pieces and pieces that span tasks, and empty
    /// pieces among them.
    #[test]
    fn a_window_is_filled_in_order_by_tasks_on_many_threads() {
        let data: Vec<u8> = (0..5000u32).map(|i| (i * 13 % 253) as u8).collect();
        let cuts = [0, 1, 1, 7, 8, 300, 301, 2048, 4999, 5000];
        let segments: Vec<&[u8]> = cuts.windows(2).map(|w| &data[w[0]..w[1]]).collect();
        for threads in [1, 4] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for task in [1, 7, 64, 4096, 10_000] {
                let mut out = vec![0u8; data.len()];
                pool.install(|| {
                    super::fill_window_in(wgpu::WriteOnly::from_mut(&mut out[..]), &segments, task)
                });
                assert!(out == data, "{threads} threads, tasks of {task} bytes");
            }
        }
    }

    /// Every submission to the queue is counted with its host seconds: the
    /// windows of an upload (one each) and a read-back's copy.
    #[test]
    fn submissions_are_counted_with_their_seconds() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let data: Vec<u8> = (0..1000u32).map(|i| (i * 11 % 251) as u8).collect();
        let before = ctx.traffic();
        let b = ctx
            .storage_from_pieces_in(
                &mut super::Staging::default(),
                "test",
                1000,
                [&data[..]],
                128,
            )
            .unwrap();
        let uploaded = ctx.traffic();
        assert_eq!(uploaded.submits - before.submits, 1000u64.div_ceil(128));
        let back: Vec<u8> = ctx.read(&b, 1000, &mut None, None).unwrap();
        assert_eq!(back, data);
        let after = ctx.traffic();
        assert_eq!(after.submits - uploaded.submits, 1);
        assert!(after.submit_seconds > before.submit_seconds);
    }

    /// The same upload on a thread beside the caller
    /// (`Context::beside_the_caller`): its submissions, waits (at most one
    /// per window after the first two, a staging buffer mapped again) and
    /// bytes are counted beside, the caller's counts left as they were;
    /// the bytes land all the same.
    #[test]
    fn an_upload_beside_the_caller_is_counted_apart() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = s.ctx.clone();
        let data: Vec<u8> = (0..1000u32).map(|i| (i * 7 % 251) as u8).collect();
        let before = ctx.traffic();
        let b = std::thread::scope(|scope| {
            scope
                .spawn(|| {
                    ctx.beside_the_caller(|| {
                        ctx.storage_from_pieces_in(
                            &mut super::Staging::default(),
                            "test",
                            1000,
                            [&data[..]],
                            128,
                        )
                    })
                })
                .join()
                .unwrap()
                .unwrap()
        });
        let after = ctx.traffic();
        let windows = 1000u64.div_ceil(128);
        assert_eq!(after.beside_submits - before.beside_submits, windows);
        assert!(after.beside_waits - before.beside_waits <= windows - 2);
        assert_eq!(after.beside_to_device - before.beside_to_device, 1000);
        assert_eq!(after.to_device - before.to_device, 1000);
        assert_eq!((after.submits, after.waits), (before.submits, before.waits));
        let back: Vec<u8> = ctx.read(&b, 1000, &mut None, None).unwrap();
        assert_eq!(back, data);
    }

    /// A sibling context is on the same device (a buffer one writes, the
    /// other reads back) and counts its own traffic, from zero.
    #[test]
    fn a_sibling_shares_the_device_and_counts_apart() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let sibling = s.sibling_solver().unwrap();
        let (ctx, other) = (&s.ctx, &sibling.ctx);
        assert!(ctx.device == other.device);
        assert_eq!(other.traffic().to_device, 0);
        let data: Vec<u8> = (0..4096u32).map(|i| (i * 11 % 251) as u8).collect();
        let before = (ctx.traffic(), other.traffic());
        let b = other.storage_init("test", &data).unwrap();
        let back: Vec<u8> = ctx.read(&b, data.len(), &mut None, None).unwrap();
        assert_eq!(back, data);
        let after = (ctx.traffic(), other.traffic());
        let n = data.len() as u64;
        assert_eq!(after.1.to_device - before.1.to_device, n);
        assert_eq!(after.0.to_device, before.0.to_device);
        assert_eq!(after.0.from_device - before.0.from_device, n);
        assert_eq!(after.1.from_device, before.1.from_device);
        // Its solver solves on the shared device, counted apart too.
        let mut sib = sibling;
        let mut a = solver_cpu::SymCsc::from_pattern(3, [(0, 1), (1, 2)]);
        for j in 0..3 {
            for k in a.col_ptr[j]..a.col_ptr[j + 1] {
                a.values[k] = if a.row_idx[k] == j { 4.0 } else { -1.0 };
            }
        }
        let before = ctx.traffic();
        solver_cpu::SpdSolver::prepare(&mut sib, &a).unwrap();
        let mut x = vec![1.0, 2.0, 3.0];
        solver_cpu::SpdSolver::solve_in_place(&mut sib, &mut x, 1).unwrap();
        let mut ax = vec![0.0; 3];
        a.mul_vec(&x, &mut ax);
        assert!(
            ax.iter()
                .zip([1.0, 2.0, 3.0])
                .all(|(p, q)| (p - q).abs() < 1e-6),
            "{ax:?}"
        );
        assert_eq!(ctx.traffic().to_device, before.to_device);
        assert!(sib.ctx.traffic().to_device > n);
    }

    /// A read-back's bytes handed back are filled again by a later read of
    /// no more bytes (the same memory), with that read's bytes.
    #[test]
    fn read_backs_reuse_the_vectors_handed_back() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let data: Vec<u8> = (0..4096u32).map(|i| (i * 13 % 251) as u8).collect();
        let b = ctx.storage_init("test", &data).unwrap();
        let mut staging = None;
        let first = ctx.read_parts(&[(&b, 4096)], &mut staging, None).unwrap();
        let first = first.into_iter().next().unwrap();
        assert_eq!(first, data);
        let at = first.as_ptr();
        ctx.recycle(first);
        let again = ctx.read_parts(&[(&b, 1000)], &mut staging, None).unwrap();
        let again = again.into_iter().next().unwrap();
        assert_eq!(again.as_ptr(), at, "the vector handed back is filled again");
        assert_eq!(again, data[..1000]);
        ctx.recycle(again);
        // A read of more bytes than any kept vector holds is whole too.
        let twice = ctx
            .storage_init("test", &[&data[..], &data[..]].concat())
            .unwrap();
        let big = ctx.read::<u8>(&twice, 8192, &mut staging, None).unwrap();
        assert_eq!(big[..4096], data[..]);
        assert_eq!(big[4096..], data[..]);
    }

    /// What `fill` writes into the staging memory lands in the buffer, in
    /// order, and counts as bytes moved; no bytes write nothing.
    #[test]
    fn write_buffer_with_fills_the_buffer_in_order() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let values: Vec<f64> = (0..1000).map(|i| 1.0 / (i as f64 + 0.5)).collect();
        let b = ctx.storage("test", 8000).unwrap();
        let moved = ctx.traffic().to_device;
        ctx.write_buffer_with(&b, 8000, |view| {
            view.into_chunks::<8>()
                .0
                .write_iter(values.iter().map(|v| v.to_ne_bytes()));
        });
        ctx.write_buffer_with(&b, 0, |_| panic!("no bytes, no fill"));
        assert_eq!(ctx.traffic().to_device - moved, 8000);
        let back = ctx.read::<f64>(&b, 1000, &mut None, None).unwrap();
        assert_eq!(back, values);
    }

    /// `write_buffer_par` lands its bytes in order, as one write (up to a
    /// task's bytes) or through the staging memory filled in three tasks
    /// (two tasks' bytes and 12 more), counted once as bytes moved.
    #[test]
    fn write_buffer_par_fills_the_buffer_in_order() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        for words in [1000, super::FILL_TASK / 4, 2 * super::FILL_TASK / 4 + 3] {
            let values: Vec<u32> = (0..words as u32)
                .map(|i| i.wrapping_mul(2_654_435_761))
                .collect();
            let bytes = 4 * words as u64;
            let b = ctx.storage("test", bytes).unwrap();
            let moved = ctx.traffic().to_device;
            ctx.write_buffer_par(&b, bytemuck::cast_slice(&values));
            assert_eq!(ctx.traffic().to_device - moved, bytes, "{words} words");
            let back = ctx.read::<u32>(&b, words, &mut None, None).unwrap();
            assert!(back == values, "{words} words");
        }
    }
}
