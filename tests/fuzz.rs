//! Fuzz harness (issue 16, "Keep it that way") for the mesh readers (OBJ, PLY ascii and
//! binary, STL ascii and binary), the job readers (TOML, JSON) and the job/selection
//! builder (`Job::from_str` + `Problem::build` + the `measure`-level report rows and table).
//!
//! Runs on stable: `arbtest` drives the search (random seeds, time budget, seed
//! reproduction) and every input is a structure-aware mutation of a seed file from
//! `tests/fuzz-corpus/<target>/` (byte flips, truncation, splicing, extreme numbers, huge
//! PLY counts, 70,000-character names, CR-only line endings, ...); `job_build` also
//! generates jobs field by field against a fixed icosphere.
//!
//! The rule checked on every input: no panic, no hang (one input > 5 s fails), memory
//! bounded by the input's size (a counting global allocator: one input may not make its
//! thread hold more than 64 MiB + 1000 x input length at any time).
//!
//! * Short run (CI default, ~6 s per target): `cargo test --release -p metricdeform --test fuzz`
//! * Long run: `METRICDEFORM_FUZZ_SECONDS=600 cargo test --release -p metricdeform --test fuzz
//!   -- --nocapture` (seconds per target; the executions per target are printed).
//! * Reproduce one search: a failing target prints `arbtest failed! Seed: 0x...`; run that
//!   target alone with `ARBTEST_SEED=0x...` set.
//! * `METRICDEFORM_FUZZ_STRICT=1` also fails on the known bugs (panics listed in [`KNOWN`],
//!   hangs recognised by [`known_hang`], which are otherwise counted and not run).
//! * `METRICDEFORM_FUZZ_STACK=<bytes>`: stack of the fuzzing threads (default 8 MiB, as the
//!   CLI's main thread).
//!
//! On a failure the input is printed (escaped) and written to `target/fuzz-failures/`. If the
//! process dies without a word from the harness (a stack overflow aborts it), the input it
//! died on is in `target/fuzz-failures/inflight/<target>.<ext>` (a first line with its length
//! in bytes, then the input; rewritten in place before every input, removed when a target
//! finishes); the next run of that target saves it as `<target>-unfinished-<hash>.<ext>`.
//! The first input of each known bug found in a run is saved there too, as
//! `<target>-<bug id>-<hash>.<ext>`, and the slowest input of each target as
//! `<target>-slowest-<hash>.<ext>`.
//!
//! Every bug found has a reproducer in `tests/fuzz-corpus/regressions/` with a note and a
//! `regression_*` test that replays it. A bug found and not yet fixed goes in [`KNOWN`] (or
//! `known_hang`) with its test `#[ignore]`d, so that the suite still runs.

use arbitrary::Unstructured;
use glam::DVec3;
use metricdeform::job::{Job, JobFormat};
use metricdeform::mesh::topology::Topology;
use metricdeform::mesh::FaceGroup;
use metricdeform::mesh::{io, validate};
use metricdeform::pipeline::Options;
use metricdeform::problem::{max_error, Problem};
use metricdeform::report::{constraint_rows, explain_miss, table};
use metricdeform::Mesh;
use serde_json::{json, Value};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::io::Write as _;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Once, OnceLock};
use std::time::{Duration, Instant};

// ---------------------------------------------------------------------------------------
// Memory: a counting allocator (per thread, only while an input runs)
// ---------------------------------------------------------------------------------------

struct Counting;

thread_local! {
    /// Whether allocations of this thread are being counted (an input is running).
    static TRACK: Cell<bool> = const { Cell::new(false) };
    /// Bytes held by this thread's allocations since the input started (frees of older
    /// allocations may make it negative).
    static HELD: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
    /// Soft limit: exceeding it fails the input once it returns.
    static LIMIT: Cell<isize> = const { Cell::new(isize::MAX) };
}

/// Past the soft limit by this much, the allocation is refused (and the process aborts)
/// after the input has been saved: the machine must not be driven out of memory.
const HARD_MARGIN: isize = 1 << 30;

#[inline]
fn account(delta: isize) -> bool {
    // `try_with`: thread-locals may be gone while a thread exits.
    TRACK
        .try_with(|t| {
            if !t.get() {
                return true;
            }
            let held = HELD.with(|h| {
                let v = h.get() + delta;
                h.set(v);
                v
            });
            PEAK.with(|p| p.set(p.get().max(held)));
            let limit = LIMIT.with(|l| l.get());
            if held > limit.saturating_add(HARD_MARGIN) {
                t.set(false);
                hard_memory_failure(held as usize);
                return false;
            }
            true
        })
        .unwrap_or(true)
}

#[cold]
fn hard_memory_failure(held: usize) {
    let msg = format!(
        "allocation would make this input hold {held} bytes, more than 1 GiB past the limit"
    );
    save_running_input_and_report(&msg, None);
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !account(layout.size() as isize) {
            return std::ptr::null_mut();
        }
        System.alloc(layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !account(layout.size() as isize) {
            return std::ptr::null_mut();
        }
        System.alloc_zeroed(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        account(-(layout.size() as isize));
        System.dealloc(ptr, layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if !account(new_size as isize - layout.size() as isize) {
            return std::ptr::null_mut();
        }
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

fn memory_limit(input_len: usize) -> isize {
    (64usize << 20).saturating_add(input_len.saturating_mul(1000)) as isize
}

// ---------------------------------------------------------------------------------------
// Settings
// ---------------------------------------------------------------------------------------

/// Seconds of search per target (default 6: 8 targets stay under 1.5 minutes on 2 cores).
fn budget() -> Duration {
    let secs = std::env::var("METRICDEFORM_FUZZ_SECONDS")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .unwrap_or(6.0);
    Duration::from_secs_f64(secs.max(0.0))
}

fn strict() -> bool {
    std::env::var("METRICDEFORM_FUZZ_STRICT").is_ok_and(|v| !v.is_empty() && v != "0")
}

/// One input may run this long.
const HANG_LIMIT: Duration = Duration::from_secs(5);

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn corpus_dir(target: &str) -> PathBuf {
    root().join("tests/fuzz-corpus").join(target)
}

fn failures_dir() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target"));
    target.join("fuzz-failures")
}

/// Scratch folder for the files the readers are given (tmpfs when there is one).
fn scratch_dir() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let shm = Path::new("/dev/shm");
        let b = tempfile::Builder::new()
            .prefix("metricdeform-fuzz")
            .tempdir_in(shm);
        b.or_else(|_| tempfile::tempdir()).expect("scratch dir")
    })
    .path()
}

// ---------------------------------------------------------------------------------------
// The running input: for the watchdog and the allocator's last words
// ---------------------------------------------------------------------------------------

#[derive(Clone)]
struct Running {
    target: &'static str,
    ext: &'static str,
    input: Arc<Vec<u8>>,
    started: Instant,
}

static RUNNING: Mutex<Vec<Running>> = Mutex::new(Vec::new());

thread_local! {
    /// Index into RUNNING of this thread's target; usize::MAX when none.
    static SLOT: Cell<usize> = const { Cell::new(usize::MAX) };
}

fn escaped(bytes: &[u8]) -> String {
    const SHOW: usize = 2000;
    let head = &bytes[..bytes.len().min(SHOW)];
    let mut s = format!("b\"{}\"", head.escape_ascii());
    if bytes.len() > SHOW {
        s.push_str(&format!(" ... ({} bytes in all)", bytes.len()));
    }
    s
}

fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf29ce484222325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x100000001b3)
    })
}

