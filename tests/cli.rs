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

/// `measure JOB --report m.json` in `dir`: it must exit 0; the output and
/// the report.
fn measure_reported(dir: &Path, job: &str) -> (Output, serde_json::Value) {
    let out = bin()
        .args(["measure", job, "--report", "m.json"])
        .current_dir(dir)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "measure {job}: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let report = read_json(dir, "m.json");
    (out, report)
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
    let (_, report) = measure_reported(dir.path(), "job.json");
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
    let expected = if metricdeform::pipeline::auto_uses_gpu(faces, hardware) {
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
    let (_, report) = measure_reported(dir.path(), "job.toml");
    assert!(report.get("solver").is_none());
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

/// The `v` positions and the `f` triangles (0-based) of an OBJ of triangles,
/// read here independently of the crate's reader.
fn read_obj(path: &Path) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let text = std::fs::read_to_string(path).unwrap();
    let (mut v, mut f) = (Vec::new(), Vec::new());
    for line in text.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.first() {
            Some(&"v") => v.push([1, 2, 3].map(|k| t[k].parse::<f64>().unwrap())),
            Some(&"f") => {
                assert_eq!(t.len(), 4, "not a triangle: {line}");
                f.push(
                    [1, 2, 3]
                        .map(|k| t[k].split('/').next().unwrap().parse::<usize>().unwrap() - 1),
                );
            }
            _ => {}
        }
    }
    (v, f)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn tri_area(v: &[[f64; 3]], t: [usize; 3]) -> f64 {
    let (e1, e2) = (sub(v[t[1]], v[t[0]]), sub(v[t[2]], v[t[0]]));
    let c = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    0.5 * norm(c)
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()).max(1e-300)
}

/// The report's displacement statistics are those of the written mesh against
/// the input: recomputed here from the two OBJ files, as % of the input's
/// bbox diagonal (max, mean, nearest-rank 99th percentile); the stdout
/// summary line gives them too.
#[test]
fn displacement_statistics_match_the_written_mesh() {
    let job = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.3\n";
    let (out, dir) = deform_job("spot.obj", job, &["--report", "r.json"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (x, faces) = read_obj(&dir.path().join("spot.obj"));
    let (y, faces_out) = read_obj(&dir.path().join("out.obj"));
    assert_eq!(faces, faces_out);
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for t in &faces {
        for &i in t {
            for k in 0..3 {
                lo[k] = lo[k].min(x[i][k]);
                hi[k] = hi[k].max(x[i][k]);
            }
        }
    }
    let diagonal = norm(sub(hi, lo));
    let mut d: Vec<f64> = x
        .iter()
        .zip(&y)
        .map(|(a, b)| norm(sub(*b, *a)) / diagonal * 100.0)
        .collect();
    d.sort_by(f64::total_cmp);
    let n = d.len();
    let max = d[n - 1];
    let mean = d.iter().sum::<f64>() / n as f64;
    let p99 = d[(99 * n).div_ceil(100) - 1];
    // A volume x1.3 moves the surface by several % of the diagonal.
    assert!(max > 1.0, "max {max}");
    let r = read_json(dir.path(), "r.json");
    let disp = &r["displacement"];
    for (key, want) in [
        ("max_percent", max),
        ("mean_percent", mean),
        ("p99_percent", p99),
    ] {
        let got = disp[key].as_f64().unwrap();
        assert!(
            close(got, want, 1e-9),
            "{key}: report {got}, recomputed {want}"
        );
    }
    let line = stdout
        .lines()
        .find(|l| l.contains("displacement"))
        .unwrap_or_else(|| panic!("no displacement on stdout: {stdout}"));
    assert!(line.contains(&format!("max {max:.4}")), "{line}");
    assert!(line.contains(&format!("p99 {p99:.4}")), "{line}");
}

/// The pieces a plane cuts from a triangle mesh, found here independently of
/// the crate's section walk: the faces with corners on both sides (signed
/// distance >= 0 counts as positive, as the contract says) joined by union-find
/// across the edges that change sides. Returns, per piece in order of its
/// smallest face index, (its crossed edges, the distance from `origin` to its
/// nearest crossing point).
fn plane_pieces(
    v: &[[f64; 3]],
    faces: &[[usize; 3]],
    origin: [f64; 3],
    normal: [f64; 3],
) -> Vec<(usize, f64)> {
    use std::collections::{BTreeMap, HashMap, HashSet};
    let d: Vec<f64> = v.iter().map(|p| dot(sub(*p, origin), normal)).collect();
    let pos = |i: usize| d[i] >= 0.0;
    let mut parent: HashMap<usize, usize> = HashMap::new();
    fn find(p: &mut HashMap<usize, usize>, mut a: usize) -> usize {
        while p[&a] != a {
            let up = p[&p[&a]];
            p.insert(a, up);
            a = up;
        }
        a
    }
    let mut edge_faces: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
    for (fi, t) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if pos(a) != pos(b) {
                parent.insert(fi, fi);
                edge_faces.entry((a.min(b), a.max(b))).or_default().push(fi);
            }
        }
    }
    for fs in edge_faces.values() {
        for &g in &fs[1..] {
            let (ra, rb) = (find(&mut parent, fs[0]), find(&mut parent, g));
            parent.insert(rb, ra);
        }
    }
    /// A piece: (smallest face, crossed edges, nearest crossing).
    type Piece = (usize, HashSet<(usize, usize)>, f64);
    let mut pieces: BTreeMap<usize, Piece> = BTreeMap::new();
    let keys: Vec<usize> = parent.keys().copied().collect();
    for f in keys {
        let r = find(&mut parent, f);
        let e = pieces
            .entry(r)
            .or_insert((usize::MAX, HashSet::new(), f64::INFINITY));
        e.0 = e.0.min(f);
    }
    for (&(a, b), fs) in &edge_faces {
        let r = find(&mut parent, fs[0]);
        let t = d[a] / (d[a] - d[b]);
        let p = [0, 1, 2].map(|k| v[a][k] + t * (v[b][k] - v[a][k]));
        let e = pieces.get_mut(&r).unwrap();
        e.1.insert((a, b));
        e.2 = e.2.min(norm(sub(p, origin)));
    }
    let mut list: Vec<(usize, usize, f64)> = pieces
        .into_values()
        .map(|(f, e, dist)| (f, e.len(), dist))
        .collect();
    list.sort_by_key(|p| p.0);
    list.into_iter().map(|(_, e, dist)| (e, dist)).collect()
}

