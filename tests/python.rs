//! The Python package's tests (python/tests), run as part of `cargo test`:
//! build the wheel with maturin, install it into a folder of its own (`pip
//! install --target`), run pytest with that folder first on `PYTHONPATH` and
//! `METRICDEFORM_CLI` naming this build's CLI.
//!
//! Needs `maturin` and `python3` with pytest and numpy (`python3 -m pip install
//! maturin pytest numpy trimesh`); without them the test says so and passes,
//! unless `REQUIRE_PYTHON=1` (as in CI, `.ci/run`) makes it fail.

use std::path::PathBuf;
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Runs `cmd`; its output on failure.
fn run(cmd: &mut Command) -> Result<String, String> {
    let shown = format!("{cmd:?}");
    match cmd.output() {
        Ok(out) if out.status.success() => Ok(String::from_utf8_lossy(&out.stdout).into_owned()),
        Ok(out) => Err(format!(
            "{shown} failed ({}):\n{}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )),
        Err(e) => Err(format!("{shown}: {e}")),
    }
}

/// What is missing to run the Python tests, if anything.
fn missing_tools() -> Option<String> {
    if let Err(e) = run(Command::new("maturin").arg("--version")) {
        return Some(format!("maturin is not installed ({e})"));
    }
    if let Err(e) = run(Command::new("python3").args(["-c", "import numpy, pytest"])) {
        return Some(format!(
            "python3 with numpy and pytest is not available ({e})"
        ));
    }
    None
}

fn required() -> bool {
    std::env::var_os("REQUIRE_PYTHON").is_some_and(|v| v == "1")
}

#[test]
fn python_package_passes_its_tests() {
    if let Some(why) = missing_tools() {
        if required() {
            panic!("REQUIRE_PYTHON=1 but {why}");
        }
        eprintln!("skipping the Python package's tests: {why}");
        return;
    }
    let work = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("python");
    let _ = std::fs::remove_dir_all(&work);
    std::fs::create_dir_all(&work).unwrap();
    let wheels = work.join("wheels");
    run(Command::new("maturin")
        .args(["build", "--release", "--quiet", "-m"])
        .arg(root().join("python").join("Cargo.toml"))
        .arg("-o")
        .arg(&wheels)
        .current_dir(root()))
    .unwrap_or_else(|e| panic!("building the wheel: {e}"));
    let wheel = std::fs::read_dir(&wheels)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "whl"))
        .expect("maturin wrote a wheel");
    // Installed into a folder of its own (no virtual environment, which some
    // system Pythons cannot make without an extra package), put first on the
    // path; numpy, pytest and trimesh come from the system's site-packages.
    let site = work.join("site");
    run(Command::new("python3")
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-index",
            "--target",
        ])
        .arg(&site)
        .arg(&wheel))
    .unwrap_or_else(|e| panic!("installing the wheel: {e}"));
    // From a folder outside the source tree, so that the installed package is
    // the one imported.
    let out = run(Command::new("python3")
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
        .arg(root().join("python").join("tests"))
        .env("PYTHONPATH", &site)
        .env("METRICDEFORM_CLI", env!("CARGO_BIN_EXE_metricdeform"))
        .current_dir(&work))
    .unwrap_or_else(|e| panic!("pytest: {e}"));
    eprintln!("{out}");
    assert!(out.contains(" passed"), "{out}");
    // In CI every test runs (trimesh installed, the CLI given).
    assert!(
        !required() || !out.contains(" skipped"),
        "REQUIRE_PYTHON=1 but some Python tests skipped: {out}"
    );
}
