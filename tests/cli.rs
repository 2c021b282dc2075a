//! The command line of the contract: exit codes, messages, nothing written on bad
//! input, the input never modified.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn meshes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("data/meshes")
}

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_metricdeform"));
    c.env_remove("METRICDEFORM_BACKEND");
    c
}

/// Write a job into a fresh directory (with a copy of the mesh) and run `deform`.
fn deform_job(mesh: &str, job: &str, extra: &[&str]) -> (Output, tempfile::TempDir) {
    deform_job_env(mesh, job, extra, &[])
}

fn deform_job_env(
    mesh: &str,
    job: &str,
    extra: &[&str],
    env: &[(&str, &str)],
) -> (Output, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    if !mesh.is_empty() {
        std::fs::copy(meshes().join(mesh), dir.path().join(mesh)).unwrap();
    }
    let job_path = dir.path().join("job.toml");
    std::fs::write(&job_path, job).unwrap();
    let mut cmd = bin();
    cmd.arg("deform").arg(&job_path).arg("--quiet");
    if !extra.contains(&"--backend") {
        cmd.args(["--backend", "cpu"]);
    }
    for (k, v) in env {
        cmd.env(k, v);
    }
    let out = cmd.args(extra).current_dir(dir.path()).output().unwrap();
    (out, dir)
}

/// Parse a JSON file the command wrote.
fn read_json(dir: &Path, name: &str) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join(name)).unwrap()).unwrap()
}

fn files(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Exit 2, the message contains every `needle`, nothing new written, input intact.
fn assert_bad_input(mesh: &str, job: &str, needles: &[&str]) {
    let (out, dir) = deform_job(mesh, job, &["--report", "report.json"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "stderr: {stderr}");
    for n in needles {
        assert!(stderr.contains(n), "message lacks '{n}': {stderr}");
    }
    let mut expected = vec!["job.toml".to_string()];
    if !mesh.is_empty() {
        expected.push(mesh.to_string());
        let a = std::fs::read(meshes().join(mesh)).unwrap();
        let b = std::fs::read(dir.path().join(mesh)).unwrap();
        assert!(a == b, "input mesh modified");
    }
    expected.sort();
    assert_eq!(files(dir.path()), expected, "something was written");
}

#[test]
fn volume_on_open_mesh_is_refused() {
    assert_bad_input(
        "stanford-bunny.obj",
        "mesh = \"stanford-bunny.obj\"\n[[constraint]]\nkind = \"volume\"\nname = \"body\"\n",
        &["stanford-bunny.obj", "body", "boundary edges"],
    );
}

#[test]
fn non_manifold_mesh_is_refused() {
    assert_bad_input(
        "suzanne.obj",
        "mesh = \"suzanne.obj\"\n[[constraint]]\nkind = \"area\"\nregion = { faces = [0, 1] }\n",
        &["suzanne.obj", "non-manifold"],
    );
}

#[test]
fn unknown_field_is_rejected() {
    assert_bad_input("spot.obj", "mesh = \"spot.obj\"\ncolour = 3\n", &["colour"]);
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"volume\"\nwieght = 2.0\n",
        &["wieght"],
    );
}

#[test]
fn unknown_kind_is_rejected() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"lenght\"\n",
        &["lenght"],
    );
}

#[test]
fn missing_mesh_file_is_named() {
    assert_bad_input(
        "",
        "mesh = \"nowhere.obj\"\n[[constraint]]\nkind = \"volume\"\n",
        &["nowhere.obj"],
    );
}

#[test]
fn out_of_range_indices_are_named() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"area\"\nname = \"ear\"\nregion = { faces = [1, 99999] }\n",
        &["ear", "99999"],
    );
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"length\"\nname = \"seam\"\ncurve = { path = [0, 123456] }\n",
        &["seam", "123456"],
    );
}

#[test]
fn plane_missing_the_mesh_is_refused() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"length\"\nname = \"girth\"\ncurve = { plane = { origin = [0.0, 50.0, 0.0], normal = [0.0, 1.0, 0.0] } }\n",
        &["girth", "misses"],
    );
}