/// `measure` reports and prints each constraint's selection on spot, checked
/// against counts made here from the OBJ: a sphere's faces (centroid within),
/// their area and bounding box; a plane through the four legs (4 loops, the
/// chosen one holding the crossing nearest the origin) and one through the
/// body (1 loop); a curve's points (one per crossed edge of its loop). No
/// constraint has a target: each is just measured (target = original, met).
#[test]
fn measure_reports_selection_facts() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    let legs = ([-0.2, -0.6, -0.1], [0.0, 1.0, 0.0]);
    let body = ([0.0, 0.0, 0.3], [0.0, 1.0, 0.0]);
    let (center, radius) = ([0.0, 0.55, -0.4], 0.35);
    let job = format!(
        "mesh = \"spot.obj\"\n\
         [[constraint]]\nkind = \"length\"\nname = \"legs\"\n\
         curve = {{ plane = {{ origin = {:?}, normal = {:?} }} }}\n\
         [[constraint]]\nkind = \"length\"\nname = \"body\"\n\
         curve = {{ plane = {{ origin = {:?}, normal = {:?} }} }}\n\
         [[constraint]]\nkind = \"area\"\nname = \"head\"\n\
         region = {{ sphere = {{ center = {center:?}, radius = {radius:?} }} }}\n",
        legs.0, legs.1, body.0, body.1
    );
    std::fs::write(dir.path().join("job.toml"), job).unwrap();
    let (out, report) = measure_reported(dir.path(), "job.toml");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let (v, faces) = read_obj(&dir.path().join("spot.obj"));
    // The sphere: faces whose centroid is within it, none near its surface.
    let mut region = Vec::new();
    for (fi, t) in faces.iter().enumerate() {
        let c = [0, 1, 2].map(|k| (v[t[0]][k] + v[t[1]][k] + v[t[2]][k]) / 3.0);
        let r = norm(sub(c, center));
        assert!((r - radius).abs() > 1e-9, "face {fi} on the sphere");
        if r <= radius {
            region.push(fi);
        }
    }
    let area: f64 = region.iter().map(|&f| tri_area(&v, faces[f])).sum();
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for &f in &region {
        for &i in &faces[f] {
            for k in 0..3 {
                lo[k] = lo[k].min(v[i][k]);
                hi[k] = hi[k].max(v[i][k]);
            }
        }
    }
    let leg_pieces = plane_pieces(&v, &faces, legs.0, legs.1);
    let body_pieces = plane_pieces(&v, &faces, body.0, body.1);
    // Spot stands on four legs: a cut at y = -0.6 crosses each once.
    assert_eq!(leg_pieces.len(), 4);
    assert_eq!(body_pieces.len(), 1);
    let nearest = |p: &[(usize, f64)]| {
        (0..p.len())
            .min_by(|&a, &b| p[a].1.total_cmp(&p[b].1))
            .unwrap()
    };
    let leg_chosen = nearest(&leg_pieces);
    // The origin is beside a leg other than the first in face order, so that
    // the choice is not the first piece found.
    assert_ne!(leg_chosen, 0);

    let r = report;
    let rows = r["constraints"].as_array().unwrap();
    assert_eq!(rows.len(), 3);
    for row in rows {
        assert_eq!(row["target"], row["original"], "{row}");
        assert_eq!(row["met"], true, "{row}");
    }
    let (lr, br, hr) = (&rows[0], &rows[1], &rows[2]);
    assert_eq!(lr["loops"], 4, "{lr}");
    assert_eq!(lr["chosen_loop"], leg_chosen + 1, "{lr}");
    assert_eq!(lr["points"], leg_pieces[leg_chosen].0, "{lr}");
    assert_eq!(br["loops"], 1, "{br}");
    assert_eq!(br["chosen_loop"], 1, "{br}");
    assert_eq!(br["points"], body_pieces[0].0, "{br}");
    assert!(lr.get("faces").is_none() && hr.get("loops").is_none());
    assert_eq!(hr["faces"], region.len(), "{hr}");
    assert!(
        close(hr["area"].as_f64().unwrap(), area, 1e-12),
        "{hr} vs {area}"
    );
    assert!(close(hr["original"].as_f64().unwrap(), area, 1e-12), "{hr}");
    for k in 0..3 {
        assert_eq!(hr["bbox"]["min"][k].as_f64(), Some(lo[k]), "{hr}");
        assert_eq!(hr["bbox"]["max"][k].as_f64(), Some(hi[k]), "{hr}");
    }
    // The same facts on stdout, one line per constraint under the table.
    let line = |name: &str| {
        stdout
            .lines()
            .find(|l| l.starts_with(&format!("  {name}: ")))
            .unwrap_or_else(|| panic!("no line for {name}: {stdout}"))
            .to_string()
    };
    let l = line("legs");
    assert!(
        l.contains("4 loops")
            && l.contains(&format!("loop {}", leg_chosen + 1))
            && l.contains(&format!("{} points", leg_pieces[leg_chosen].0)),
        "{l}"
    );
    assert!(line("body").contains("1 loop,"), "{stdout}");
    assert!(
        line("head").contains(&format!("{} faces", region.len())),
        "{stdout}"
    );
}

