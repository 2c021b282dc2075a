//! Pipeline benchmark: full runs to 0.001 % on the CPU backend, printed as a table
//! (mesh, faces, iterations, seconds per phase, max metric error, peak memory).
//!
//! `cargo bench --bench pipeline` (add `-- --quick` to skip the largest mesh);
//! one row: `-- --row NAME MULTIPLIERS [--preview N] [--backend cpu|gpu]`. A GPU
//! row also runs the CPU backend on the same problem and prints the largest
//! vertex deviation between the two results, in % of the bbox diagonal.
//! Each row runs in a fresh child process so that peak memory is per run.
//! A row also prints its Rust heap's peak (this process's own allocations,
//! counted by a global allocator here; a GPU driver's are not in it), and
//! `--heap-trace` prints the heap at every progress report. `--gpu-only`:
//! no CPU run after a GPU row; `--factors-at-once on|off`:
//! `Options::overlap_factorizations`.

#[path = "../tests/common/mod.rs"]
mod common;

use metricdeform::job::{Job, JobFormat};
use metricdeform::memory::peak_memory_mb;
use metricdeform::pipeline::{deform, Options, Progress, SolverBackend, SolverSummary};
use metricdeform::problem::{max_error, Problem};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering as AtomicOrdering};
use std::time::Instant;

/// Counts the bytes of this process's Rust heap and their peak: the host
/// memory the pipeline itself takes, apart from what the GPU driver
/// allocates (on lavapipe, the emulated device's memory comes from the C
/// heap and is not counted; VmHWM counts both).
struct CountingHeap;

static HEAP: AtomicUsize = AtomicUsize::new(0);
static HEAP_PEAK: AtomicUsize = AtomicUsize::new(0);

fn heap_grew(by: usize) {
    let now = HEAP.fetch_add(by, AtomicOrdering::Relaxed) + by;
    HEAP_PEAK.fetch_max(now, AtomicOrdering::Relaxed);
}

// SAFETY: every call goes to the system allocator as asked; the counters
// only add and subtract the sizes it was given.
unsafe impl GlobalAlloc for CountingHeap {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            heap_grew(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            heap_grew(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        HEAP.fetch_sub(layout.size(), AtomicOrdering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            HEAP.fetch_sub(layout.size(), AtomicOrdering::Relaxed);
            heap_grew(new_size);
        }
        p
    }
}

#[global_allocator]
static COUNTING_HEAP: CountingHeap = CountingHeap;

/// How a row refines its mesh.
#[derive(Clone, Copy)]
enum Refine {
    /// `k` times 1-to-4 midpoint subdivision (x 4^k faces).
    Midpoint(usize),
    /// Every edge cut in `n` (x n^2 faces).
    Uniform(usize),
}

fn row(
    name: &str,
    job_text: &str,
    refine: Refine,
    multipliers: &str,
    preview: Option<usize>,
    backend: SolverBackend,
) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes");
    let text = format!("{job_text}\n[solver]\nmultipliers = \"{multipliers}\"\n");
    let job = Job::from_str(&text, JobFormat::Toml, &dir, name).unwrap();
    let t0 = Instant::now();
    // As the binary does: a GPU run's device opened while the mesh is read.
    if backend == SolverBackend::Gpu {
        solver_gpu::open_ahead();
    }
    let mut mesh = metricdeform::mesh::io::read_mesh(&job.mesh_path()).unwrap();
    match refine {
        Refine::Midpoint(k) => {
            for _ in 0..k {
                mesh = mesh.subdivide_midpoint();
            }
        }
        Refine::Uniform(n) => mesh = mesh.subdivide_uniform(n),
    }
    let problem = Problem::build(&job, mesh, &job.mesh_path()).unwrap();
    let load = t0.elapsed().as_secs_f64();
    let mut options = Options::from_spec(&job.spec.solver);
    options.preview = preview;
    options.backend = backend;
    // `--factors-at-once on|off`: Options::overlap_factorizations (default:
    // on from 8 of rayon's threads, `pipeline::overlaps_factorizations`).
    if let Some(j) = std::env::args().position(|a| a == "--factors-at-once") {
        options.overlap_factorizations = match std::env::args().nth(j + 1).as_deref() {
            Some("on") => Some(true),
            Some("off") => Some(false),
            other => panic!("--factors-at-once {other:?}: expected on or off"),
        };
    }
    let mut cpu_marks = Vec::new();
    let out = deform(&problem, &options, &mut host_cpu_marks(&mut cpu_marks)).unwrap();
    let total = t0.elapsed().as_secs_f64();
    let peak = peak_memory_mb();
    let heap_peak = HEAP_PEAK.load(AtomicOrdering::Relaxed) as f64 / 1048576.0;
    println!(
        "| {name}{}{} | {} | {multipliers} | {} + {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.2e} | {:.0} |",
        preview.map_or(String::new(), |n| format!(" (preview {n})")),
        if backend == SolverBackend::Cpu {
            String::new()
        } else {
            format!(" ({})", backend.name())
        },
        problem.mesh.num_faces(),
        out.scale_driven_iterations,
        out.fine_tune_iterations,
        load,
        out.seconds_scale_driven,
        out.seconds_fine_tune,
        total,
        100.0 * max_error(&problem, &out.positions),
        peak
    );
    println!(
        "{name} ({}): Rust heap peak {heap_peak:.0} MiB (the pipeline's own host allocations, \
         the driver's not counted)",
        backend.name()
    );
    if backend == SolverBackend::Cpu || std::env::args().any(|a| a == "--gpu-only") {
        proxies(name, backend.name(), &out.solver, &cpu_marks, None);
    } else {
        options.backend = SolverBackend::Cpu;
        let mut cpu_run_marks = Vec::new();
        let cpu = deform(&problem, &options, &mut host_cpu_marks(&mut cpu_run_marks)).unwrap();
        let dev = common::max_deviation(&problem.mesh, &cpu.positions, &out.positions);
        println!(
            "{name} ({}): largest vertex deviation from the CPU result {:.2e} % of the bbox diagonal",
            backend.name(),
            100.0 * dev
        );
        proxies(name, "cpu", &cpu.solver, &cpu_run_marks, None);
        proxies(
            name,
            backend.name(),
            &out.solver,
            &cpu_marks,
            Some(&cpu.solver),
        );
    }
}

