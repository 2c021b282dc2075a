//! Output files: written whole or not at all, a run's outputs as one set, and
//! nothing left behind on an interrupt (contract: "Output is written atomically",
//! "both or neither", "SIGINT/SIGTERM stop a run promptly").
//!
//! * [`stage`] writes a file's bytes to a temporary `.<name>.tmp-<pid>-<n>` beside
//!   its destination and syncs it. Every failure a write can meet (no directory, no
//!   permission, a full disk, `/proc`) happens here, before any destination changes.
//! * [`commit`] renames every staged file over its destination. If a rename fails,
//!   the destinations already renamed get back what they held before (kept as
//!   hard links, or copies, until the set is complete): a run leaves all its
//!   outputs or none.
//! * While a temporary file exists it is registered. [`install_interrupt_handler`]
//!   catches SIGINT and SIGTERM, removes the registered files and exits 130 or 143
//!   at once, even inside a long solve; destinations keep their previous contents.
//! * A temporary file whose process is gone (killed with SIGKILL) is removed by the
//!   next [`stage`] into the same directory for the same name.

use crate::error::{Error, Result};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard};

/// Temporary files and directories that exist now, removed on an interrupt.
static TEMPORARIES: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());
/// The signal that interrupted the run, 0 while none did.
static INTERRUPTED: AtomicI32 = AtomicI32::new(0);
static COUNTER: AtomicUsize = AtomicUsize::new(0);
/// Whether a [`commit`] has put files in place (for the interrupt message).
static COMMITTED: AtomicBool = AtomicBool::new(false);

fn temporaries() -> MutexGuard<'static, Vec<PathBuf>> {
    TEMPORARIES.lock().unwrap_or_else(|e| e.into_inner())
}

fn register(p: &Path) {
    temporaries().push(p.to_path_buf());
}

fn unregister(p: &Path) {
    temporaries().retain(|q| q != p);
}

/// A file written to its temporary path, not yet at its destination. Dropped
/// without [`commit`], it removes its temporary file.
#[derive(Debug)]
pub struct Staged {
    tmp: PathBuf,
    dest: PathBuf,
}

impl Staged {
    /// Where [`commit`] puts the file.
    pub fn destination(&self) -> &Path {
        &self.dest
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        let _ = fs::remove_file(&self.tmp);
        unregister(&self.tmp);
    }
}

fn io_err(path: &Path, source: std::io::Error) -> Error {
    Error::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// `.<name>.tmp-<pid>-<n>`, beside `dest`.
fn temporary_path(dest: &Path) -> Result<PathBuf> {
    let name = dest
        .file_name()
        .ok_or_else(|| Error::bad(format!("{}: the path has no file name", dest.display())))?;
    Ok(parent_dir(dest).join(format!(
        ".{}.tmp-{}-{}",
        name.to_string_lossy(),
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    )))
}

/// Removes `.<name>.tmp-<pid>-<n>` files of `dest` whose process no longer runs
/// (Linux: no `/proc/<pid>`; elsewhere nothing is removed).
fn remove_stale_temporaries(dest: &Path) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Some(name) = dest.file_name() else { return };
    let prefix = format!(".{}.tmp-", name.to_string_lossy());
    let Ok(entries) = fs::read_dir(parent_dir(dest)) else {
        return;
    };
    for e in entries.flatten() {
        let file_name = e.file_name();
        let Some(rest) = file_name.to_str().and_then(|s| s.strip_prefix(&prefix)) else {
            continue;
        };
        let Some((pid, n)) = rest.split_once('-') else {
            continue;
        };
        let (Ok(pid), true) = (pid.parse::<u32>(), n.bytes().all(|b| b.is_ascii_digit())) else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let path = e.path();
            if fs::remove_file(&path).is_ok() {
                log::info!("removed {} (left by a killed run)", path.display());
            }
        }
    }
}