/// `measure` takes a job without any target (constraints with neither scale
/// nor value) and a job with no constraint at all: it measures, exit 0.
#[test]
fn measure_needs_no_targets() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    std::fs::write(dir.path().join("bare.toml"), "mesh = \"spot.obj\"\n").unwrap();
    std::fs::write(
        dir.path().join("kept.json"),
        r#"{"mesh": "spot.obj", "constraint": [{"kind": "volume"}, {"kind": "area", "region": {"faces": [0, 1, 2]}}]}"#,
    )
    .unwrap();
    for job in ["bare.toml", "kept.json"] {
        let (_, r) = measure_reported(dir.path(), job);
        let rows = r["constraints"].as_array().unwrap();
        assert_eq!(rows.len(), if job == "bare.toml" { 0 } else { 2 });
        for row in rows {
            assert_eq!(row["target"], row["original"], "{row}");
            assert_eq!(row["error_percent"], 0.0, "{row}");
        }
        if job == "kept.json" {
            assert_eq!(rows[1]["faces"], 3);
        }
    }
}

/// A binary little-endian PLY read here by hand (independently of the crate's
/// reader): per element, its property names and, per record, the values
/// (a list property's entries first, then the scalars, in header order).
struct Ply {
    vertex_props: Vec<String>,
    face_props: Vec<String>,
    vertex: Vec<Vec<f64>>,
    face_indices: Vec<Vec<usize>>,
    face: Vec<Vec<f64>>,
}

