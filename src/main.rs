//! `metricdeform`: the command line of the contract (deform, measure, adapters, demo).

use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use metricdeform::job::BACKENDS;
use metricdeform::job::{Job, JobFormat};
use metricdeform::mesh::io;
use metricdeform::pipeline::{choose_backend as choose, deform, Options, Progress, SolverBackend};
use metricdeform::problem::Problem;
use metricdeform::report::{table, Report, RunInfo};
use metricdeform::{output, render, Error};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::str::FromStr;
use std::time::Instant;

const DEMO_JOB: &str = include_str!("../examples/spot-demo.toml");
const DEMO_MESH: &str = include_str!("../data/meshes/spot.obj");

#[derive(Parser)]
#[command(
    name = "metricdeform",
    version,
    about = "Deform a triangle mesh so that demanded lengths, areas and volumes hold exactly"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
enum Backend {
    Auto,
    Cpu,
    Gpu,
}

#[derive(clap::Args, Clone)]
struct RunArgs {
    /// auto (GPU when an adapter exists, else CPU), cpu or gpu. Default: METRICDEFORM_BACKEND, the job's [solver] backend, else auto.
    #[arg(long, value_enum)]
    backend: Option<Backend>,
    /// Output mesh (overrides the job's `output`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the JSON report here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Stop the scale-driven phase after N iterations and skip the fine-tune.
    #[arg(long, value_name = "N")]
    preview: Option<usize>,
    #[command(flatten)]
    picture: PictureArgs,
    /// No progress output (warnings still go to stderr).
    #[arg(long)]
    quiet: bool,
}

/// `--render` and how the picture is made (CPU only, no GPU needed).
#[derive(clap::Args, Clone)]
struct PictureArgs {
    /// Write a PNG picture: for deform, input and result side by side,
    /// coloured by --color, with every constraint drawn and named; for
    /// measure, the input with every selection.
    #[arg(long, value_name = "PATH")]
    render: Option<PathBuf>,
    /// The picture's size in pixels.
    #[arg(long, value_name = "WxH", default_value = "1600x800", value_parser = render::parse_size)]
    render_size: (u32, u32),
    /// The camera: three-quarter (front-right, a little above), front, side, top or iso.
    #[arg(long, default_value = "three-quarter", value_parser = render::View::from_str)]
    view: render::View,
    /// What colours the result's faces: scale (sqrt of the area ratio), distortion (quasi-conformal) or displacement.
    #[arg(long, default_value = "scale", value_parser = render::ColorBy::from_str)]
    color: render::ColorBy,
}

impl PictureArgs {
    fn params(&self) -> render::RenderParams {
        render::RenderParams {
            width: self.render_size.0,
            height: self.render_size.1,
            view: self.view,
            color: self.color,
        }
    }
}

#[derive(Subcommand)]
enum Command {
    /// Deform the job's mesh so that its constraints hold.
    Deform {
        /// Job file (.toml or .json).
        job: PathBuf,
        #[command(flatten)]
        args: RunArgs,
    },
    /// Print the metrics of the input mesh, no deformation.
    Measure {
        job: PathBuf,
        #[arg(long)]
        report: Option<PathBuf>,
        #[command(flatten)]
        picture: PictureArgs,
    },
    /// List the GPU adapters and which one `--backend gpu` would use.
    Adapters,
    /// Run the bundled job on spot (no files needed).
    Demo {
        /// Print the demo's job file (examples/spot-demo.toml) and exit, running nothing.
        #[arg(long)]
        print_job: bool,
        #[command(flatten)]
        args: RunArgs,
    },
}

fn main() -> ExitCode {
    metricdeform::memory::keep_freed_memory();
    quiet_vulkan_layers();
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    let cli = Cli::parse();
    if let Err(e) = output::install_interrupt_handler() {
        log::warn!("{e}: an interrupt will not clean up temporary files");
    }
    let result = match cli.command {
        Command::Deform { job, args } => Job::load(&job).and_then(|j| run(&j, &args)),
        Command::Measure {
            job,
            report,
            picture,
        } => Job::load(&job).and_then(|j| measure(&j, report.as_deref(), &picture)),
        Command::Adapters => adapters(),
        Command::Demo {
            print_job: true, ..
        } => {
            print!("{DEMO_JOB}");
            Ok(0)
        }
        Command::Demo { args, .. } => demo(&args),
    };
    solver_gpu::drop_opened_ahead();
    match result {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(e.exit_code() as u8)
        }
    }
}