/// Writes `data` to a synced temporary file beside `dest`; [`commit`] moves it
/// there. `dest` itself is not touched.
pub fn stage(dest: &Path, data: &[u8]) -> Result<Staged> {
    if dest.is_dir() {
        return Err(Error::bad(format!(
            "{} is a directory: give a file name",
            dest.display()
        )));
    }
    remove_stale_temporaries(dest);
    let tmp = temporary_path(dest)?;
    register(&tmp);
    // From here on, dropping `staged` removes the temporary file.
    let staged = Staged {
        tmp,
        dest: dest.to_path_buf(),
    };
    let written = (|| -> std::io::Result<()> {
        let mut file = fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&staged.tmp)?;
        file.write_all(data)?;
        file.sync_all()
    })();
    written.map_err(|e| io_err(dest, e))?;
    Ok(staged)
}

/// Moves every staged file to its destination: all of them, or, when one rename
/// fails, none (destinations renamed before it get their previous contents back).
/// Refused after an interrupt.
pub fn commit(staged: Vec<Staged>) -> Result<()> {
    // Holding the registry keeps the interrupt handler out until the set is
    // complete or rolled back.
    let guard = temporaries();
    if INTERRUPTED.load(Ordering::SeqCst) != 0 {
        drop(guard);
        return Err(Error::Internal(
            "interrupted before the outputs were written".into(),
        ));
    }
    let mut done: Vec<(&Path, Option<PathBuf>)> = Vec::new();
    let mut failure = None;
    for s in &staged {
        let backup = match keep_previous(&s.dest) {
            Ok(b) => b,
            Err(e) => {
                failure = Some(io_err(&s.dest, e));
                break;
            }
        };
        if let Err(e) = fs::rename(&s.tmp, &s.dest) {
            if let Some(b) = backup {
                let _ = fs::remove_file(b);
            }
            failure = Some(io_err(&s.dest, e));
            break;
        }
        done.push((&s.dest, backup));
    }
    match failure {
        None => {
            for (dest, backup) in done {
                if let Some(b) = backup {
                    let _ = fs::remove_file(b);
                }
                // Make the rename durable (best effort; not possible everywhere).
                #[cfg(unix)]
                if let Ok(d) = fs::File::open(parent_dir(dest)) {
                    let _ = d.sync_all();
                }
                log::debug!("wrote {}", dest.display());
            }
            COMMITTED.store(true, Ordering::SeqCst);
            drop(guard);
            for s in &staged {
                unregister(&s.tmp);
            }
            Ok(())
        }
        Some(e) => {
            for (dest, backup) in done.into_iter().rev() {
                match backup {
                    Some(b) => {
                        let _ = fs::rename(b, dest);
                    }
                    None => {
                        let _ = fs::remove_file(dest);
                    }
                }
            }
            drop(guard);
            Err(e)
        }
    }
}

/// A second name (hard link, else a copy) for what `dest` holds now, so that a
/// failed set can put it back. None when `dest` does not exist.
fn keep_previous(dest: &Path) -> std::io::Result<Option<PathBuf>> {
    if fs::symlink_metadata(dest).is_err() {
        return Ok(None);
    }
    let backup = temporary_path(dest).map_err(|e| std::io::Error::other(e.to_string()))?;
    if fs::hard_link(dest, &backup).is_err() {
        fs::copy(dest, &backup)?;
    }
    Ok(Some(backup))
}

/// Writes one file atomically: [`stage`] then [`commit`].
pub fn write_atomic(dest: &Path, data: &[u8]) -> Result<()> {
    commit(vec![stage(dest, data)?])
}

/// A temporary directory removed on drop and on an interrupt (the demo's files).
#[derive(Debug)]
pub struct TempDir(PathBuf);

impl TempDir {
    /// Creates `<system temp>/<prefix>-<pid>`.
    pub fn new(prefix: &str) -> Result<TempDir> {
        let dir = std::env::temp_dir().join(format!("{prefix}-{}", std::process::id()));
        register(&dir);
        let t = TempDir(dir);
        fs::create_dir_all(&t.0).map_err(|e| io_err(&t.0, e))?;
        Ok(t)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
        unregister(&self.0);
    }
}

/// Best-effort "same file": equal canonical paths, the parent directory
/// canonicalised when the file does not exist yet.
pub fn same_file(a: &Path, b: &Path) -> bool {
    fn canon(p: &Path) -> Option<PathBuf> {
        if let Ok(c) = fs::canonicalize(p) {
            return Some(c);
        }
        let name = p.file_name()?;
        Some(fs::canonicalize(parent_dir(p)).ok()?.join(name))
    }
    match (canon(a), canon(b)) {
        (Some(x), Some(y)) => x == y,
        _ => a == b,
    }
}