fn read_ply(path: &Path) -> Ply {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let hlen = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..hlen]).unwrap();
    assert!(
        header.contains("format binary_little_endian 1.0"),
        "{header}"
    );
    /// (element name, count, [(type, property name)]).
    type Element = (String, usize, Vec<(String, String)>);
    let mut elems: Vec<Element> = Vec::new();
    for line in header.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.first() {
            Some(&"element") => elems.push((t[1].into(), t[2].parse().unwrap(), Vec::new())),
            Some(&"property") => {
                let (ty, name) = if t[1] == "list" {
                    (format!("list {} {}", t[2], t[3]), t[4])
                } else {
                    (t[1].to_string(), t[2])
                };
                elems.last_mut().unwrap().2.push((ty, name.into()));
            }
            _ => {}
        }
    }
    let mut at = hlen;
    let mut take = |n: usize| {
        let s = &bytes[at..at + n];
        at += n;
        s.to_vec()
    };
    let mut ply = Ply {
        vertex_props: Vec::new(),
        face_props: Vec::new(),
        vertex: Vec::new(),
        face_indices: Vec::new(),
        face: Vec::new(),
    };
    for (name, count, props) in &elems {
        let names: Vec<String> = props.iter().map(|p| p.1.clone()).collect();
        for _ in 0..*count {
            let mut scalars = Vec::new();
            for (ty, _) in props {
                match ty.as_str() {
                    "double" => scalars.push(f64::from_le_bytes(take(8).try_into().unwrap())),
                    "list uchar int" => {
                        let n = take(1)[0] as usize;
                        let idx = (0..n)
                            .map(|_| i32::from_le_bytes(take(4).try_into().unwrap()) as usize)
                            .collect();
                        ply.face_indices.push(idx);
                    }
                    other => panic!("unexpected PLY type {other}"),
                }
            }
            match name.as_str() {
                "vertex" => ply.vertex.push(scalars),
                "face" => ply.face.push(scalars),
                other => panic!("unexpected element {other}"),
            }
        }
        match name.as_str() {
            "vertex" => ply.vertex_props = names,
            _ => ply.face_props = names,
        }
    }
    assert_eq!(at, bytes.len(), "trailing bytes");
    ply
}