/// Mesa's device-select Vulkan layer (an implicit layer, loaded by every Vulkan
/// program) asks Wayland for the default GPU and, where no XDG_RUNTIME_DIR is
/// set (servers, CI, containers), prints "error: XDG_RUNTIME_DIR is invalid or
/// not set" on every run, though nothing failed. wgpu chooses the adapter
/// itself, so the layer is switched off, unless the user configured it
/// (NODEVICE_SELECT, MESA_VK_DEVICE_SELECT, DRI_PRIME).
fn quiet_vulkan_layers() {
    let configured = ["NODEVICE_SELECT", "MESA_VK_DEVICE_SELECT", "DRI_PRIME"]
        .iter()
        .any(|v| std::env::var_os(v).is_some());
    if !configured {
        // Single-threaded here: no thread has started yet.
        std::env::set_var("NODEVICE_SELECT", "1");
    }
}

fn adapters() -> Result<u8, Error> {
    let list = solver_gpu::list_adapters();
    if list.is_empty() {
        println!("wgpu sees no GPU adapter (Vulkan)");
    }
    for a in &list {
        println!(
            "{} ({}, {}, driver {} {}, SHADER_F64: {}, TIMESTAMP_QUERY: {})",
            a.name,
            a.backend,
            a.device_type,
            a.driver,
            a.driver_info,
            if a.shader_f64 { "yes" } else { "no" },
            if a.timestamp_query { "yes" } else { "no" }
        );
    }
    match solver_gpu::default_adapter() {
        Ok(a) => println!(
            "`--backend gpu` would use: {} (set WGPU_ADAPTER_NAME to choose)",
            a.name
        ),
        Err(why) => {
            println!("no GPU adapter in use: {why}");
            println!("`--backend gpu` would fail; `--backend auto` uses the CPU.");
        }
    }
    Ok(0)
}

fn demo(args: &RunArgs) -> Result<u8, Error> {
    // Removed on return and on an interrupt.
    let tmp = output::TempDir::new("metricdeform-demo")?;
    let dir = tmp.path();
    let io_err = |path: PathBuf| move |source| Error::Io { path, source };
    std::fs::create_dir_all(dir.join("data/meshes"))
        .and_then(|_| std::fs::create_dir_all(dir.join("examples")))
        .map_err(io_err(dir.to_path_buf()))?;
    let mesh = dir.join("data/meshes/spot.obj");
    std::fs::write(&mesh, DEMO_MESH).map_err(io_err(mesh.clone()))?;
    let mut job = Job::from_str(
        DEMO_JOB,
        JobFormat::Toml,
        &dir.join("examples"),
        "demo job (examples/spot-demo.toml)",
    )?;
    job.spec.mesh = PathBuf::from("../data/meshes/spot.obj");
    let mut args = args.clone();
    if args.out.is_none() {
        args.out = Some(PathBuf::from("spot.deformed.obj"));
    }
    run(&job, &args)
}

/// The backend asked for: flag, then the job, then METRICDEFORM_BACKEND,
/// then auto.
fn backend_name(flag: Option<Backend>, job: &Job) -> String {
    let from_env = std::env::var("METRICDEFORM_BACKEND")
        .ok()
        .filter(|s| !s.is_empty());
    match flag {
        Some(Backend::Auto) => "auto".to_string(),
        Some(Backend::Cpu) => "cpu".to_string(),
        Some(Backend::Gpu) => "gpu".to_string(),
        None => job
            .spec
            .solver
            .backend
            .clone()
            .or(from_env)
            .unwrap_or_else(|| "auto".into()),
    }
}