/// Mean of the outer iterations after the first: (wall seconds, seconds not
/// spent waiting for the GPU, the part of those spent handing work to the
/// GPU's queue).
fn later_outer_seconds(s: &SolverSummary) -> (f64, f64, f64) {
    let later = &s.outer[1.min(s.outer.len())..];
    let n = later.len().max(1) as f64;
    let mean = |f: &dyn Fn(&metricdeform::pipeline::OuterIteration) -> f64| {
        later.iter().map(f).sum::<f64>() / n
    };
    (
        mean(&|o| o.seconds),
        mean(&|o| o.seconds - o.work.device_seconds),
        mean(&|o| o.work.submit_seconds),
    )
}

/// CPU seconds the host's threads (this one and rayon's workers) have run,
/// from the kernel's per-thread clocks. Unlike wall seconds outside the GPU
/// waits, these leave out time a host thread stood descheduled: on lavapipe
/// the emulated GPU runs submitted work on the same cores while the host goes
/// on, which a discrete GPU does elsewhere.
fn host_cpu_seconds() -> f64 {
    fn own() -> f64 {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `t` is a valid timespec for the call to fill.
        let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0;
        assert!(ok, "clock_gettime(CLOCK_THREAD_CPUTIME_ID) failed");
        t.tv_sec as f64 + 1e-9 * t.tv_nsec as f64
    }
    own() + rayon::broadcast(|_| own()).iter().sum::<f64>()
}

/// A progress callback that marks [`host_cpu_seconds`] at each scale-driven
/// iteration's report (after its scale factors, before its shape step).
fn host_cpu_marks(marks: &mut Vec<f64>) -> impl FnMut(Progress) + '_ {
    let trace = std::env::args().any(|a| a == "--heap-trace");
    move |p| {
        if trace {
            eprintln!(
                "heap at {p:?}: {:.0} MiB, peak so far {:.0} MiB",
                HEAP.load(AtomicOrdering::Relaxed) as f64 / 1048576.0,
                HEAP_PEAK.load(AtomicOrdering::Relaxed) as f64 / 1048576.0
            );
        }
        if let Progress::ScaleDriven { .. } = p {
            marks.push(host_cpu_seconds());
        }
    }
}

/// Mean host CPU seconds between consecutive marks from the second on: one
/// shape step and the next iteration's scale factors each, the first shape
/// step (pattern analysis, first uploads) left out.
fn later_outer_cpu_seconds(marks: &[f64]) -> Option<f64> {
    let later = marks.get(1..).filter(|m| m.len() >= 2)?;
    Some((later[later.len() - 1] - later[0]) / (later.len() - 1) as f64)
}