/// Writes the input to target/fuzz-failures/ and returns the path.
fn save_failure(target: &str, kind: &str, ext: &str, input: &[u8]) -> PathBuf {
    let dir = failures_dir();
    let _ = std::fs::create_dir_all(&dir);
    let path = dir.join(format!("{target}-{kind}-{:016x}.{ext}", fnv(input)));
    let _ = std::fs::write(&path, input);
    path
}

/// Called when the process cannot go on (hang, allocation far past the limit): saves and
/// prints the running input of `slot` (this thread's when None).
fn save_running_input_and_report(what: &str, slot: Option<usize>) {
    let slot = slot.unwrap_or_else(|| SLOT.with(|s| s.get()));
    let running = RUNNING.try_lock().ok().and_then(|r| r.get(slot).cloned());
    match running {
        Some(r) => {
            let kind = if what.contains("hang") {
                "hang"
            } else {
                "memory"
            };
            let path = save_failure(r.target, kind, r.ext, &r.input);
            // Straight to stderr: the test harness's capture would swallow it on exit.
            let _ = writeln!(
                std::io::stderr(),
                "\nFUZZ FAILURE [{}]: {what}\n  input: {}\n  saved: {}\n",
                r.target,
                escaped(&r.input),
                path.display()
            );
        }
        None => {
            let _ = writeln!(
                std::io::stderr(),
                "\nFUZZ FAILURE: {what} (input unknown)\n"
            );
        }
    }
}

/// One watchdog for the whole binary: an input running longer than HANG_LIMIT ends the
/// process (the stuck thread cannot be stopped) after its input has been saved.
fn start_watchdog() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        std::thread::spawn(|| loop {
            std::thread::sleep(Duration::from_millis(200));
            let stuck = {
                let r = RUNNING.lock().unwrap_or_else(|e| e.into_inner());
                r.iter()
                    .position(|x| x.started.elapsed() > HANG_LIMIT && !x.input.is_empty())
            };
            if let Some(i) = stuck {
                let msg = format!("hang: one input ran longer than {HANG_LIMIT:?}");
                save_running_input_and_report(&msg, Some(i));
                std::process::exit(101);
            }
        });
    });
}

// ---------------------------------------------------------------------------------------
// Panics: captured per thread, classified against the known bugs
// ---------------------------------------------------------------------------------------

thread_local! {
    static QUIET: Cell<bool> = const { Cell::new(false) };
    static LAST_PANIC: std::cell::RefCell<Option<(String, String)>> =
        const { std::cell::RefCell::new(None) };
}

fn install_panic_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let location = info
                .location()
                .map(|l| format!("{}:{}", l.file(), l.line()))
                .unwrap_or_default();
            let payload = info.payload();
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            LAST_PANIC.with(|p| *p.borrow_mut() = Some((location, message)));
            if !QUIET.with(|q| q.get()) {
                default(info);
            }
        }));
    });
}

/// A bug the harness finds today, not yet fixed in src/ (owned by others). Inputs that
/// panic with this signature are counted, not failed (unless METRICDEFORM_FUZZ_STRICT).
struct Known {
    id: &'static str,
    /// Substring of the panic location (`file:line`).
    location: &'static str,
    /// Substring of the panic message.
    message: &'static str,
}

/// None open: the two found so far (report-table-long-name, ply-binary-empty-element-hang)
/// are fixed and replayed by the `regression_*` tests.
const KNOWN: &[Known] = &[];

/// Known hangs cannot be caught after the fact (the stuck thread cannot be stopped), so
/// their inputs are recognised here before they run and counted, not run (unless strict,
/// or when a `regression_*` test replays them). None is open.
fn known_hang(_target: &Target, _input: &[u8]) -> Option<&'static str> {
    None
}

thread_local! {
    /// Set while a `regression_*` test replays a reproducer: nothing is skipped.
    static REPLAY: Cell<bool> = const { Cell::new(false) };
}

fn classify(location: &str, message: &str) -> Option<&'static Known> {
    KNOWN
        .iter()
        .find(|k| location.contains(k.location) && message.contains(k.message))
}

