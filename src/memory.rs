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
/// of MiB of them at a million faces). A no-op elsewhere.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn malloc_trim(pad: usize) -> std::ffi::c_int;
        }
        // SAFETY: malloc_trim only returns free pages of glibc's own arenas.
        unsafe {
            malloc_trim(0);
        }
    }
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