/// PLY output carries per face `scale` and `distortion` and per vertex
/// `dx dy dz` (the string form of `output`): the distortion's area-weighted
/// mean and max are the report's quasi-conformal figures, the scale is
/// sqrt(area out / area in) of the written positions, the displacement is
/// written minus input. The file reads back as an input mesh.
#[test]
fn ply_output_carries_scale_distortion_and_displacement() {
    let job = "mesh = \"spot.obj\"\noutput = \"out.ply\"\n[[constraint]]\nkind = \"area\"\nregion = { sphere = { center = [0.0, 0.55, -0.4], radius = 0.35 } }\nscale = 1.5\n";
    let (out, dir) = deform_job("spot.obj", job, &["--report", "r.json"]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (x, faces) = read_obj(&dir.path().join("spot.obj"));
    let ply = read_ply(&dir.path().join("out.ply"));
    assert_eq!(ply.vertex_props, ["x", "y", "z", "dx", "dy", "dz"]);
    assert_eq!(ply.face_props, ["vertex_indices", "scale", "distortion"]);
    assert_eq!(ply.vertex.len(), x.len());
    let fi: Vec<Vec<usize>> = faces.iter().map(|t| t.to_vec()).collect();
    assert_eq!(ply.face_indices, fi);
    let y: Vec<[f64; 3]> = ply.vertex.iter().map(|r| [r[0], r[1], r[2]]).collect();
    for (i, r) in ply.vertex.iter().enumerate() {
        assert_eq!([r[3], r[4], r[5]], sub(y[i], x[i]), "vertex {i}");
    }
    let mut moved = 0.0f64;
    for r in &ply.vertex {
        moved = moved.max(norm([r[3], r[4], r[5]]));
    }
    assert!(moved > 1e-3, "nothing moved: {moved}");
    let (mut sum, mut wsum, mut max) = (0.0, 0.0, 1.0f64);
    let (mut s_lo, mut s_hi) = (f64::INFINITY, 0.0f64);
    for (f, t) in faces.iter().enumerate() {
        let (a_in, a_out) = (tri_area(&x, *t), tri_area(&y, *t));
        let (scale, dist) = (ply.face[f][0], ply.face[f][1]);
        assert!(
            close(scale, (a_out / a_in).sqrt(), 1e-9),
            "face {f}: {scale}"
        );
        s_lo = s_lo.min(scale);
        s_hi = s_hi.max(scale);
        sum += a_in * dist;
        wsum += a_in;
        max = max.max(dist);
    }
    // The head grew by 1.5 in area: some faces scale up, by sqrt(1.5) on average.
    assert!(s_hi > 1.1 && s_lo < s_hi, "scales {s_lo} .. {s_hi}");
    let r = read_json(dir.path(), "r.json");
    let qc = &r["distortion"];
    let (mean_r, max_r) = (
        qc["quasi_conformal_mean"].as_f64().unwrap(),
        qc["quasi_conformal_max"].as_f64().unwrap(),
    );
    assert!(
        close(sum / wsum, mean_r, 1e-9),
        "{} vs {mean_r}",
        sum / wsum
    );
    assert!(close(max, max_r, 1e-9), "{max} vs {max_r}");
    assert!(max > 1.0);

    // The PLY written is an input again: measure it, and deform it to PLY.
    let job2 = "mesh = \"out.ply\"\noutput = \"again.ply\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.1\n";
    std::fs::write(dir.path().join("again.toml"), job2).unwrap();
    let (_, m) = measure_reported(dir.path(), "again.toml");
    assert_eq!(m["mesh"]["vertices"], x.len());
    assert_eq!(m["mesh"]["faces"], faces.len());
    let out = bin()
        .args(["deform", "again.toml", "--backend", "cpu", "--quiet"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let again = read_ply(&dir.path().join("again.ply"));
    assert_eq!(again.face_indices, fi);
    // Displacements are against out.ply's positions, not spot.obj's.
    for (i, r) in again.vertex.iter().enumerate() {
        assert_eq!(
            [r[3], r[4], r[5]],
            sub([r[0], r[1], r[2]], y[i]),
            "vertex {i}"
        );
    }
}

/// `[output] attributes = false` writes plain geometry (x y z and
/// vertex_indices only); the table's `path` is the output path, in TOML and
/// in JSON; `[output]` with `attributes` only keeps the default path; OBJ
/// output stays plain whatever `attributes` says.
#[test]
fn output_table_switches_attributes_off() {
    let constraint = "[[constraint]]\nkind = \"volume\"\nscale = 1.1\n";
    let job = format!(
        "mesh = \"spot.obj\"\n[output]\npath = \"flat.ply\"\nattributes = false\n{constraint}"
    );
    let (out, dir) = deform_job("spot.obj", &job, &[]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ply = read_ply(&dir.path().join("flat.ply"));
    assert_eq!(ply.vertex_props, ["x", "y", "z"]);
    assert_eq!(ply.face_props, ["vertex_indices"]);
    assert_eq!(ply.face.len(), 5856);

    // Table with the path only: attributes on (the default).
    let job = format!("mesh = \"spot.obj\"\n[output]\npath = \"full.ply\"\n{constraint}");
    let (out, dir) = deform_job("spot.obj", &job, &[]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ply = read_ply(&dir.path().join("full.ply"));
    assert_eq!(ply.face_props, ["vertex_indices", "scale", "distortion"]);

    // Table without a path: the default name beside the job.
    let job = format!("mesh = \"spot.obj\"\n[output]\nattributes = false\n{constraint}");
    let (out, dir) = deform_job("spot.obj", &job, &[]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(dir.path().join("spot.deformed.obj").exists());

    // JSON, and `--out` with a .ply keeps the job's attributes = false.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    std::fs::write(
        dir.path().join("job.json"),
        r#"{"mesh": "spot.obj", "output": {"path": "j.ply", "attributes": false},
            "constraint": [{"kind": "volume", "scale": 1.1}]}"#,
    )
    .unwrap();
    for extra in [&[][..], &["--out", "o.ply"][..]] {
        let out = bin()
            .args(["deform", "job.json", "--backend", "cpu", "--quiet"])
            .args(extra)
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert_eq!(
            out.status.code(),
            Some(0),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    for name in ["j.ply", "o.ply"] {
        let ply = read_ply(&dir.path().join(name));
        assert_eq!(ply.vertex_props, ["x", "y", "z"], "{name}");
        assert_eq!(ply.face_props, ["vertex_indices"], "{name}");
    }
}

/// A misspelt key in `[output]`, or an `output` that is neither a path nor a
/// table, is bad input naming the job file and what is expected.
#[test]
fn bad_output_table_is_refused() {
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[output]\natributes = false\n[[constraint]]\nkind = \"volume\"\n",
        &["job.toml", "atributes", "attributes"],
    );
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\noutput = 3\n[[constraint]]\nkind = \"volume\"\n",
        &["job.toml", "output", "path"],
    );
    assert_bad_input(
        "spot.obj",
        "mesh = \"spot.obj\"\n[output]\nattributes = \"no\"\n[[constraint]]\nkind = \"volume\"\n",
        &["job.toml", "bool"],
    );
}

/// trimesh (`process=False`, which keeps the vertices as in the file) loads
/// our PLY with its extra properties: same vertex and face counts, same first
/// vertex, and the face properties are there. Skipped with a message when
/// python3 with trimesh is not available, unless REQUIRE_TRIMESH=1 (CI).
#[test]
fn trimesh_loads_the_ply_output() {
    let required = std::env::var("REQUIRE_TRIMESH").is_ok_and(|v| v == "1");
    let probe = Command::new("python3")
        .args(["-c", "import trimesh, numpy"])
        .output();
    let available = probe.as_ref().is_ok_and(|o| o.status.success());
    if !available {
        let why = match &probe {
            // The exception's line (the last of a traceback).
            Ok(o) => String::from_utf8_lossy(&o.stderr)
                .lines()
                .last()
                .unwrap_or("")
                .to_string(),
            Err(e) => format!("python3: {e}"),
        };
        assert!(
            !required,
            "REQUIRE_TRIMESH=1 but trimesh is not importable: {why}"
        );
        eprintln!(
            "skipped: python3 with trimesh is not available ({})",
            why.trim()
        );
        return;
    }
    let job = "mesh = \"spot.obj\"\noutput = \"out.ply\"\n[[constraint]]\nkind = \"volume\"\nscale = 1.2\n";
    let (out, dir) = deform_job("spot.obj", job, &[]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ply = read_ply(&dir.path().join("out.ply"));
    assert_eq!(ply.face_props, ["vertex_indices", "scale", "distortion"]);
    let script = "import sys, trimesh\n\
                  m = trimesh.load(sys.argv[1], process=False)\n\
                  raw = m.metadata.get('_ply_raw', {}).get('face', {}).get('data', {})\n\
                  names = raw.dtype.names if hasattr(raw, 'dtype') else tuple(raw)\n\
                  print(len(m.vertices), len(m.faces), *map(repr, m.vertices[0].tolist()), \
                  'scale' in names and 'distortion' in names)\n";
    let run = Command::new("python3")
        .args(["-c", script])
        .arg(dir.path().join("out.ply"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "trimesh failed: {}{stdout}",
        String::from_utf8_lossy(&run.stderr)
    );
    let fields: Vec<&str> = stdout.split_whitespace().collect();
    assert_eq!(
        fields[0].parse::<usize>().unwrap(),
        ply.vertex.len(),
        "{stdout}"
    );
    assert_eq!(
        fields[1].parse::<usize>().unwrap(),
        ply.face_indices.len(),
        "{stdout}"
    );
    let v0: Vec<f64> = fields[2..5].iter().map(|t| t.parse().unwrap()).collect();
    assert_eq!(v0, ply.vertex[0][..3], "first vertex: {stdout}");
    assert_eq!(fields.last(), Some(&"True"), "face properties: {stdout}");
}

/// `demo --print-job` prints the bundled job file as it is in the repository,
/// writes nothing, and the text is a job: beside spot.obj at the path it
/// names, `measure` runs it and finds its three constraints.
#[test]
fn demo_prints_its_job() {
    let dir = tempfile::tempdir().unwrap();
    let out = bin()
        .args(["demo", "--print-job"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    assert!(
        files(dir.path()).is_empty(),
        "wrote {:?}",
        files(dir.path())
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    assert_eq!(
        text,
        std::fs::read_to_string(root.join("examples/spot-demo.toml")).unwrap()
    );
    let parsed: toml::Table = toml::from_str(&text).unwrap();
    let mesh = parsed["mesh"].as_str().unwrap();
    // Lay out the mesh where the job says (relative to the job file).
    let jobs = dir.path().join("jobs");
    std::fs::create_dir_all(&jobs).unwrap();
    let mesh_path = jobs.join(mesh);
    std::fs::create_dir_all(mesh_path.parent().unwrap()).unwrap();
    std::fs::copy(meshes().join("spot.obj"), &mesh_path).unwrap();
    std::fs::write(jobs.join("demo.toml"), &text).unwrap();
    let (_, r) = measure_reported(dir.path(), "jobs/demo.toml");
    let names: Vec<&str> = r["constraints"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["belly girth", "head", "volume"]);
}

/// The README's JSON job example is a job: `measure` runs it on spot.
#[test]
fn readme_json_job_example_runs() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let start = readme
        .find("```json\n{\n  \"mesh\"")
        .expect("README has a JSON job example")
        + "```json\n".len();
    let len = readme[start..].find("```").unwrap();
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(meshes().join("spot.obj"), dir.path().join("spot.obj")).unwrap();
    std::fs::write(dir.path().join("job.json"), &readme[start..start + len]).unwrap();
    let (_, r) = measure_reported(dir.path(), "job.json");
    assert_eq!(r["constraints"].as_array().unwrap().len(), 3);
}

/// Whether a GPU adapter is present; without one, a failure where
/// `REQUIRE_GPU=1` asks for one.
fn gpu_adapter_present() -> bool {
    let present = solver_gpu::gpu_available();
    assert!(
        present || std::env::var("REQUIRE_GPU").map_or(true, |v| v != "1"),
        "REQUIRE_GPU=1 but no GPU adapter is available"
    );
    present
}

/// The demo's constraints on spot (several outer iterations), for the GPU
/// paths' comparisons.
const SPOT_GPU_JOB: &str = "mesh = \"spot.obj\"\noutput = \"out.obj\"\n\
    [[constraint]]\nkind = \"length\"\n\
    curve = { plane = { origin = [0.0, -0.1, 0.3], normal = [0.0, 0.0, 1.0] } }\nscale = 1.1\n\
    [[constraint]]\nkind = \"area\"\n\
    region = { sphere = { center = [0.0, 0.55, -0.4], radius = 0.35 } }\nscale = 1.3\n\
    [[constraint]]\nkind = \"volume\"\nscale = 1.0\n";

/// `METRICDEFORM_GPU_FACTORIZATION=gpu`: every Cholesky factor is made on
/// the GPU, submitted ahead (the scale factors' by their set-up, the
/// scale-driven kind's in slices beside that set-up where it still runs,
/// else while the host estimates the first scale factors, the
/// fine-tune's in slices from the first solve on), and the
/// result is the host-made factors' within the parity bound (1e-3 % of the
/// bbox diagonal), with fewer bytes moved (the factors stay on the device).
#[test]
fn gpu_factorization_gives_the_host_factors_result() {
    if !gpu_adapter_present() {
        return;
    }
    let f64_adapter = solver_gpu::default_adapter().is_ok_and(|a| a.shader_f64);
    let job = SPOT_GPU_JOB;
    let run = |factorization: &str| {
        let (out, dir) = deform_job_env(
            "spot.obj",
            job,
            &["--backend", "gpu", "--report", "r.json"],
            &[
                ("METRICDEFORM_GPU_FACTORIZATION", factorization),
                ("RUST_LOG", "solver_gpu=debug"),
            ],
        );
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert_eq!(out.status.code(), Some(0), "{factorization}: {err}");
        let mesh = metricdeform::mesh::io::read_mesh(&dir.path().join("out.obj")).unwrap();
        let moved = read_json(dir.path(), "r.json")["solver"]["transfer_bytes"]
            .as_u64()
            .unwrap();
        (mesh.positions, moved, err)
    };
    let (host, host_moved, _) = run("host");
    let (gpu, gpu_moved, log) = run("gpu");
    if f64_adapter {
        let line = |kind: &str, how: &str| {
            log.lines()
                .any(|l| l.contains(kind) && l.contains("factored on the GPU") && l.contains(how))
        };
        assert!(
            line("(ScaleDriven system, F64)", "submitted ahead"),
            "{log}"
        );
        // Recorded while the scale factors' set-up ran on.
        assert!(
            line("(ScaleDriven system, F64)", "recorded ahead in"),
            "{log}"
        );
        assert!(line("(FineTune system, F64)", "submitted ahead"), "{log}");
        // In slices, the next ones submitted where the device idles (after
        // each solve, before each shape matrix), the rest by its set-up.
        assert!(line("(FineTune system, F64)", "in 10 slices"), "{log}");
        assert!(
            log.contains("FineTune system's factor: slice 2 of 10 submitted to the GPU ahead"),
            "{log}"
        );
        // The fine-tune's factorization is the scale-driven kind's
        // recording, bound to its own values.
        assert!(
            line(
                "(FineTune system, F64)",
                "the scale-driven kind's recording"
            ),
            "{log}"
        );
        // The scale factors' own factor too, submitted by their set-up.
        assert!(
            line("(ScaleFactors system, F64)", "submitted ahead"),
            "{log}"
        );
        assert!(
            gpu_moved < host_moved,
            "{gpu_moved} bytes against {host_moved}"
        );
    }
    let (lo, hi) = host.iter().fold(
        (glam::DVec3::splat(f64::MAX), glam::DVec3::splat(f64::MIN)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let diagonal = (hi - lo).length();
    let worst = host
        .iter()
        .zip(&gpu)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    assert_eq!(host.len(), gpu.len());
    assert!(
        worst <= 1e-5 * diagonal,
        "GPU-made factors' result {:.2e} % of the bbox diagonal from the host-made's",
        100.0 * worst / diagonal
    );
}

/// On a host with threads to spare for uploads beside the caller (4 of
/// rayon's threads here), the shape matrices' pattern is set up on its own
/// thread from the shape model's set-up on (the blocks' pattern, the
/// expansion, the shape sum and its ring pairs) and taken up by the first
/// shape matrix; the run writes the very mesh a run on 2 threads writes,
/// where the first matrix sets its pattern up itself.
#[test]
fn a_shape_pattern_set_up_ahead_writes_the_same_mesh() {
    if !gpu_adapter_present() {
        return;
    }
    let f64_adapter = solver_gpu::default_adapter().is_ok_and(|a| a.shader_f64);
    let job = SPOT_GPU_JOB;
    let run = |threads: &str| {
        let (out, dir) = deform_job_env(
            "spot.obj",
            job,
            &["--backend", "gpu"],
            &[
                ("RAYON_NUM_THREADS", threads),
                ("RUST_LOG", "solver_gpu=debug"),
            ],
        );
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert_eq!(out.status.code(), Some(0), "{threads} threads: {err}");
        (std::fs::read(dir.path().join("out.obj")).unwrap(), err)
    };
    let (two, log_two) = run("2");
    let (four, log_four) = run("4");
    let taken = |log: &str| log.contains("shape pattern set up ahead: waited");
    assert!(!taken(&log_two), "{log_two}");
    if f64_adapter {
        assert!(taken(&log_four), "{log_four}");
    }
    assert!(two == four, "the meshes written on 2 and 4 threads differ");
}