// ---------------------------------------------------------------------------------------
// Running one input
// ---------------------------------------------------------------------------------------

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Verdict {
    /// Parsed (or built) without error.
    Accepted,
    /// Rejected with an error: fine.
    Rejected,
    /// A known bug (counted; a failure only when strict).
    Known(&'static str),
}

#[derive(Default)]
struct Stats {
    execs: u64,
    accepted: u64,
    known: std::collections::BTreeMap<&'static str, u64>,
    max_len: usize,
    max_peak: isize,
    /// The slowest input and its seconds.
    slowest: (f64, Vec<u8>),
    gen_secs: f64,
    exec_secs: f64,
    /// Where the running input is written first (see [`Inflight`]).
    inflight: Option<Inflight>,
}

struct Target {
    name: &'static str,
    ext: &'static str,
    slot: usize,
    run: fn(&[u8], &Fixture) -> bool,
}

/// Runs `target.run` on `input` under the guards; panics (failing the test) on an unknown
/// panic or a memory blow-up, after printing and saving the input.
fn exec(target: &Target, fx: &Fixture, input: &[u8], stats: &mut Stats) -> Verdict {
    if !strict() && !REPLAY.with(|r| r.get()) {
        if let Some(id) = known_hang(target, input) {
            let n = stats.known.entry(id).or_insert(0);
            if *n == 0 {
                save_failure(target.name, id, target.ext, input);
            }
            *n += 1;
            stats.execs += 1;
            return Verdict::Known(id);
        }
    }
    // A crash that cannot be caught (stack overflow, abort) leaves this file behind.
    if let Some(f) = &stats.inflight {
        f.record(input);
    }
    let shared = Arc::new(input.to_vec());
    {
        let mut r = RUNNING.lock().unwrap_or_else(|e| e.into_inner());
        r[target.slot] = Running {
            target: target.name,
            ext: target.ext,
            input: shared,
            started: Instant::now(),
        };
    }
    let limit = memory_limit(input.len());
    HELD.with(|h| h.set(0));
    PEAK.with(|p| p.set(0));
    LIMIT.with(|l| l.set(limit));
    QUIET.with(|q| q.set(true));
    LAST_PANIC.with(|p| *p.borrow_mut() = None);
    TRACK.with(|t| t.set(true));
    let t0 = Instant::now();
    let result = catch_unwind(AssertUnwindSafe(|| (target.run)(input, fx)));
    let secs = t0.elapsed().as_secs_f64();
    stats.exec_secs += secs;
    TRACK.with(|t| t.set(false));
    QUIET.with(|q| q.set(false));
    {
        let mut r = RUNNING.lock().unwrap_or_else(|e| e.into_inner());
        r[target.slot].input = Arc::new(Vec::new());
    }
    let peak = PEAK.with(|p| p.get());
    stats.execs += 1;
    stats.max_len = stats.max_len.max(input.len());
    stats.max_peak = stats.max_peak.max(peak);
    if secs > stats.slowest.0 {
        stats.slowest = (secs, input.to_vec());
    }
    let fail = |kind: &str, what: String| -> ! {
        let path = save_failure(target.name, kind, target.ext, input);
        panic!(
            "FUZZ FAILURE [{}]: {what}\n  input: {}\n  saved: {}",
            target.name,
            escaped(input),
            path.display()
        );
    };
    if peak > limit {
        fail(
            "memory",
            format!(
                "one input of {} bytes made its thread hold {peak} bytes (limit {limit})",
                input.len()
            ),
        );
    }
    match result {
        Ok(true) => {
            stats.accepted += 1;
            Verdict::Accepted
        }
        Ok(false) => Verdict::Rejected,
        Err(_) => {
            let (location, message) = LAST_PANIC
                .with(|p| p.borrow_mut().take())
                .unwrap_or_default();
            match classify(&location, &message) {
                Some(k) if !strict() => {
                    let n = stats.known.entry(k.id).or_insert(0);
                    if *n == 0 {
                        save_failure(target.name, k.id, target.ext, input);
                    }
                    *n += 1;
                    Verdict::Known(k.id)
                }
                _ => fail("panic", format!("panic at {location}: {message}")),
            }
        }
    }
}

/// The seed corpus, unmutated, then the mutation search for the time budget.
/// `target/fuzz-failures/inflight/<target>.<ext>`: the input being run, after a first
/// line with its length in bytes (written in place, never truncated: a rewrite per input
/// costs 200 us on ext4, this ~1 us). If the test process dies without a word from the
/// harness (stack overflow, abort), this is the input it died on; the next run of the
/// target saves it as `<target>-unfinished-<hash>.<ext>` and says so; a target that
/// finishes removes it.
struct Inflight {
    path: PathBuf,
    file: Option<std::fs::File>,
}

impl Inflight {
    fn open(target: &Target) -> Inflight {
        let dir = failures_dir().join("inflight");
        let _ = std::fs::create_dir_all(&dir);
        let path = dir.join(format!("{}.{}", target.name, target.ext));
        if let Ok(old) = std::fs::read(&path) {
            if let Some(nl) = old.iter().position(|&c| c == b'\n') {
                let len: usize = String::from_utf8_lossy(&old[..nl])
                    .trim()
                    .parse()
                    .unwrap_or(0);
                if let Some(input) = old.get(nl + 1..nl + 1 + len) {
                    let saved = save_failure(target.name, "unfinished", target.ext, input);
                    eprintln!(
                        "fuzz {}: an earlier run did not finish (crash, abort or kill) while \
                         running {}; saved as {}",
                        target.name,
                        escaped(input),
                        saved.display()
                    );
                }
            }
        }
        let file = std::fs::OpenOptions::new()
            .create(true)
            .write(true)
            .truncate(true)
            .open(&path)
            .ok();
        Inflight { path, file }
    }

    fn record(&self, input: &[u8]) {
        #[cfg(unix)]
        if let Some(f) = &self.file {
            use std::os::unix::fs::FileExt;
            let _ = f.write_all_at(format!("{:>20}\n", input.len()).as_bytes(), 0);
            let _ = f.write_all_at(input, 21);
        }
    }

    fn finish(self) {
        drop(self.file);
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Stack of the fuzzing threads: `METRICDEFORM_FUZZ_STACK` bytes, default 8 MiB.
fn stack_size() -> usize {
    std::env::var("METRICDEFORM_FUZZ_STACK")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(8 << 20)
}

/// Each target searches on its own thread with the stack of a command-line run's main
/// thread (8 MiB), so that a stack overflow found here is one the CLI has too.
fn fuzz(target: &'static Target) {
    let t = std::thread::Builder::new()
        .name(target.name.into())
        .stack_size(stack_size())
        .spawn(move || fuzz_on_this_thread(target))
        .unwrap();
    if let Err(e) = t.join() {
        std::panic::resume_unwind(e);
    }
}

fn fuzz_on_this_thread(target: &Target) {
    install_panic_hook();
    start_watchdog();
    let fx = fixture();
    let seeds = read_corpus(target.name);
    assert!(!seeds.is_empty(), "no seed files for {}", target.name);
    let mut stats = Stats {
        inflight: Some(Inflight::open(target)),
        ..Stats::default()
    };
    for (path, bytes) in &seeds {
        let v = exec(target, fx, bytes, &mut stats);
        assert_eq!(
            v,
            Verdict::Accepted,
            "seed file {} must be accepted",
            path.display()
        );
    }
    let splice: Vec<Vec<u8>> = all_seeds();
    let t0 = Instant::now();
    let budget = budget();
    let stats = Mutex::new(stats);
    if !budget.is_zero() {
        arbtest::arbtest(|u| {
            let g0 = Instant::now();
            let input = if target.name == "job_build" && u.ratio(1, 2)? {
                generated_job(u, fx)?
            } else {
                let (_, seed) = u.choose(&seeds)?;
                mutate(u, seed, &splice, target.name)?
            };
            let mut st = stats.lock().unwrap();
            st.gen_secs += g0.elapsed().as_secs_f64();
            exec(target, fx, &input, &mut st);
            Ok(())
        })
        .size_max(4096)
        .budget(budget)
        .run();
    }
    let mut s = stats.into_inner().unwrap();
    if let Some(f) = s.inflight.take() {
        f.finish();
    }
    let secs = t0.elapsed().as_secs_f64();
    let slow = save_failure(target.name, "slowest", target.ext, &s.slowest.1);
    eprintln!(
        "fuzz {:<10} gen {:.2} s exec {:.2} s; {:>9} executions in {:>7.1} s ({:>8.0}/s), {} accepted, longest input {} bytes, \
         peak held {} KiB, known bugs hit: {:?}, slowest input {:.3} s ({} bytes, {})",
        target.name,
        s.gen_secs,
        s.exec_secs,
        s.execs,
        secs,
        s.execs as f64 / secs.max(1e-9),
        s.accepted,
        s.max_len,
        s.max_peak / 1024,
        s.known,
        s.slowest.0,
        s.slowest.1.len(),
        slow.display()
    );
    TOTAL_EXECS.fetch_add(s.execs, Ordering::Relaxed);
}

static TOTAL_EXECS: AtomicU64 = AtomicU64::new(0);

fn read_corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(corpus_dir(target))
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    files.retain(|p| p.is_file());
    files.sort();
    files
        .into_iter()
        .map(|p| {
            let b = std::fs::read(&p).unwrap();
            (p, b)
        })
        .collect()
}

fn all_seeds() -> Vec<Vec<u8>> {
    TARGETS
        .iter()
        .flat_map(|t| read_corpus(t.name).into_iter().map(|(_, b)| b))
        .collect()
}

// ---------------------------------------------------------------------------------------
// Mutations
// ---------------------------------------------------------------------------------------

const EXTREMES: &[&str] = &[
    "1e308",
    "-1e308",
    "1e309",
    "-0",
    "-0.0",
    "nan",
    "NaN",
    "-nan",
    "inf",
    "-inf",
    "infinity",
    "4294967295",
    "4294967296",
    "4000000000",
    "2147483647",
    "-2147483648",
    "18446744073709551615",
    "18446744073709551616",
    "9223372036854775807",
    "-9223372036854775808",
    "99999999999999999999999999",
    "1e-320",
    "5e-324",
    "0",
    "-1",
    "1",
    "2",
    "3",
    "255",
    "256",
    "65535",
    "65536",
    "0x10",
    "1_000",
    "1.",
    ".5",
    "1e",
    "+",
    "-",
];

const DICT_COMMON: &[&str] = &["\n", "\r\n", "\r", " ", "\t", "\0", "#", "\"", "'", "\\"];
const DICT_OBJ: &[&str] = &[
    "v ",
    "f ",
    "g ",
    "o ",
    "vt ",
    "vn ",
    "s ",
    "l ",
    "/",
    "//",
    "f 1 2 3\n",
    "f -1 -2 -3\n",
    "f 1/1/1 2//2 3/3\n",
    "v 1 2 3\n",
    "g a b a\n",
    "o \n",
    "f 1 2\n",
    "f 4294967295 1 2\n",
];
const DICT_PLY: &[&str] = &[
    "ply\n",
    "format ascii 1.0\n",
    "format binary_little_endian 1.0\n",
    "format binary_big_endian 1.0\n",
    "element vertex 4294967295\n",
    "element face 4294967295\n",
    "element vertex 18446744073709551615\n",
    "element edge 3\n",
    "property float x\n",
    "property double z\n",
    "property uchar red\n",
    "property list uchar int vertex_indices\n",
    "property list uint uint vertex_indices\n",
    "property list uchar float vertex_indices\n",
    "property list int int vertex_index\n",
    "property list uchar uchar extra\n",
    "end_header\n",
    "comment ",
    "obj_info ",
    "255 ",
    "int",
    "uint8",
    "float32",
];
const DICT_STL: &[&str] = &[
    "solid ",
    "solid\n",
    "facet normal 0 0 1\n",
    "outer loop\n",
    "vertex 0 0 0\n",
    "vertex nan inf -inf\n",
    "endloop\n",
    "endfacet\n",
    "endsolid\n",
    "endsolid x\n",
];
const DICT_JOB: &[&str] = &[
    "kind",
    "name",
    "curve",
    "plane",
    "origin",
    "normal",
    "path",
    "closed",
    "points",
    "face",
    "bary",
    "region",
    "faces",
    "faces_file",
    "sphere",
    "center",
    "radius",
    "box",
    "min",
    "max",
    "group",
    "vertices",
    "translate",
    "scale",
    "value",
    "mesh",
    "output",
    "[[constraint]]\n",
    "[[handle]]\n",
    "[[curvature]]\n",
    "[solver]\n",
    "[solver.weights]\n",
    "length",
    "area",
    "volume",
    "true",
    "false",
    "null",
    "[]",
    "{}",
    "[0, 1, 2]",
    "=",
    ":",
    ",",
    "{",
    "}",
    "[",
    "]",
    "\"\"\"",
    "'''",
    "\\u0000",
    "\\ud800",
    "1979-05-27T07:32:00Z",
    "k_f",
    "tolerance",
    "max_iterations",
    "backend",
    "inf",
    "nan",
    "-0.0",
];

fn dict_for(target: &str) -> &'static [&'static str] {
    match target {
        "obj" => DICT_OBJ,
        "ply_ascii" | "ply_binary" => DICT_PLY,
        "stl_ascii" | "stl_binary" => DICT_STL,
        _ => DICT_JOB,
    }
}

/// Byte spans of the numbers in `b` (optional sign, digits, '.', exponent).
fn number_spans(b: &[u8]) -> Vec<(usize, usize)> {
    let mut spans = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let start = i;
        let mut j = i;
        if j < b.len() && (b[j] == b'-' || b[j] == b'+') {
            j += 1;
        }
        let digits_start = j;
        while j < b.len() && (b[j].is_ascii_digit() || b[j] == b'.') {
            j += 1;
        }
        if j > digits_start && b[digits_start..j].iter().any(|c| c.is_ascii_digit()) {
            if j < b.len() && (b[j] == b'e' || b[j] == b'E') {
                let mut k = j + 1;
                if k < b.len() && (b[k] == b'-' || b[k] == b'+') {
                    k += 1;
                }
                let e0 = k;
                while k < b.len() && b[k].is_ascii_digit() {
                    k += 1;
                }
                if k > e0 {
                    j = k;
                }
            }
            spans.push((start, j));
            i = j;
        } else {
            // Linear: a run of dots (or a lone sign) is skipped as a whole.
            i = j.max(start + 1);
        }
    }
    spans
}