#[test]
fn empty_region_is_refused() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"area\"\nname = \"nothing\"\nregion = { sphere = { center = [40.0, 0.0, 0.0], radius = 0.1 } }\n",
        &["nothing", "no faces"],
    );
}

#[test]
fn nan_coordinates_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(meshes().join("spot.obj")).unwrap();
    let bad = text.replacen(
        "v 0.348799 -0.334989 -0.0832331",
        "v 0.348799 nan -0.0832331",
        1,
    );
    assert_ne!(bad, text);
    std::fs::write(dir.path().join("nan.obj"), bad).unwrap();
    std::fs::write(
        dir.path().join("job.toml"),
        "mesh = \"nan.obj\"\n[[constraint]]\nkind = \"volume\"\n",
    )
    .unwrap();
    let out = bin()
        .args(["deform", "job.toml", "--backend", "cpu", "--quiet"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("nan.obj") && stderr.contains("vertex 0"),
        "{stderr}"
    );
    assert_eq!(
        files(dir.path()),
        vec!["job.toml".to_string(), "nan.obj".to_string()]
    );
}

#[test]
fn scale_and_value_together_are_refused() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"volume\"\nname = \"v\"\nscale = 1.1\nvalue = 0.8\n",
        &["'v'", "scale", "value"],
    );
}

/// No adapter matches: `--backend gpu` is a usage error (exit 2), never a silent
/// fallback; `auto` falls back to the CPU and says so.
#[test]
fn gpu_backend_without_adapter_is_usage_error() {
    let job = "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"volume\"\n";
    let no_adapter = [("WGPU_ADAPTER_NAME", "no-such-adapter-anywhere")];
    let (out, dir) = deform_job_env("spot.obj", job, &["--backend", "gpu"], &no_adapter);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--backend gpu") && err.contains("no-such-adapter-anywhere"),
        "{err}"
    );
    assert_eq!(
        files(dir.path()),
        vec!["job.toml".to_string(), "spot.obj".to_string()]
    );
    let (out, dir) = deform_job_env(
        "spot.obj",
        job,
        &["--backend", "auto", "--report", "r.json"],
        &no_adapter,
    );
    assert_eq!(out.status.code(), Some(0));
    assert!(String::from_utf8_lossy(&out.stderr).contains("backend: cpu (auto"));
    assert_eq!(read_json(dir.path(), "r.json")["backend"], "cpu");
}

/// `METRICDEFORM_BACKEND` sets the default; the flag overrides it.
#[test]
fn backend_environment_default_and_flag_override() {
    let (_out, dir) = deform_job(
        "spot.obj",
        "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"volume\"\n",
        &[],
    );
    let run = |flag: Option<&str>| {
        let mut cmd = bin();
        cmd.arg("deform").arg("job.toml").arg("--quiet");
        if let Some(f) = flag {
            cmd.args(["--backend", f]);
        }
        cmd.args(["--report", "r.json"])
            .env("METRICDEFORM_BACKEND", "gpu")
            .env("WGPU_ADAPTER_NAME", "no-such-adapter-anywhere")
            .current_dir(dir.path())
            .output()
            .unwrap()
    };
    // No flag: the environment asks for the GPU, and there is none: exit 2.
    let out = run(None);
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stderr).contains("--backend gpu"));
    // The flag wins over the environment.
    let out = run(Some("cpu"));
    assert_eq!(out.status.code(), Some(0));
    assert_eq!(read_json(dir.path(), "r.json")["backend"], "cpu");
}