/// Resolve the backend: flag, then the job, then METRICDEFORM_BACKEND, then auto
/// (the GPU on a hardware adapter from the measured crossover on, see
/// [`auto_uses_gpu`]). Returns the solver backend and the adapter in use (GPU only).
fn choose_backend(
    flag: Option<Backend>,
    job: &Job,
    faces: usize,
    quiet: bool,
) -> Result<(SolverBackend, Option<String>), Error> {
    let name = backend_name(flag, job);
    if !BACKENDS.contains(&name.as_str()) {
        return Err(Error::bad(format!(
            "unknown backend '{name}' (from METRICDEFORM_BACKEND or the job): expected auto, cpu or gpu"
        )));
    }
    let choice = choose(&name, faces)?;
    if let Some(note) = &choice.note {
        // A fallback or a warning is said even under --quiet (contract).
        if choice.note_always || !quiet {
            eprintln!("{note}");
        }
    }
    Ok((choice.backend, choice.adapter))
}

/// The job's name in messages: its file, or the demo.
fn job_name(job: &Job) -> String {
    job.path
        .as_ref()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| "the demo job".into())
}

/// Every file a run reads: the mesh, the job file and any `faces_file`.
fn input_files(job: &Job) -> Vec<(String, PathBuf)> {
    let mut inputs = vec![("the input mesh".to_string(), job.mesh_path())];
    if let Some(p) = &job.path {
        inputs.push(("the job file".to_string(), p.clone()));
    }
    let regions = job
        .spec
        .constraint
        .iter()
        .filter_map(|c| c.region.as_ref())
        .chain(job.spec.handle.iter().filter_map(|h| h.region.as_ref()))
        .chain(job.spec.curvature.iter().map(|c| &c.region));
    for r in regions {
        if let Some(f) = &r.faces_file {
            inputs.push(("a faces_file of the job".to_string(), job.resolve_path(f)));
        }
    }
    inputs
}

/// Contract: `--out` and `--report` differ from each other and from every
/// input, name files (not directories) in existing directories. Checked before
/// any work, so that a bad path costs nothing and nothing is written.
fn check_outputs(job: &Job, outputs: &[(&str, &Path)]) -> Result<(), Error> {
    let inputs = input_files(job);
    for (i, (what, path)) in outputs.iter().enumerate() {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        if !dir.is_dir() {
            return Err(Error::bad(format!(
                "{what} {}: directory {} does not exist; create it or choose another path",
                path.display(),
                dir.display()
            )));
        }
        if path.is_dir() {
            return Err(Error::bad(format!(
                "{what} {} is a directory; give a file name",
                path.display()
            )));
        }
        for (input, ipath) in &inputs {
            if output::same_file(path, ipath) {
                return Err(Error::bad(format!(
                    "{what} {} is {input} ({}): inputs are never overwritten; choose another path",
                    path.display(),
                    ipath.display()
                )));
            }
        }
        for (other, opath) in &outputs[..i] {
            if output::same_file(path, opath) {
                return Err(Error::bad(format!(
                    "{what} {} is also the {other}: give them different paths",
                    path.display()
                )));
            }
        }
    }
    Ok(())
}