fn binary_offset(input: &[u8]) -> usize {
    // PLY: after end_header; STL: after the 84-byte header.
    if let Some(p) = input.windows(11).position(|w| w == b"end_header\n") {
        p + 11
    } else if input.len() >= 84 && !input.starts_with(b"solid") {
        84
    } else {
        0
    }
}

const LONG: usize = 70_000;

fn mutate(
    u: &mut Unstructured<'_>,
    seed: &[u8],
    splice: &[Vec<u8>],
    target: &str,
) -> arbitrary::Result<Vec<u8>> {
    let mut b = seed.to_vec();
    // Mostly one mutation, sometimes a few (stacked mutations rarely stay parseable).
    let n = *u.choose(&[1usize, 1, 1, 2, 2, 3, 5])?;
    for _ in 0..n {
        let before = b.len();
        mutate_once(u, &mut b, splice, target)?;
        if b.len() > MAX_INPUT && b.len() > before {
            b.truncate(before.max(MAX_INPUT));
        }
    }
    Ok(b)
}

/// Inputs do not grow past this (a 70,000-character name and some room around it).
const MAX_INPUT: usize = 256 * 1024;

fn mutate_once(
    u: &mut Unstructured<'_>,
    b: &mut Vec<u8>,
    splice: &[Vec<u8>],
    target: &str,
) -> arbitrary::Result<()> {
    {
        let len = b.len();
        let pos = if len == 0 {
            0
        } else {
            u.int_in_range(0..=len)?
        };
        // Weighted choice: cheap local edits often, big ones rarely.
        let op = match u.int_in_range(0..=99)? {
            0..=14 => 0,
            15..=24 => 1,
            25..=29 => 2,
            30..=37 => 3,
            38..=54 => 4,
            55..=66 => 7,
            67 => 9,
            68..=70 => 10,
            71..=80 => 11,
            81..=87 => 14,
            88..=90 => 16,
            91..=92 => 17,
            93..=95 => 18,
            _ => 19,
        };
        match op {
            // byte flips
            0 if len > 0 => {
                let i = pos.min(len - 1);
                b[i] ^= 1 << u.int_in_range(0..=7)?;
            }
            1 if len > 0 => {
                let i = pos.min(len - 1);
                b[i] = u.arbitrary()?;
            }
            // truncation
            2 => b.truncate(pos),
            // splicing: a piece of any seed (of any target) at a random place
            3 => {
                let other = u.choose(splice)?;
                if !other.is_empty() {
                    let a = u.int_in_range(0..=other.len() - 1)?;
                    let e = u.int_in_range(a..=other.len())?;
                    b.splice(pos..pos, other[a..e].iter().copied());
                }
            }
            // number replacement with an extreme value
            4..=6 => {
                let spans = number_spans(b);
                if !spans.is_empty() {
                    let (s, e) = *u.choose(&spans)?;
                    let x = u.choose(EXTREMES)?;
                    b.splice(s..e, x.bytes());
                }
            }
            // dictionary token insertion
            7 | 8 => {
                let d = if u.ratio(1, 4)? {
                    DICT_COMMON
                } else {
                    dict_for(target)
                };
                let t = u.choose(d)?;
                b.splice(pos..pos, t.bytes());
            }
            // very long names: 70,000 copies of a byte at a random place
            9 => {
                let c = if len > 0 && u.ratio(1, 2)? {
                    b[pos.min(len - 1)]
                } else {
                    *u.choose(&b"aZ_-.0\xc3"[..])?
                };
                let c = if c == b'\n' || c == b'\r' { b'n' } else { c };
                b.splice(pos..pos, std::iter::repeat_n(c, LONG));
            }
            // line endings: CR only, CRLF, LF only
            10 => {
                let mode = u.int_in_range(0..=2)?;
                *b = match mode {
                    0 => b
                        .iter()
                        .map(|&c| if c == b'\n' { b'\r' } else { c })
                        .collect(),
                    1 => {
                        let mut out = Vec::with_capacity(b.len() * 2);
                        for &c in b.iter() {
                            if c == b'\n' {
                                out.push(b'\r');
                            }
                            out.push(c);
                        }
                        out
                    }
                    _ => b.iter().copied().filter(|&c| c != b'\r').collect(),
                };
            }
            // lines: delete, duplicate (up to 1000 times), swap
            11..=13 => {
                let lines: Vec<&[u8]> = b.split_inclusive(|&c| c == b'\n').collect();
                if !lines.is_empty() {
                    let i = u.choose_index(lines.len())?;
                    let j = u.choose_index(lines.len())?;
                    let mut out: Vec<Vec<u8>> = lines.iter().map(|l| l.to_vec()).collect();
                    match u.int_in_range(0..=2)? {
                        0 => {
                            out.remove(i);
                        }
                        1 => {
                            let k = *u.choose(&[1usize, 2, 10, 1000])?;
                            let l = out[i].clone();
                            let k = k.min(MAX_INPUT / l.len().max(1)).max(1);
                            out.splice(i..i, std::iter::repeat_n(l, k));
                        }
                        _ => out.swap(i, j),
                    }
                    *b = out.concat();
                }
            }
            // binary payload: a 1/2/4/8-byte word set to an extreme
            14 | 15 => {
                let off = binary_offset(b);
                if len > off + 8 {
                    let at = u.int_in_range(off..=len - 8)?;
                    let words: &[[u8; 8]] = &[
                        u64::MAX.to_le_bytes(),
                        0u64.to_le_bytes(),
                        (u32::MAX as u64).to_le_bytes(),
                        (i32::MAX as u64).to_le_bytes(),
                        f64::NAN.to_le_bytes(),
                        f64::INFINITY.to_le_bytes(),
                        f64::MAX.to_le_bytes(),
                        ((f32::NAN.to_bits() as u64) | ((f32::INFINITY.to_bits() as u64) << 32))
                            .to_le_bytes(),
                        (f32::MIN_POSITIVE.to_bits() as u64 * 0x1_0000_0001).to_le_bytes(),
                        (0xffu64).to_le_bytes(),
                        (0x80u64).to_le_bytes(),
                    ];
                    let w = u.choose(words)?;
                    let width = *u.choose(&[1usize, 2, 4, 8])?;
                    let w = if u.ratio(1, 2)? {
                        let mut r = *w;
                        r.reverse();
                        r
                    } else {
                        *w
                    };
                    b[at..at + width].copy_from_slice(&w[..width]);
                }
            }
            // STL: the triangle count at offset 80, sometimes kept consistent with the size
            16 if len >= 84 && target == "stl_binary" => {
                let n: u32 = match u.int_in_range(0..=5)? {
                    0 => ((len - 84) / 50) as u32,
                    1 => u32::MAX,
                    2 => 0,
                    3 => u32::MAX / 50,
                    4 => ((len - 84) / 50) as u32 + 1,
                    _ => u.arbitrary()?,
                };
                b[80..84].copy_from_slice(&n.to_le_bytes());
            }
            // binary records duplicated (a 50-byte STL triangle, or any chunk), count fixed
            17 if len > 84 && target == "stl_binary" => {
                let k = *u.choose(&[1usize, 3, 100, 5000])?.min(&(MAX_INPUT / 50));
                let t = u.int_in_range(0..=(len - 84).saturating_sub(50) / 50)?;
                let start = (84 + 50 * t).min(len);
                let rec: Vec<u8> = b[start..(start + 50).min(len)].to_vec();
                for _ in 0..k {
                    b.extend_from_slice(&rec);
                }
                let n = ((b.len() - 84) / 50) as u32;
                b[80..84].copy_from_slice(&n.to_le_bytes());
            }
            // PLY: one element count in the header set to an extreme or a bigger count
            18 if target.starts_with("ply") => {
                let hdr_end = binary_offset(b).max(1).min(b.len());
                let spans: Vec<(usize, usize)> = number_spans(&b[..hdr_end])
                    .into_iter()
                    .filter(|&(s, _)| b[..s].ends_with(b"vertex ") || b[..s].ends_with(b"face "))
                    .collect();
                if !spans.is_empty() {
                    let (s, e) = *u.choose(&spans)?;
                    let x = *u.choose(&[
                        "4294967295",
                        "4000000000",
                        "18446744073709551615",
                        "9223372036854775807",
                        "5",
                        "3",
                        "0",
                        "1000000",
                    ])?;
                    b.splice(s..e, x.bytes());
                }
            }
            // random bytes inserted
            _ => {
                let k = u.int_in_range(1..=16)?;
                let bytes: Vec<u8> = (0..k).map(|_| u.arbitrary()).collect::<Result<_, _>>()?;
                b.splice(pos..pos, bytes);
            }
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// job_build: jobs generated field by field against the fixed mesh
// ---------------------------------------------------------------------------------------

thread_local! {
    /// Whether the job being generated stays mostly valid (so that Problem::build gets
    /// past the first field and the selections and report rows run).
    static SANE: Cell<bool> = const { Cell::new(false) };
}

/// True for a wild value: always outside sane jobs, rarely inside them.
fn wild(u: &mut Unstructured<'_>) -> arbitrary::Result<bool> {
    if SANE.with(|s| s.get()) {
        u.ratio(1, 150)
    } else {
        Ok(true)
    }
}

fn gen_f64(u: &mut Unstructured<'_>) -> arbitrary::Result<f64> {
    if !wild(u)? {
        return Ok(u.int_in_range(-1500..=1500)? as f64 / 1000.0);
    }
    Ok(match u.int_in_range(0..=9)? {
        0 => *u.choose(&[
            0.0,
            -0.0,
            1e308,
            -1e308,
            f64::MAX,
            f64::MIN_POSITIVE,
            5e-324,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e-12,
            4294967295.0,
        ])?,
        1 => u.arbitrary()?,
        _ => u.int_in_range(-1500..=1500)? as f64 / 1000.0,
    })
}

/// A positive number in sane jobs (scales, values, radii), anything otherwise.
fn gen_pos(u: &mut Unstructured<'_>) -> arbitrary::Result<f64> {
    if !wild(u)? {
        return Ok(u.int_in_range(1..=3000)? as f64 / 1000.0);
    }
    gen_f64(u)
}

fn gen_vec3(u: &mut Unstructured<'_>) -> arbitrary::Result<Value> {
    Ok(json!([gen_f64(u)?, gen_f64(u)?, gen_f64(u)?]))
}

fn gen_index(u: &mut Unstructured<'_>, n: usize) -> arbitrary::Result<Value> {
    if !wild(u)? {
        return Ok(json!(u.int_in_range(0..=n - 1)?));
    }
    Ok(match u.int_in_range(0..=15)? {
        0 => json!(*u.choose(&[
            u64::MAX,
            u32::MAX as u64,
            u32::MAX as u64 + 1,
            1u64 << 53,
            i64::MAX as u64,
            n as u64,
        ])?),
        1 => json!(-1),
        2 => json!(n - 1),
        _ => json!(u.int_in_range(0..=n - 1)?),
    })
}

fn gen_indices(u: &mut Unstructured<'_>, n: usize) -> arbitrary::Result<Value> {
    if u.ratio(1, 20)? {
        return Ok(json!((0..n).collect::<Vec<_>>()));
    }
    let k = u.int_in_range(0..=8)?;
    let v: Vec<Value> = (0..k).map(|_| gen_index(u, n)).collect::<Result<_, _>>()?;
    Ok(Value::Array(v))
}

fn gen_name(u: &mut Unstructured<'_>) -> arbitrary::Result<Value> {
    if !wild(u)? && u.ratio(9, 10)? {
        return Ok(json!(
            *u.choose(&["neck", "top", "ear", "bottom", "a b", "é😀"])?
        ));
    }
    Ok(match u.int_in_range(0..=7)? {
        0 => json!("x".repeat(LONG)),
        1 => json!("é".repeat(u.int_in_range(1..=40_000)?)),
        2 => json!(""),
        3 => json!("\u{0}\r\n\t{}'\"\\ 😀"),
        4 => json!(65535usize),
        5 => json!("w".repeat(*u.choose(&[65_534usize, 65_535, 65_536, 65_537])?)),
        _ => json!(*u.choose(&["neck", "top", "ear", "bottom", "a b"])?),
    })
}

fn gen_curve(u: &mut Unstructured<'_>, fx: &Fixture) -> arbitrary::Result<Value> {
    let nv = fx.sphere.positions.len();
    let nf = fx.sphere.faces.len();
    let mut m = serde_json::Map::new();
    let k = if wild(u)? && u.ratio(1, 10)? { 2 } else { 1 };
    let last = if wild(u)? { 3 } else { 2 };
    for _ in 0..k {
        match u.int_in_range(0..=last)? {
            0 => {
                m.insert(
                    "plane".into(),
                    json!({"origin": gen_vec3(u)?, "normal": gen_vec3(u)?}),
                );
            }
            1 => {
                m.insert("path".into(), gen_indices(u, nv)?);
                if u.ratio(1, 2)? {
                    m.insert("closed".into(), json!(u.arbitrary::<bool>()?));
                }
            }
            2 => {
                let k = u.int_in_range(0..=6)?;
                let mut pts = Vec::new();
                let mut face = u.int_in_range(0..=nf - 1)?;
                for _ in 0..k {
                    if u.ratio(1, 3)? {
                        face = u.int_in_range(0..=nf - 1)?;
                    }
                    let f = if u.ratio(1, 20)? {
                        gen_index(u, nf)?
                    } else {
                        json!(face)
                    };
                    let bary = if u.ratio(1, 2)? {
                        let a = u.int_in_range(0..=100)? as f64 / 100.0;
                        let b = u.int_in_range(0..=100)? as f64 / 100.0 * (1.0 - a);
                        json!([a, b, 1.0 - a - b])
                    } else {
                        gen_vec3(u)?
                    };
                    pts.push(json!({"face": f, "bary": bary}));
                }
                m.insert("points".into(), Value::Array(pts));
            }
            _ => {
                m.insert("closed".into(), json!(true));
            }
        }
    }
    Ok(Value::Object(m))
}

fn gen_region(
    u: &mut Unstructured<'_>,
    fx: &Fixture,
    allow_vertices: bool,
) -> arbitrary::Result<Value> {
    let nv = fx.sphere.positions.len();
    let nf = fx.sphere.faces.len();
    let mut m = serde_json::Map::new();
    let k = if wild(u)? && u.ratio(1, 10)? { 2 } else { 1 };
    let last = if wild(u)? { 6 } else { 4 };
    for _ in 0..k {
        match u.int_in_range(0..=last)? {
            0 => {
                m.insert("faces".into(), gen_indices(u, nf)?);
            }
            1 => {
                let f = if !wild(u)? {
                    "ear.txt"
                } else {
                    *u.choose(&[
                        "ear.txt",
                        "bad.txt",
                        "huge.txt",
                        "empty.txt",
                        "crlf.txt",
                        "long.txt",
                        "missing.txt",
                        "",
                        ".",
                        "/",
                    ])?
                };
                m.insert("faces_file".into(), json!(f));
            }
            2 => {
                m.insert(
                    "sphere".into(),
                    json!({"center": gen_vec3(u)?, "radius": gen_pos(u)?}),
                );
            }
            3 => {
                m.insert(
                    "box".into(),
                    json!({"min": gen_vec3(u)?, "max": gen_vec3(u)?}),
                );
            }
            4 => {
                m.insert("group".into(), gen_name(u)?);
            }
            5 if allow_vertices || u.ratio(1, 10)? => {
                m.insert("vertices".into(), gen_indices(u, nv)?);
            }
            _ => {}
        }
    }
    Ok(Value::Object(m))
}

fn gen_solver(u: &mut Unstructured<'_>) -> arbitrary::Result<Value> {
    let mut m = serde_json::Map::new();
    let strings: &[(&str, &[&str])] = &[
        ("backend", &["auto", "cpu", "gpu", "tpu", ""]),
        ("multipliers", &["per_kind", "per_constraint", "x"]),
        ("regulariser", &["area", "uniform", "x"]),
        ("curvature_target", &["scaled", "literal", "x"]),
        ("volume_share", &["area", "tetrahedra", "x"]),
        ("acceleration", &["auto", "anderson", "none", "x"]),
    ];
    for (key, values) in strings {
        if u.ratio(1, 4)? {
            let v = if wild(u)? {
                *u.choose(values)?
            } else {
                values[0]
            };
            m.insert((*key).into(), json!(v));
        }
    }
    for key in ["tolerance", "scale_threshold"] {
        if u.ratio(1, 3)? {
            m.insert(key.into(), json!(gen_pos(u)?));
        }
    }
    for key in ["max_iterations", "fine_tune_iterations"] {
        if u.ratio(1, 4)? {
            m.insert(key.into(), gen_index(u, 100)?);
        }
    }
    if u.ratio(1, 3)? {
        let mut w = serde_json::Map::new();
        for key in ["k_f", "k_m", "k_l", "k_d", "k_r", "k_p"] {
            if u.ratio(1, 2)? {
                w.insert(key.into(), json!(gen_pos(u)?));
            }
        }
        m.insert("weights".into(), Value::Object(w));
    }
    Ok(Value::Object(m))
}

fn gen_job_value(u: &mut Unstructured<'_>, fx: &Fixture) -> arbitrary::Result<Value> {
    let sane = u.ratio(2, 3)?;
    SANE.with(|s| s.set(sane));
    let mut root = serde_json::Map::new();
    let meshes = [
        "icosphere.obj",
        "open.obj",
        "flat.obj",
        "x.stl",
        "",
        "a/b.ply",
    ];
    let mesh = if wild(u)? {
        *u.choose(&meshes)?
    } else {
        *u.choose(&meshes[..2])?
    };
    root.insert("mesh".into(), json!(mesh));
    if u.ratio(1, 5)? {
        root.insert(
            "output".into(),
            json!(*u.choose(&["out.obj", "", "icosphere.obj", "o/p.ply"])?),
        );
    }
    let kinds = ["length", "area", "volume", "Length", "mass"];
    let mut cons = Vec::new();
    for _ in 0..u.int_in_range(0..=4)? {
        let mut c = serde_json::Map::new();
        let kind = if wild(u)? && u.ratio(1, 30)? {
            *u.choose(&kinds)?
        } else {
            *u.choose(&kinds[..3])?
        };
        c.insert("kind".into(), json!(kind));
        if u.ratio(1, 2)? {
            c.insert("name".into(), gen_name(u)?);
        }
        let wrong = wild(u)? && u.ratio(1, 15)?;
        if (kind == "length") != wrong {
            c.insert("curve".into(), gen_curve(u, fx)?);
        }
        if (kind == "area") != wrong {
            c.insert("region".into(), gen_region(u, fx, false)?);
        }
        match u.int_in_range(0..=3)? {
            0 => {}
            1 => {
                c.insert("scale".into(), json!(gen_pos(u)?));
            }
            2 => {
                c.insert("value".into(), json!(gen_pos(u)?));
            }
            _ if wild(u)? => {
                c.insert("scale".into(), json!(gen_f64(u)?));
                c.insert("value".into(), json!(gen_f64(u)?));
            }
            _ => {}
        }
        cons.push(Value::Object(c));
    }
    root.insert("constraint".into(), Value::Array(cons));
    let mut handles = Vec::new();
    for _ in 0..u.int_in_range(0..=2)? {
        let mut h = serde_json::Map::new();
        if u.ratio(1, 2)? {
            h.insert("region".into(), gen_region(u, fx, true)?);
        } else {
            h.insert(
                "vertices".into(),
                gen_indices(u, fx.sphere.positions.len())?,
            );
        }
        if u.ratio(1, 2)? {
            h.insert("translate".into(), gen_vec3(u)?);
        }
        handles.push(Value::Object(h));
    }
    root.insert("handle".into(), Value::Array(handles));
    let mut curv = Vec::new();
    for _ in 0..u.int_in_range(0..=2)? {
        curv.push(json!({"region": gen_region(u, fx, false)?, "scale": gen_pos(u)?}));
    }
    root.insert("curvature".into(), Value::Array(curv));
    if u.ratio(1, 3)? {
        root.insert("solver".into(), gen_solver(u)?);
    }
    Ok(Value::Object(root))
}

/// A generated job as text: `J` + JSON or `T` + TOML (the first byte says which), text
/// mutations now and then.
fn generated_job(u: &mut Unstructured<'_>, fx: &Fixture) -> arbitrary::Result<Vec<u8>> {
    let v = gen_job_value(u, fx)?;
    let mut text = if u.ratio(1, 2)? {
        match toml::to_string(&v) {
            Ok(t) => format!("T{t}"),
            Err(_) => format!("J{v}"),
        }
    } else {
        format!("J{v}")
    }
    .into_bytes();
    if u.ratio(1, 4)? {
        let (tag, body) = text.split_at(1);
        let body = mutate(u, body, &[body.to_vec()], "job_build")?;
        text = [tag, &body].concat();
    }
    Ok(text)
}

// ---------------------------------------------------------------------------------------
// The fixed meshes (job_build) and scratch files
// ---------------------------------------------------------------------------------------

struct Fixture {
    sphere: Mesh,
    open: Mesh,
    flat: Mesh,
    job_dir: PathBuf,
}

/// Icosphere (subdivision level 2: 162 vertices, 320 faces) with groups top, bottom, ear.
fn icosphere() -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut p: Vec<DVec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|v| DVec3::from_array(*v).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..2 {
        let mut mid = std::collections::HashMap::new();
        let mut nf = Vec::new();
        for t in &f {
            let mut m = [0u32; 3];
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                m[k] = *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                    p.push(((p[a as usize] + p[b as usize]) / 2.0).normalize());
                    (p.len() - 1) as u32
                });
            }
            nf.push([t[0], m[0], m[2]]);
            nf.push([t[1], m[1], m[0]]);
            nf.push([t[2], m[2], m[1]]);
            nf.push(m);
        }
        f = nf;
    }
    let centroid = |t: &[u32; 3]| t.iter().map(|&v| p[v as usize]).sum::<DVec3>() / 3.0;
    let group = |name: &str, keep: &dyn Fn(DVec3) -> bool| FaceGroup {
        name: name.into(),
        faces: (0..f.len()).filter(|&i| keep(centroid(&f[i]))).collect(),
    };
    let groups = vec![
        group("top", &|c| c.z > 0.5),
        group("bottom", &|c| c.z < -0.5),
        group("ear", &|c| c.x > 0.8),
    ];
    Mesh {
        positions: p.clone(),
        faces: f.clone(),
        groups,
    }
}