/// The counts that predict a discrete GPU's cost (issue: GPU that
/// accelerates), one line per run: host seconds per outer iteration after
/// the first without the waits on the GPU, and the CPU seconds the host's
/// threads ran in that time (both against the CPU backend's outer iteration
/// when `cpu` is given), PCG iterations per shape solve, host waits
/// per PCG iteration and per outer iteration (by phase), preconditioner set-ups per system kind, bytes moved;
/// kernel dispatches and modelled device bytes per PCG iteration, against the
/// least bytes of the operator applications, and the chain of dependent
/// steps through the kernels (`solver_gpu::KernelWork`).
fn proxies(
    name: &str,
    backend: &str,
    s: &SolverSummary,
    marks: &[f64],
    cpu: Option<&SolverSummary>,
) {
    let (wall, host, submits) = later_outer_seconds(s);
    let host_cpu = later_outer_cpu_seconds(marks);
    let shape = &s.scale_driven;
    let all_iterations = s.scale_factors.iterations + shape.iterations + s.fine_tune.iterations;
    let waits = s.scale_factors.device_waits + shape.device_waits + s.fine_tune.device_waits;
    let beside = s.scale_factors.device_waits_beside
        + shape.device_waits_beside
        + s.fine_tune.device_waits_beside;
    let mut line = format!(
        "{name} ({backend}) proxies: outer iteration after the first {wall:.3} s, {host:.3} s of it \
         on the host ({} CPU seconds of the host's threads; {submits:.3} s in queue submissions); shape solves: {} scale-driven with {:.1} iterations on average (most {}), \
         {} fine-tune with at most {}; host waits per PCG iteration {:.3} ({waits} / {all_iterations}; \
         {beside} more on threads beside the main one), \
         per outer iteration {:.1} ({} + {} + {} in {} outer iterations: scale factors, scale-driven, \
         fine-tune); preconditioner set-ups {} + {} + {} (scale factors, scale-driven, fine-tune); {:.1} MB moved",
        host_cpu.map_or("no".into(), |c| format!("{c:.3}")),
        shape.solves,
        shape.iterations as f64 / shape.solves.max(1) as f64,
        shape.iterations_max,
        s.fine_tune.solves,
        s.fine_tune.iterations_max,
        waits as f64 / all_iterations.max(1) as f64,
        waits as f64 / s.outer.len().max(1) as f64,
        s.scale_factors.device_waits,
        shape.device_waits,
        s.fine_tune.device_waits,
        s.outer.len(),
        s.scale_factors.preconditioner_setups,
        shape.preconditioner_setups,
        s.fine_tune.preconditioner_setups,
        s.transfer_bytes() as f64 / 1e6
    );
    let phases = [&s.scale_factors, shape, &s.fine_tune];
    let dispatches: u64 = phases.iter().map(|w| w.device_dispatches).sum();
    if dispatches > 0 {
        let bytes: u64 = phases.iter().map(|w| w.device_bytes).sum();
        let minimal: u64 = phases.iter().map(|w| w.device_bytes_minimal).sum();
        let per = |v: u64, it: usize| v as f64 / it.max(1) as f64;
        line.push_str(&format!(
            "; kernel dispatches per PCG iteration {:.0} (scale-driven shape solves {:.0}); \
             modelled device bytes per PCG iteration {:.2} MB (scale-driven {:.2} MB), \
             {:.2}x the least bytes of its operator applications (scale-driven {:.2}x); \
             serial steps per PCG iteration {:.0} (scale-driven shape solves {:.0})",
            per(dispatches, all_iterations),
            per(shape.device_dispatches, shape.iterations),
            per(bytes, all_iterations) / 1e6,
            per(shape.device_bytes, shape.iterations) / 1e6,
            bytes as f64 / minimal.max(1) as f64,
            shape.device_bytes as f64 / shape.device_bytes_minimal.max(1) as f64,
            per(
                phases.iter().map(|w| w.device_serial_steps).sum(),
                all_iterations
            ),
            per(shape.device_serial_steps, shape.iterations),
        ));
        let (at_use, at_use_s, ahead, ahead_s) = phases.iter().fold((0, 0.0, 0, 0.0), |a, w| {
            (
                a.0 + w.device_compiles,
                a.1 + w.device_compile_seconds,
                a.2 + w.device_compiles_ahead,
                a.3 + w.device_compile_ahead_seconds,
            )
        });
        line.push_str(&format!(
            "; pipelines compiled at their first use {at_use} ({at_use_s:.3} s), ahead on \
             other threads {ahead} ({ahead_s:.3} s)"
        ));
    }
    if let Some(c) = cpu {
        let (cpu_wall, _, _) = later_outer_seconds(c);
        line.push_str(&format!(
            "; host seconds per outer iteration / the CPU backend's outer iteration: {:.1} % \
             ({:.1} % outside queue submissions)",
            100.0 * host / cpu_wall,
            100.0 * (host - submits) / cpu_wall
        ));
        if let Some(c) = host_cpu {
            line.push_str(&format!(
                " (host CPU seconds: {:.1} %)",
                100.0 * c / cpu_wall
            ));
        }
    }
    println!("{line}");
}

