//! Memory probes of this process (Linux `/proc/self/status`), for the report
//! and the `debug` log.

/// Peak resident set size of this process in MiB (VmHWM), 0 when unknown.
pub fn peak_memory_mb() -> f64 {
    proc_status_mb("VmHWM:")
}

/// Current resident set size of this process in MiB (VmRSS), 0 when unknown.
pub fn resident_memory_mb() -> f64 {
    proc_status_mb("VmRSS:")
}

/// Memory the system can give this process without swapping (Linux
/// `MemAvailable`, `/proc/meminfo`), in bytes; `None` where unknown.
pub fn available_memory_bytes() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Hands the allocator's free memory back to the system (glibc keeps freed
/// blocks of its per-thread arenas resident; a large set-up step leaves hundreds
/// of MiB of them at a million faces), on a thread of its own: the caller
/// goes on meanwhile (at homer 1.2M each hand-back took 0.03-0.06 s of the
/// pipeline's main thread; an allocation meanwhile waits at most for its
/// arena's turn). Done here where no thread can be started. A no-op
/// elsewhere.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let spawned = std::thread::Builder::new()
            .name("free memory".into())
            .spawn(trim_free_memory);
        if let Err(e) = spawned {
            log::debug!("no thread to hand free memory back on ({e}): handed back here");
            trim_free_memory();
        }
    }
}

/// glibc's free pages handed back (`malloc_trim`), logged.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn trim_free_memory() {
    let (t, before) = (std::time::Instant::now(), resident_memory_mb());
    // SAFETY: malloc_trim only returns free pages of glibc's own arenas,
    // each under its arena's lock.
    unsafe {
        libc::malloc_trim(0);
    }
    log::debug!(
        "free memory handed back: resident {before:.0} to {:.0} MiB in {:.3} s",
        resident_memory_mb(),
        t.elapsed().as_secs_f64()
    );
}

/// Has glibc's allocator serve every block from its heaps and keep freed
/// blocks for reuse (`mallopt`: `M_MMAP_MAX` 0, `M_TRIM_THRESHOLD` 2 GiB),
/// for a process that runs the pipeline on large meshes: the binary and the
/// benches call it first thing. By default glibc maps each block of more
/// than 32 MiB afresh and unmaps it when freed, so every such vector (3
/// values a vertex at 4.3M faces: 52 MB) is new pages that the kernel
/// zeroes on first touch, in every outer iteration. [`release_free_memory`]
/// still hands free pages back between the pipeline's phases. Left as it is
/// where the user set glibc's own malloc settings (`MALLOC_MMAP_MAX_`,
/// `MALLOC_TRIM_THRESHOLD_`, `GLIBC_TUNABLES`); a no-op off glibc.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        if malloc_set_by_user() {
            return;
        }
        // SAFETY: mallopt only changes glibc's allocation parameters; blocks
        // already mapped stay valid and are unmapped when freed.
        unsafe {
            libc::mallopt(libc::M_MMAP_MAX, 0);
            libc::mallopt(libc::M_TRIM_THRESHOLD, std::ffi::c_int::MAX);
        }
    }
}

/// Whether the user set glibc's own malloc settings.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn malloc_set_by_user() -> bool {
    [
        "MALLOC_MMAP_MAX_",
        "MALLOC_TRIM_THRESHOLD_",
        "GLIBC_TUNABLES",
    ]
    .iter()
    .any(|v| std::env::var_os(v).is_some())
}

fn proc_status_mb(field: &str) -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with(field)).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|kb| kb.parse::<f64>().ok())
                    .map(|kb| kb / 1024.0)
            })
        })
        .unwrap_or(0.0)
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    /// Once freed memory is kept, a block over glibc's largest mmap
    /// threshold (32 MiB) comes from a heap: glibc's count of blocks mapped
    /// on their own does not grow while it is held. Without the setting the
    /// block is such a mapping.
    #[test]
    fn a_large_block_comes_from_a_heap_once_freed_memory_is_kept() {
        if super::malloc_set_by_user() {
            eprintln!("skipped: glibc's malloc settings are the user's here");
            return;
        }
        super::keep_freed_memory();
        // SAFETY: mallinfo2 only reads glibc's counters.
        let mapped = || unsafe { libc::mallinfo2() }.hblks;
        let before = mapped();
        let block: Vec<u8> = Vec::with_capacity(48 << 20);
        let held = mapped();
        drop(std::hint::black_box(block));
        // Another test may free a mapped block meanwhile, never map one.
        assert!(
            held <= before,
            "{held} blocks mapped on their own, {before} before"
        );
    }
}