fn fixture() -> &'static Fixture {
    static FX: OnceLock<Fixture> = OnceLock::new();
    FX.get_or_init(|| {
        let sphere = icosphere();
        // Open: the faces of group "top" removed (group indices renumbered).
        let mut open = sphere.clone();
        let top: std::collections::HashSet<usize> =
            sphere.groups[0].faces.iter().copied().collect();
        let mut new_index = vec![usize::MAX; sphere.faces.len()];
        open.faces.clear();
        for (i, t) in sphere.faces.iter().enumerate() {
            if !top.contains(&i) {
                new_index[i] = open.faces.len();
                open.faces.push(*t);
            }
        }
        for g in &mut open.groups {
            g.faces = g
                .faces
                .iter()
                .filter(|&&i| new_index[i] != usize::MAX)
                .map(|&i| new_index[i])
                .collect();
        }
        // Flat: z squashed to 0 (zero volume, everything coplanar).
        let mut flat = sphere.clone();
        for p in &mut flat.positions {
            p.z = 0.0;
        }
        let job_dir = scratch_dir().join("job");
        std::fs::create_dir_all(&job_dir).unwrap();
        let files: &[(&str, String)] = &[
            ("ear.txt", "0 1 2 3\n10 11\n".into()),
            ("bad.txt", "1 2 x -3 1e3".into()),
            (
                "huge.txt",
                "18446744073709551615 4294967295 99999999999999999999999 319".into(),
            ),
            ("empty.txt", String::new()),
            ("crlf.txt", "5\r6\r\n7\r".into()),
            ("long.txt", "1 ".repeat(100_000)),
        ];
        for (name, text) in files {
            std::fs::write(job_dir.join(name), text).unwrap();
        }
        Fixture {
            sphere,
            open,
            flat,
            job_dir,
        }
    })
}