/// Mesh I/O at scale: homer subdivided `subdivisions` times, written and read
/// back as OBJ and PLY (`--io N`).
fn io_row(subdivisions: usize) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes/homer.obj");
    let mut mesh = metricdeform::mesh::io::read_mesh(&path).unwrap();
    for _ in 0..subdivisions {
        mesh = mesh.subdivide_midpoint();
    }
    let dir = tempfile::tempdir().unwrap();
    for ext in ["obj", "ply"] {
        let out = dir.path().join(format!("big.{ext}"));
        let t0 = Instant::now();
        metricdeform::mesh::io::write_mesh(&out, &mesh, &mesh.positions, None).unwrap();
        let write = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let back = metricdeform::mesh::io::read_mesh(&out).unwrap();
        let read = t1.elapsed().as_secs_f64();
        assert_eq!(back.num_faces(), mesh.num_faces());
        println!(
            "| {ext} | {} | {:.0} MB | write {write:.3} s | read {read:.3} s |",
            mesh.num_faces(),
            std::fs::metadata(&out).unwrap().len() as f64 / 1e6
        );
    }
}

fn main() {
    metricdeform::memory::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--io") {
        io_row(args[i + 1].parse().unwrap());
        return;
    }
    if let Some(i) = args.iter().position(|a| a == "--row") {
        let _ = env_logger::builder().format_timestamp_millis().try_init();
        let (name, mult) = (&args[i + 1], &args[i + 2]);
        let job: String = match name.split_once('-').map_or(name.as_str(), |(m, _)| m) {
            "spot" => common::SPOT_DEMO.into(),
            "fandisk" => common::fig9_fandisk(2.0),
            "homer" => common::TABLE1_HOMER.into(),
            "girths" => common::GIRTHS_HOMER.into(),
            _ => panic!("unknown row {name}"),
        };
        // Suffix: -xN (N = 4^k, midpoint subdivision), the sizes, about
        // 100k, 1M and 4M faces (homer's 12k faces x n^2, every edge cut in n), or
        // -uN (every edge cut in N).
        let refine = match name.rsplit_once('-').map(|(_, r)| r) {
            None => Refine::Midpoint(0),
            Some("x16") => Refine::Midpoint(2),
            Some("x64") => Refine::Midpoint(3),
            Some("x256") => Refine::Midpoint(4),
            Some("100k") => Refine::Uniform(3),
            Some("1m") => Refine::Uniform(10),
            Some("4m") => Refine::Uniform(19),
            // -uN: every edge cut in N (e.g. -u9: 972,000 faces, just under 1M).
            Some(s) if s.starts_with('u') && s[1..].parse::<usize>().is_ok() => {
                Refine::Uniform(s[1..].parse().unwrap())
            }
            Some(_) => panic!("unknown row {name}"),
        };
        // `--preview N`: the CLI's preview (N scale-driven steps, no fine-tune).
        let preview = args
            .iter()
            .position(|a| a == "--preview")
            .map(|j| args[j + 1].parse().expect("--preview N"));
        let backend = match args.iter().position(|a| a == "--backend") {
            None => SolverBackend::Cpu,
            Some(j) => match args[j + 1].as_str() {
                "cpu" => SolverBackend::Cpu,
                "cpu-direct" => SolverBackend::CpuDirect,
                "gpu" => SolverBackend::Gpu,
                other => panic!("--backend {other}: expected cpu, cpu-direct or gpu"),
            },
        };
        row(name, &job, refine, mult, preview, backend);
        return;
    }
    let quick = args.iter().any(|a| a == "--quick");
    println!("| mesh | faces | multipliers | iterations (scale-driven + fine-tune) | load s | scale-driven s | fine-tune s | total s | max metric error % | peak MiB |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut rows = vec![
        ("spot", "per_constraint"),
        ("fandisk", "per_constraint"),
        ("homer", "per_constraint"),
        ("spot", "per_kind"),
        ("homer", "per_kind"),
    ];
    if !quick {
        rows.push(("spot-x16", "per_constraint"));
        rows.push(("homer-x16", "per_constraint"));
    }
    let exe = std::env::current_exe().unwrap();
    for (name, mult) in rows {
        let status = std::process::Command::new(&exe)
            .args(["--row", name, mult])
            .status()
            .unwrap();
        if !status.success() {
            println!("| {name} | - | {mult} | failed: {status} | | | | | | |");
        }
    }
}