fn run(job: &Job, args: &RunArgs) -> Result<u8, Error> {
    let t0 = Instant::now();
    let out_path = args.out.clone().unwrap_or_else(|| job.output_path());
    let mut outputs = vec![("output mesh", out_path.as_path())];
    if let Some(r) = &args.report {
        outputs.push(("report", r.as_path()));
    }
    if let Some(r) = &args.picture.render {
        outputs.push(("picture", r.as_path()));
    }
    check_outputs(job, &outputs)?;
    let mut options = Options::from_spec(&job.spec.solver);
    options.preview = args.preview;
    // A run asked to be on the GPU opens its device while the mesh is read
    // (`main` ends one not taken).
    if backend_name(args.backend, job) == "gpu" {
        solver_gpu::open_ahead();
    }
    let problem = Problem::load(job)?;
    print_warnings(&problem.warnings);
    if problem.constraints.is_empty() && problem.handles.is_empty() && problem.curvature.is_empty()
    {
        return Err(Error::bad(format!(
            "{}: no [[constraint]], [[handle]] or [[curvature]]: nothing to deform. \
             Add a constraint (`metricdeform measure` prints the input's metrics)",
            job_name(job)
        )));
    }
    let (backend, adapter) =
        choose_backend(args.backend, job, problem.mesh.num_faces(), args.quiet)?;
    options.backend = backend;
    let t_load = t0.elapsed().as_secs_f64();

    let bar = progress_bar(args.quiet);
    let plain = !args.quiet && !std::io::stderr().is_terminal();
    let mut on_progress = |p: Progress| {
        let msg = match p {
            Progress::ScaleDriven { iteration, max_error, max_scale_change } => format!(
                "scale-driven iteration {iteration}: metrics off by at most {:.3e} %, max |s-1| {max_scale_change:.3e}",
                max_error * 100.0
            ),
            Progress::FineTune { iteration, max_error } => {
                format!("fine-tune iteration {iteration}: metrics off by at most {:.3e} %", max_error * 100.0)
            }
        };
        if plain {
            eprintln!("{msg}");
        } else if let Some(b) = &bar {
            b.set_message(msg);
            b.tick();
        }
    };
    let outcome = deform(&problem, &options, &mut on_progress)?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let mut x = outcome.positions.clone();
    if out_path
        .extension()
        .map(|e| e.eq_ignore_ascii_case("stl"))
        .unwrap_or(false)
    {
        // STL stores f32: measure what is written.
        for p in x.iter_mut() {
            *p = p.as_vec3().as_dvec3();
        }
    }
    let input = &problem.mesh.positions;
    // PLY output carries per-face scale and distortion and per-vertex
    // displacement (of the positions written: PLY stores f64) unless the job
    // says `[output] attributes = false`; OBJ and STL stay plain geometry.
    let ply = out_path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
    let attributes = (ply && job.output_attributes())
        .then(|| io::PlyAttributes::deformation(&problem.mesh, input, &outcome.positions));
    let mesh_bytes = io::encode_mesh_with(
        &out_path,
        &problem.mesh,
        &outcome.positions,
        Some(&problem.mesh_path),
        attributes.as_ref(),
    )?;
    let preview = args.preview.is_some();
    let report = Report::of_deformation(
        &problem,
        options.tolerance,
        &outcome,
        &x,
        &metricdeform::distortion::face_distortions(&problem.mesh, input, &x),
        RunInfo {
            output: Some(out_path.display().to_string()),
            backend: backend.name().to_string(),
            adapter,
            load_seconds: t_load,
            total_seconds: t0.elapsed().as_secs_f64(),
            preview,
        },
    );
    let rows = &report.constraints;
    let reason = report.reason.clone();
    let satisfied = report.satisfied;
    let displacement = report.displacement;
    let (qc_mean, qc_max) = (
        report.distortion.quasi_conformal_mean,
        report.distortion.quasi_conformal_max,
    );
    // The mesh and the report as a pair: both or neither.
    let mut staged = vec![output::stage(&out_path, &mesh_bytes)?];
    if let Some(path) = &args.report {
        staged.push(output::stage(path, &report_json(&report)?)?);
    }
    if let Some(path) = &args.picture.render {
        let notes = annotations(&problem, |i| {
            format!(
                "{} -> {}",
                render::format_value(rows[i].original),
                render::format_value(rows[i].result)
            )
        });
        let png = render::render_deformation(
            &problem.mesh,
            &problem.mesh.positions,
            &x,
            &notes,
            &args.picture.params(),
        )?;
        staged.push(output::stage(path, &png)?);
    }
    output::commit(staged)?;
    print!("{}", table(rows));
    println!(
        "distortion: quasi-conformal mean {:.4}, max {:.4}; displacement (% of the bbox diagonal): \
         max {:.4}, mean {:.4}, p99 {:.4}; iterations: {} scale-driven, {} fine-tune; {:.2} s",
        qc_mean,
        qc_max,
        displacement.max_percent,
        displacement.mean_percent,
        displacement.p99_percent,
        report.iterations.scale_driven,
        report.iterations.fine_tune,
        report.seconds.total
    );
    println!("wrote {}", out_path.display());
    if let Some(path) = &args.report {
        println!("wrote {}", path.display());
    }
    if let Some(path) = &args.picture.render {
        println!("wrote {}", path.display());
    }
    if preview {
        println!(
            "PREVIEW: the scale-driven phase stopped after {} iteration(s) and the fine-tune was skipped; \
             the metrics are not expected to hold yet. Run without --preview for the exact result.",
            outcome.scale_driven_iterations
        );
        return Ok(0);
    }
    if let Some(r) = &reason {
        println!("NOT SATISFIED: {r}");
        eprintln!("warning: {r}");
    }
    Ok(if satisfied { 0 } else { 3 })
}