// ---------------------------------------------------------------------------------------
// The targets
// ---------------------------------------------------------------------------------------

thread_local! {
    static FILE_COUNTER: Cell<u64> = const { Cell::new(0) };
}

/// read_mesh on the bytes (written to a scratch file with the extension), then what every
/// command does next with a mesh: topology and validation.
fn read_mesh_bytes(bytes: &[u8], ext: &str) -> bool {
    let n = FILE_COUNTER.with(|c| {
        c.set(c.get() + 1);
        c.get()
    });
    let tid = format!("{:?}", std::thread::current().id());
    let tid: String = tid.chars().filter(|c| c.is_ascii_digit()).collect();
    let path = scratch_dir().join(format!("in-{tid}-{}.{ext}", n % 2));
    std::fs::write(&path, bytes).expect("write scratch input");
    let ok = match io::read_mesh(&path) {
        Ok(mesh) => {
            let topo = Topology::build(&mesh);
            // Accepted = readable; validation may still refuse the mesh.
            let valid = validate::validate(&mesh, &topo, &path).is_ok();
            let x = &mesh.positions;
            let _ = mesh.signed_volume(x);
            let _ = mesh.bbox_diagonal(x);
            if valid && mesh.num_faces() <= 5000 {
                select_on(&mesh, &path);
            }
            true
        }
        Err(e) => {
            let _ = e.to_string();
            false
        }
    };
    let _ = std::fs::remove_file(&path);
    ok
}