/// Whether SIGINT or SIGTERM has arrived (the handler exits the process right
/// after, so a caller only sees this in the window before the exit).
pub fn interrupted() -> bool {
    INTERRUPTED.load(Ordering::SeqCst) != 0
}

/// Catches SIGINT and SIGTERM: removes the registered temporary files, says so
/// on stderr and exits with 128 + the signal (130, 143) without running exit
/// handlers, so no GPU driver or solver thread is torn down under a running
/// thread. A commit in progress finishes (or rolls back) first. Unix only; a
/// no-op elsewhere.
pub fn install_interrupt_handler() -> Result<()> {
    #[cfg(unix)]
    {
        use signal_hook::consts::{SIGINT, SIGTERM};
        let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM])
            .map_err(|e| Error::Internal(format!("cannot install the signal handler: {e}")))?;
        std::thread::Builder::new()
            .name("interrupt".into())
            .spawn(move || {
                if let Some(sig) = signals.forever().next() {
                    INTERRUPTED.store(sig, Ordering::SeqCst);
                    let list = temporaries();
                    for p in list.iter() {
                        if p.is_dir() {
                            let _ = fs::remove_dir_all(p);
                        } else {
                            let _ = fs::remove_file(p);
                        }
                    }
                    let name = if sig == SIGINT { "SIGINT" } else { "SIGTERM" };
                    let what = if COMMITTED.load(Ordering::SeqCst) {
                        "after its outputs were written"
                    } else {
                        "no output of this run was written"
                    };
                    let _ = writeln!(std::io::stderr(), "interrupted by {name}: stopped; {what}");
                    signal_hook::low_level::exit(128 + sig);
                }
            })
            .map_err(|e| Error::Internal(format!("cannot start the signal thread: {e}")))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir() -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "metricdeform-output-test-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        fs::create_dir_all(&d).unwrap();
        d
    }

    fn names(d: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_set_is_committed_whole() {
        let d = dir();
        fs::write(d.join("a.obj"), "old a").unwrap();
        let a = stage(&d.join("a.obj"), b"new a").unwrap();
        let b = stage(&d.join("b.json"), b"new b").unwrap();
        // Staging leaves the destinations alone.
        assert_eq!(fs::read_to_string(d.join("a.obj")).unwrap(), "old a");
        commit(vec![a, b]).unwrap();
        assert_eq!(fs::read_to_string(d.join("a.obj")).unwrap(), "new a");
        assert_eq!(fs::read_to_string(d.join("b.json")).unwrap(), "new b");
        assert_eq!(names(&d), ["a.obj", "b.json"]);
        fs::remove_dir_all(d).unwrap();
    }

    /// The second rename fails (its destination became a non-empty directory
    /// after staging): the first destination gets its old contents back, a
    /// destination that did not exist is removed, no temporary file is left.
    #[test]
    fn a_failed_rename_rolls_back_the_whole_set() {
        let d = dir();
        fs::write(d.join("a.obj"), "old a").unwrap();
        let a = stage(&d.join("a.obj"), b"new a").unwrap();
        let c = stage(&d.join("c.obj"), b"new c").unwrap();
        let b = stage(&d.join("b.json"), b"new b").unwrap();
        fs::create_dir_all(d.join("b.json/x")).unwrap();
        assert!(commit(vec![a, c, b]).is_err());
        assert_eq!(fs::read_to_string(d.join("a.obj")).unwrap(), "old a");
        assert_eq!(names(&d), ["a.obj", "b.json"]);
        fs::remove_dir_all(d).unwrap();
    }

    #[test]
    fn a_dropped_stage_leaves_nothing() {
        let d = dir();
        let a = stage(&d.join("a.obj"), b"new a").unwrap();
        assert_eq!(names(&d).len(), 1);
        drop(a);
        assert!(names(&d).is_empty());
        assert!(stage(&d, b"x").is_err(), "a directory is no destination");
        fs::remove_dir_all(d).unwrap();
    }
}