/// Fig. 16 through the CLI: exit 3, the result still written, the report names the missed metric.
#[test]
fn contradictory_demands_exit_3_with_result_and_report() {
    let job = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"area\"\nname = \"surface\"\nregion = { box = { min = [-9.0, -9.0, -9.0], max = [9.0, 9.0, 9.0] } }\n[[constraint]]\nkind = \"volume\"\nname = \"inflate\"\nscale = 3.0\n[solver]\nmax_iterations = 10\nfine_tune_iterations = 10\n";
    let (out, dir) = deform_job("spot.obj", job, &["--report", "report.json"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(
        out.status.code(),
        Some(3),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(dir.path().join("out.obj").exists());
    let report: serde_json::Value = read_json(dir.path(), "report.json");
    assert_eq!(report["satisfied"], false);
    let missed: Vec<&serde_json::Value> = report["constraints"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["met"] == false)
        .collect();
    assert!(!missed.is_empty());
    assert!(missed
        .iter()
        .all(|c| c["error_percent"].as_f64().unwrap() > 1e-3));
    assert!(report["reason"]
        .as_str()
        .unwrap()
        .contains("encloses at most"));
    assert!(stdout.contains("NOT SATISFIED"));
}

/// The embedded demo runs without any file and meets its constraints.
#[test]
fn demo_runs_and_meets_its_constraints() {
    let dir = tempfile::tempdir().unwrap();
    let out = bin()
        .args(["demo", "--backend", "cpu", "--quiet", "--report", "r.json"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(dir.path().join("spot.deformed.obj").exists());
    let report: serde_json::Value = read_json(dir.path(), "r.json");
    assert_eq!(report["satisfied"], true);
    assert_eq!(report["backend"], "cpu");
    for c in report["constraints"].as_array().unwrap() {
        assert!(c["error_percent"].as_f64().unwrap() <= 1e-3);
    }
    assert!(
        report["distortion"]["quasi_conformal_mean"]
            .as_f64()
            .unwrap()
            >= 1.0
    );
}

/// `measure` prints the input's metrics and changes nothing.
#[test]
fn measure_reports_input_metrics() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    std::fs::write(
        dir.path().join("job.json"),
        r#"{"mesh": "spot.obj", "constraint": [{"kind": "volume", "scale": 2.0}]}"#,
    )
    .unwrap();
    let out = bin()
        .args(["measure", "job.json", "--report", "m.json"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    let report: serde_json::Value = read_json(dir.path(), "m.json");
    let c = &report["constraints"][0];
    let (orig, target) = (
        c["original"].as_f64().unwrap(),
        c["target"].as_f64().unwrap(),
    );
    assert!((target - 2.0 * orig).abs() < 1e-12 && orig > 0.0);
    assert_eq!(
        files(dir.path()),
        vec![
            "job.json".to_string(),
            "m.json".to_string(),
            "spot.obj".to_string()
        ]
    );
}

/// `--preview N`: at most N scale-driven iterations and no fine-tune.
#[test]
fn preview_stops_early_and_skips_fine_tune() {
    let job = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.5\n[[constraint]]\nkind = \"length\"\ncurve = { plane = { origin = [0.0, -0.1, 0.3], normal = [0.0, 0.0, 1.0] } }\nscale = 0.9\n";
    let (out, dir) = deform_job("spot.obj", job, &["--preview", "1", "--report", "r.json"]);
    // A preview is not a failure: exit 0, and it says it is a preview, not
    // that the demands are contradictory.
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stdout}{stderr}");
    assert!(stdout.contains("PREVIEW"), "{stdout}");
    assert!(!stdout.contains("NOT SATISFIED") && !stdout.contains("contradictory"));
    assert!(!stderr.contains("contradictory"), "{stderr}");
    let report: serde_json::Value = read_json(dir.path(), "r.json");
    assert_eq!(report["preview"], true);
    assert!(report.get("reason").is_none(), "{report}");
    assert!(report["iterations"]["scale_driven"].as_u64().unwrap() <= 1);
    assert_eq!(report["iterations"]["fine_tune"].as_u64().unwrap(), 0);
    assert!(dir.path().join("out.obj").exists());
}

/// `auto` picks the faster backend by the recorded crossover: never an
/// emulated adapter (lavapipe), and a hardware one only from
/// `GPU_FASTER_FROM_FACES` on. The report's `solver` section names the work of
/// the backend that ran.
#[test]
fn auto_follows_the_crossover_and_reports_the_solver_work() {
    let job = "mesh = \"spot.obj\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.2\n";
    let (out, dir) = deform_job(
        "spot.obj",
        job,
        &["--backend", "auto", "--report", "r.json"],
    );
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = read_json(dir.path(), "r.json");
    let faces = report["mesh"]["faces"].as_u64().unwrap() as usize;
    let hardware = solver_gpu::default_adapter().is_ok_and(|a| a.device_type != "Cpu");
    let expected = if metricdeform::deform::auto_uses_gpu(faces, hardware) {
        "gpu"
    } else {
        "cpu"
    };
    assert_eq!(report["backend"], expected);
    let solver = &report["solver"];
    for kind in ["scale_factors", "scale_driven", "fine_tune"] {
        assert!(
            solver["preconditioner_setups"][kind].as_u64().unwrap() >= 1,
            "{kind}: {solver}"
        );
    }
    assert!(
        solver["pcg_iterations_max"].as_u64().unwrap() > 0,
        "{solver}"
    );
    assert!(solver["host_seconds"].as_f64().unwrap() > 0.0, "{solver}");
    if expected == "cpu" {
        assert_eq!(solver["gpu_seconds"].as_f64(), Some(0.0), "{solver}");
        assert_eq!(solver["transfer_bytes"].as_u64(), Some(0), "{solver}");
    }
    // `measure` deforms nothing and has no solver section.
    let out = bin()
        .args(["measure", "job.toml", "--report", "m.json"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    assert!(read_json(dir.path(), "m.json").get("solver").is_none());
}

const SPOT_LENGTH_JOB: &str = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"length\"\ncurve = { plane = { origin = [0.0, -0.1, 0.3], normal = [0.0, 0.0, 1.0] } }\nscale = 1.05\n";

/// `deform job.toml` on the CPU, quiet, with the report in r.json.
const DEFORM_CPU_REPORTED: [&str; 7] = [
    "deform",
    "job.toml",
    "--quiet",
    "--backend",
    "cpu",
    "--report",
    "r.json",
];

/// A fresh directory holding spot.obj, job.toml (`job`) and a previous output
/// out.obj ("previous").
fn spot_dir(job: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    std::fs::write(dir.path().join("job.toml"), job).unwrap();
    std::fs::write(dir.path().join("out.obj"), "previous").unwrap();
    dir
}

/// The previous output is intact and nothing was added (no temporary file).
fn assert_previous_output_kept(dir: &Path) {
    assert_eq!(
        std::fs::read_to_string(dir.join("out.obj")).unwrap(),
        "previous"
    );
    assert_eq!(files(dir), ["job.toml", "out.obj", "spot.obj"]);
}

/// `--report` and `--out` never overwrite an input (mesh, job, faces file) or
/// each other, in any spelling: exit 2, nothing written, inputs intact.
#[test]
fn report_and_output_never_clobber_inputs_or_each_other() {
    let job_with_faces_file = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"area\"\nregion = { faces_file = \"ear.txt\" }\nscale = 1.1\n";
    let cases: &[(&str, &[&str], &str)] = &[
        (SPOT_LENGTH_JOB, &["--report", "spot.obj"], "input mesh"),
        (SPOT_LENGTH_JOB, &["--report", "./spot.obj"], "input mesh"),
        (SPOT_LENGTH_JOB, &["--report", "job.toml"], "job file"),
        (SPOT_LENGTH_JOB, &["--out", "job.toml"], "job file"),
        (
            SPOT_LENGTH_JOB,
            &["--out", "x.obj", "--report", "x.obj"],
            "output mesh",
        ),
        (SPOT_LENGTH_JOB, &["--report", "out.obj"], "output mesh"),
        (job_with_faces_file, &["--report", "ear.txt"], "faces_file"),
        (job_with_faces_file, &["--out", "ear.txt"], "faces_file"),
        (SPOT_LENGTH_JOB, &["--report", "."], "directory"),
    ];
    for (job, extra, needle) in cases {
        let dir = tempfile::tempdir().unwrap();
        std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
        std::fs::write(dir.path().join("job.toml"), job).unwrap();
        std::fs::write(dir.path().join("ear.txt"), "0 1 2\n").unwrap();
        let before: Vec<(String, Vec<u8>)> = files(dir.path())
            .into_iter()
            .map(|f| {
                let b = std::fs::read(dir.path().join(&f)).unwrap();
                (f, b)
            })
            .collect();
        let out = bin()
            .args(["deform", "job.toml", "--quiet", "--backend", "cpu"])
            .args(*extra)
            .current_dir(dir.path())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{extra:?}: {stderr}");
        assert!(
            stderr.contains(needle),
            "{extra:?}: lacks '{needle}': {stderr}"
        );
        let after: Vec<(String, Vec<u8>)> = files(dir.path())
            .into_iter()
            .map(|f| {
                let b = std::fs::read(dir.path().join(&f)).unwrap();
                (f, b)
            })
            .collect();
        assert!(before == after, "{extra:?}: files changed");
    }
}

/// The mesh and the report are a pair: when the report cannot be written
/// (here into /proc), exit 2 and the output mesh is not written either; a
/// previous output stays as it was.
#[test]
fn unwritable_report_writes_no_mesh() {
    if !Path::new("/proc/self").is_dir() {
        eprintln!("skipped: no /proc");
        return;
    }
    let dir = spot_dir(SPOT_LENGTH_JOB);
    let out = bin()
        .args(["deform", "job.toml", "--quiet", "--backend", "cpu"])
        .args(["--report", "/proc/self/report.json"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("/proc/self/report.json"), "{stderr}");
    assert_previous_output_kept(dir.path());
}

/// A temporary file left by a killed run (its process gone) is removed by the
/// next run writing the same output; one of a live process is kept.
#[test]
fn stale_temporary_files_of_killed_runs_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    std::fs::write(dir.path().join("job.toml"), SPOT_LENGTH_JOB).unwrap();
    // pid_max is at most 2^22 on Linux: 4194999 never runs.
    let stale = ".out.obj.tmp-4194999-0";
    let live = format!(".out.obj.tmp-{}-0", std::process::id());
    std::fs::write(dir.path().join(stale), "half").unwrap();
    std::fs::write(dir.path().join(&live), "busy").unwrap();
    let out = bin()
        .args(["deform", "job.toml", "--quiet", "--backend", "cpu"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let names = files(dir.path());
    assert!(!names.contains(&stale.to_string()), "{names:?}");
    assert!(names.contains(&live), "{names:?}");
}

/// SIGTERM and SIGINT stop a long run within about a second, exit 143 / 130,
/// leave no temporary file and keep the previous output.
#[cfg(unix)]
#[test]
fn interrupts_stop_promptly_and_leave_no_temporary_files() {
    use std::time::{Duration, Instant};
    // A job that runs for minutes: 100,000 scale-driven iterations (about 300 s
    // on the 2-core CI machine), stopped by the signal after 1.5 s.
    for (signal, code) in [("TERM", 143), ("INT", 130)] {
        let job = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.5\n[[constraint]]\nkind = \"length\"\ncurve = { plane = { origin = [0.0, -0.1, 0.3], normal = [0.0, 0.0, 1.0] } }\nscale = 0.9\n[solver]\nmax_iterations = 100000\nscale_threshold = 0.0\ntolerance = 1e-12\n";
        let dir = spot_dir(job);
        let mut child = bin()
            .args(DEFORM_CPU_REPORTED)
            .current_dir(dir.path())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(1500));
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before the signal"
        );
        assert!(!dir.path().join("r.json").exists());
        let sent = Instant::now();
        let kill = Command::new("kill")
            .args([&format!("-{signal}"), &child.id().to_string()])
            .status()
            .unwrap();
        assert!(kill.success());
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break s;
            }
            if sent.elapsed() > Duration::from_secs(5) {
                let _ = child.kill();
                panic!("SIG{signal}: still running 5 s after the signal");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let waited = sent.elapsed();
        let mut stderr = String::new();
        std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut stderr).unwrap();
        assert_eq!(status.code(), Some(code), "SIG{signal}: {stderr}");
        assert!(
            waited < Duration::from_millis(1500),
            "SIG{signal}: {waited:?}"
        );
        assert!(stderr.contains("interrupted"), "{stderr}");
        assert_previous_output_kept(dir.path());
    }
}

/// A job with nothing to do is bad input (exit 2), not a silent copy.
#[test]
fn job_without_constraints_handles_or_curvature_is_refused() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n",
        &["job.toml", "nothing to deform"],
    );
}

/// A constraint name of 70,000 characters (past `format!`'s width limit)
/// measures and deforms without a panic.
#[test]
fn very_long_constraint_names_do_not_panic() {
    let name = "n".repeat(70_000);
    let job = format!(
        "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"volume\"\nname = \"{name}\"\nscale = 1.0\n"
    );
    let (out, dir) = deform_job("spot.obj", &job, &["--report", "r.json"]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        read_json(dir.path(), "r.json")["constraints"][0]["name"],
        name.as_str()
    );
    let m = bin()
        .args(["measure", "job.toml"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(
        m.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&m.stderr)
    );
    assert!(String::from_utf8_lossy(&m.stdout).contains(&name));
}

/// Nothing that is not an error says "error": with no XDG_RUNTIME_DIR (CI,
/// servers), Mesa's Vulkan device-select layer used to print
/// "error: XDG_RUNTIME_DIR is invalid or not set" on every adapter query.
#[test]
fn successful_runs_print_no_error() {
    let out = bin()
        .arg("adapters")
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("NODEVICE_SELECT")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    let all = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!all.to_lowercase().contains("error"), "{all}");
    let (out, _dir) = deform_job_env(
        "spot.obj",
        SPOT_LENGTH_JOB,
        &["--backend", "auto"],
        &[("XDG_RUNTIME_DIR", "")],
    );
    assert_eq!(out.status.code(), Some(0));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.to_lowercase().contains("error"), "{stderr}");
}

/// The contract travels with the repository (docs/CONTRACT.md); where the
/// project's shared copy is present, the two are the same text.
#[test]
fn contract_copy_is_in_step_with_the_shared_contract() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let ours = std::fs::read_to_string(root.join("docs/CONTRACT.md")).unwrap();
    assert!(ours.contains("## Command line"));
    match std::fs::read_to_string(root.join("../shared/CONTRACT.md")) {
        Ok(shared) => assert!(
            ours == shared,
            "docs/CONTRACT.md differs from ../shared/CONTRACT.md"
        ),
        Err(_) => eprintln!("skipped the comparison: no ../shared/CONTRACT.md"),
    }
}

/// Faces handled rather than refused (a duplicate face, a face with a repeated
/// corner) are named in `warning:` lines even under --quiet and in the report's
/// `warnings`; the distortion stays finite (degenerate input faces have no
/// ratio and are left out).
#[test]
fn handled_faces_are_warned_on_stderr_and_in_the_report() {
    let dir = tempfile::tempdir().unwrap();
    let mut obj = std::fs::read_to_string(meshes().join("spot.obj")).unwrap();
    let first_face = obj
        .lines()
        .find(|l| l.starts_with("f "))
        .unwrap()
        .to_string();
    obj.push_str(&format!("{first_face}\nf 1 1 2\n"));
    std::fs::write(dir.path().join("spot.obj"), obj).unwrap();
    std::fs::write(dir.path().join("job.toml"), SPOT_LENGTH_JOB).unwrap();
    let out = bin()
        .args(DEFORM_CPU_REPORTED)
        .current_dir(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    let warned: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("warning: "))
        .collect();
    assert!(warned.iter().any(|l| l.contains("duplicate")), "{stderr}");
    assert!(warned.iter().any(|l| l.contains("zero-area")), "{stderr}");
    let report = read_json(dir.path(), "r.json");
    assert_eq!(report["warnings"].as_array().unwrap().len(), warned.len());
    let qc = report["distortion"]["quasi_conformal_max"].as_f64();
    assert!(qc.is_some_and(|q| q.is_finite() && q >= 1.0), "{report}");
}