/// The selections on a mesh that passed validation (adversarial topology and geometry):
/// one job per kind of selection through `Problem::build`, and the report rows and table.
fn select_on(mesh: &Mesh, path: &Path) {
    let x = &mesh.positions;
    let (c, d) = (x[0], mesh.bbox_diagonal(x));
    if !c.is_finite() || !d.is_finite() {
        return;
    }
    let c = c.to_array();
    let last = mesh.num_vertices() - 1;
    let jobs = [
        json!({"kind": "length", "curve": {"plane": {"origin": c, "normal": [0.0, 0.0, 1.0]}}}),
        json!({"kind": "length", "curve": {"plane": {"origin": c, "normal": [1.0, 1e-9, 0.0]}}}),
        json!({"kind": "length", "curve": {"path": [0, last], "closed": true}}),
        json!({"kind": "length", "curve": {"points": [
            {"face": 0, "bary": [0.2, 0.3, 0.5]}, {"face": 0, "bary": [0.0, 0.0, 1.0]}]}}),
        json!({"kind": "area", "region": {"sphere": {"center": c, "radius": d / 3.0}}}),
        json!({"kind": "area", "region": {"faces": [0]}, "scale": 2.0}),
        json!({"kind": "volume", "scale": 1.5}),
    ];
    for (i, con) in jobs.into_iter().enumerate() {
        let mut job = json!({"mesh": "m.obj", "constraint": [con]});
        if i == 6 {
            job["handle"] = json!([{"vertices": [0], "translate": [0.0, 0.1, 0.0]}]);
            job["curvature"] = json!([{"region": {"faces": [0]}, "scale": 2.0}]);
        }
        let Ok(job) = Job::from_str(&job.to_string(), JobFormat::Json, Path::new("."), "fuzz")
        else {
            continue;
        };
        if let Ok(p) = Problem::build(&job, mesh.clone(), path) {
            let rows = constraint_rows(&p, &p.mesh.positions, 1e-5);
            let _ = table(&rows);
            let _ = explain_miss(&p, &rows, None);
        }
    }
}