fn measure(job: &Job, report_path: Option<&Path>, picture: &PictureArgs) -> Result<u8, Error> {
    let t0 = Instant::now();
    let mut outputs = Vec::new();
    if let Some(r) = report_path {
        outputs.push(("report", r));
    }
    if let Some(r) = &picture.render {
        outputs.push(("picture", r.as_path()));
    }
    check_outputs(job, &outputs)?;
    let options = Options::from_spec(&job.spec.solver);
    let problem = Problem::load(job)?;
    print_warnings(&problem.warnings);
    let x = &problem.mesh.positions;
    let report = Report::of_measurement(
        &problem,
        options.tolerance,
        RunInfo {
            backend: "none".into(),
            load_seconds: t0.elapsed().as_secs_f64(),
            total_seconds: t0.elapsed().as_secs_f64(),
            ..RunInfo::default()
        },
    );
    print!("{}", table(&report.constraints));
    let mut staged = Vec::new();
    if let Some(p) = report_path {
        staged.push(output::stage(p, &report_json(&report)?)?);
    }
    if let Some(path) = &picture.render {
        let notes = annotations(&problem, |i| {
            render::format_value(report.constraints[i].original)
        });
        let png = render::render_selections(&problem.mesh, x, &notes, &picture.params())?;
        staged.push(output::stage(path, &png)?);
    }
    output::commit(staged)?;
    if let Some(path) = &picture.render {
        println!("wrote {}", path.display());
    }
    Ok(0)
}

/// Every selection of the problem for a picture: each constraint named with
/// its kind and `values(i)` (constraint `i`'s numbers), then each handle and
/// curvature region.
fn annotations(problem: &Problem, values: impl Fn(usize) -> String) -> Vec<render::Annotation<'_>> {
    use metricdeform::metrics::Selection;
    let mut notes: Vec<render::Annotation> = problem
        .constraints
        .iter()
        .enumerate()
        .map(|(i, c)| render::Annotation {
            name: c.name.clone(),
            kind: c.kind.to_string(),
            values: values(i),
            marked: match &c.selection {
                Selection::Curve(curve) => render::Marked::Curve(curve),
                Selection::Region(region) => render::Marked::Faces(&region.faces),
                Selection::Whole => render::Marked::Whole,
            },
        })
        .collect();
    if !problem.handles.is_empty() {
        notes.push(render::Annotation {
            name: "handles".into(),
            kind: "handle".into(),
            values: format!("{} vertices", problem.handles.len()),
            marked: render::Marked::Vertices(problem.handles.iter().map(|h| h.vertex).collect()),
        });
    }
    for (i, c) in problem.curvature.iter().enumerate() {
        let name = metricdeform::problem::curvature_label(i);
        notes.push(render::Annotation {
            name,
            kind: "curvature".into(),
            values: format!("mean curvature x {}", render::format_value(c.scale)),
            marked: render::Marked::Vertices(c.vertices.clone()),
        });
    }
    notes
}

/// The input check's warnings (faces handled rather than refused): shown
/// even under --quiet.
fn print_warnings(warnings: &[String]) {
    for w in warnings {
        eprintln!("warning: {w}");
    }
}

fn report_json(report: &Report) -> Result<Vec<u8>, Error> {
    let text = serde_json::to_string_pretty(report).map_err(|e| Error::Internal(e.to_string()))?;
    Ok((text + "\n").into_bytes())
}

fn progress_bar(quiet: bool) -> Option<ProgressBar> {
    if quiet || !std::io::stderr().is_terminal() {
        return None;
    }
    let b = ProgressBar::new_spinner();
    b.set_style(ProgressStyle::with_template("{spinner} [{elapsed}] {msg}").unwrap());
    Some(b)
}