fn run_obj(b: &[u8], _: &Fixture) -> bool {
    read_mesh_bytes(b, "obj")
}
fn run_ply(b: &[u8], _: &Fixture) -> bool {
    read_mesh_bytes(b, "ply")
}
fn run_stl(b: &[u8], _: &Fixture) -> bool {
    read_mesh_bytes(b, "stl")
}

/// Job::from_str and what the commands derive from a job without its mesh.
fn run_job(text: &str, format: JobFormat, dir: &Path) -> Option<Job> {
    let job = Job::from_str(text, format, dir, "fuzz-job").ok()?;
    let _ = job.mesh_path();
    let _ = job.output_path();
    for i in 0..job.spec.constraint.len() {
        let _ = job.constraint_label(i);
    }
    let _ = Options::from_spec(&job.spec.solver);
    Some(job)
}

fn run_job_toml(b: &[u8], fx: &Fixture) -> bool {
    run_job(&String::from_utf8_lossy(b), JobFormat::Toml, &fx.job_dir).is_some()
}
fn run_job_json(b: &[u8], fx: &Fixture) -> bool {
    run_job(&String::from_utf8_lossy(b), JobFormat::Json, &fx.job_dir).is_some()
}

/// Input: a job (seed files by extension, generated ones tagged `J`/`T`), built on the
/// fixed mesh it names (icosphere/open/flat), then `measure`: rows, table, explanation.
fn run_job_build(b: &[u8], fx: &Fixture) -> bool {
    let (format, body) = match b.first() {
        Some(b'J') => (JobFormat::Json, &b[1..]),
        Some(b'T') => (JobFormat::Toml, &b[1..]),
        _ if b.trim_ascii_start().starts_with(b"{") => (JobFormat::Json, b),
        _ => (JobFormat::Toml, b),
    };
    let text = String::from_utf8_lossy(body);
    let Some(job) = run_job(&text, format, &fx.job_dir) else {
        return false;
    };
    let mesh_path = job.mesh_path();
    let name = job.spec.mesh.to_string_lossy();
    let mesh = if name.contains("open") {
        fx.open.clone()
    } else if name.contains("flat") {
        fx.flat.clone()
    } else {
        fx.sphere.clone()
    };
    let problem = match Problem::build(&job, mesh, &mesh_path) {
        Ok(p) => p,
        Err(e) => {
            let _ = e.to_string();
            return false;
        }
    };
    let options = Options::from_spec(&job.spec.solver);
    let x = &problem.mesh.positions;
    let rows = constraint_rows(&problem, x, options.tolerance);
    let _ = table(&rows);
    let _ = explain_miss(&problem, &rows, None);
    let _ = serde_json::to_string(&rows);
    let _ = max_error(&problem, x);
    for c in &problem.constraints {
        let _ = c.residual(&problem.mesh, x);
    }
    true
}

const TARGETS: &[Target] = &[
    Target {
        name: "obj",
        ext: "obj",
        slot: 0,
        run: run_obj,
    },
    Target {
        name: "ply_ascii",
        ext: "ply",
        slot: 1,
        run: run_ply,
    },
    Target {
        name: "ply_binary",
        ext: "ply",
        slot: 2,
        run: run_ply,
    },
    Target {
        name: "stl_ascii",
        ext: "stl",
        slot: 3,
        run: run_stl,
    },
    Target {
        name: "stl_binary",
        ext: "stl",
        slot: 4,
        run: run_stl,
    },
    Target {
        name: "job_toml",
        ext: "toml",
        slot: 5,
        run: run_job_toml,
    },
    Target {
        name: "job_json",
        ext: "json",
        slot: 6,
        run: run_job_json,
    },
    Target {
        name: "job_build",
        ext: "job",
        slot: 7,
        run: run_job_build,
    },
];

/// Not a fuzz target: allocates 100 MiB whatever the input, which the guard must catch.
fn run_alloc_hog(_: &[u8], _: &Fixture) -> bool {
    let v = vec![1u8; 100 << 20];
    std::hint::black_box(&v);
    true
}

const SELF_TEST: Target = Target {
    name: "selftest",
    ext: "bin",
    slot: 8,
    run: run_alloc_hog,
};

/// The memory guard works: an input of 4 bytes that makes its thread hold 100 MiB fails.
#[test]
fn guard_catches_memory_blowup() {
    install_panic_hook();
    let _ = target("obj");
    let r = catch_unwind(AssertUnwindSafe(|| {
        exec(&SELF_TEST, fixture(), b"tiny", &mut Stats::default())
    }));
    let err = r.expect_err("the memory guard did not fire");
    let msg = err.downcast_ref::<String>().cloned().unwrap_or_default();
    assert!(msg.contains("made its thread hold"), "{msg}");
}

fn target(name: &str) -> &'static Target {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        let mut r = RUNNING.lock().unwrap();
        // One slot per target, and one for the guard's self-test.
        for t in TARGETS.iter().chain([&SELF_TEST]) {
            r.push(Running {
                target: t.name,
                ext: t.ext,
                input: Arc::new(Vec::new()),
                started: Instant::now(),
            });
        }
    });
    TARGETS.iter().find(|t| t.name == name).unwrap()
}

#[test]
fn obj() {
    fuzz(target("obj"));
}

#[test]
fn ply_ascii() {
    fuzz(target("ply_ascii"));
}

#[test]
fn ply_binary() {
    fuzz(target("ply_binary"));
}

#[test]
fn stl_ascii() {
    fuzz(target("stl_ascii"));
}

#[test]
fn stl_binary() {
    fuzz(target("stl_binary"));
}

#[test]
fn job_toml() {
    fuzz(target("job_toml"));
}

#[test]
fn job_json() {
    fuzz(target("job_json"));
}

#[test]
fn job_build() {
    fuzz(target("job_build"));
}

// ---------------------------------------------------------------------------------------
// Known bugs: deterministic reproducers (un-ignore when fixed)
// ---------------------------------------------------------------------------------------

/// Replays `tests/fuzz-corpus/regressions/<file>` through `target` under the guards,
/// strictly.
fn replay_known(target_name: &str, file: &str) {
    install_panic_hook();
    start_watchdog();
    let t = target(target_name);
    let input = std::fs::read(corpus_dir("regressions").join(file)).unwrap();
    let mut stats = Stats::default();
    QUIET.with(|q| q.set(false));
    REPLAY.with(|r| r.set(true));
    // Strict: a known panic fails here.
    let v = exec(t, fixture(), &input, &mut stats);
    assert!(
        !matches!(v, Verdict::Known(_)),
        "known bug still present: {v:?} on {file}"
    );
}

/// A binary PLY element without properties and a count of 2^64 - 1 made `read_mesh` loop
/// for ever (fixed: such an element holds no bytes and is skipped). Were it back, the
/// watchdog would end the test process after 5 s (exit 101) with the input printed.
#[test]
fn regression_ply_binary_empty_element_hang() {
    replay_known("ply_binary", "ply-binary-empty-element-hang.ply");
}

/// A constraint name of 65,536+ bytes panicked in `report::table` (fixed: names are
/// padded by hand).
#[test]
fn regression_report_table_long_name() {
    replay_known("job_build", "report-table-long-name.toml");
}
