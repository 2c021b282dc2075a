//! The job file (contract: "Job file"): TOML (`.toml`) or JSON (`.json`), same schema.
//!
//! Every struct rejects unknown fields, so a misspelt key is an error and never
//! silently ignored. Paths inside the job are relative to the job file's folder.
//! [`Job::load`] parses and validates everything that can be checked without the
//! mesh; checks against the mesh (indices, empty selections) happen in
//! [`crate::selection`].

use crate::error::{Error, Result};
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::pipeline::Options;
use crate::problem::{
    constraint_label as label_of, curvature_label, handle_label, Curvature, Demand, Handle, Metric,
    Problem, Target,
};
use crate::selection::{self, check_faces, Curve, FaceSet, Region, SurfaceCurve};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

pub use crate::metrics::MetricKind;

/// The whole job file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// Input mesh (.obj, .ply or .stl), relative to the job file.
    pub mesh: PathBuf,
    /// Output mesh: a path (`output = "x.ply"`) or a table `[output]` with an
    /// optional `path` and `attributes`. Default path `<mesh stem>.deformed.<ext>`
    /// beside the job file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output: Option<OutputSpec>,
    #[serde(default)]
    pub constraint: Vec<ConstraintSpec>,
    #[serde(default)]
    pub handle: Vec<HandleSpec>,
    #[serde(default)]
    pub curvature: Vec<CurvatureSpec>,
    #[serde(default)]
    pub solver: SolverSpec,
}

/// The job's `output`: either a path, or a table `{ path, attributes }`.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum OutputSpec {
    /// `output = "x.ply"`.
    Path(PathBuf),
    /// `[output]` with `path` and `attributes`, both optional.
    Table(OutputTable),
}

/// The table form of `output`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputTable {
    /// Output mesh path; default `<mesh stem>.deformed.<ext>` beside the job file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<PathBuf>,
    /// PLY output carries the face properties `scale` and `distortion` and the
    /// vertex properties `dx dy dz` (default true); OBJ and STL never do.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attributes: Option<bool>,
}

impl OutputSpec {
    /// The path given, if any.
    pub fn path(&self) -> Option<&Path> {
        match self {
            OutputSpec::Path(p) => Some(p),
            OutputSpec::Table(t) => t.path.as_deref(),
        }
    }

    /// Whether PLY output carries the attributes (default true).
    pub fn attributes(&self) -> bool {
        match self {
            OutputSpec::Path(_) => true,
            OutputSpec::Table(t) => t.attributes.unwrap_or(true),
        }
    }
}

/// By hand rather than `untagged`, whose only message is "did not match any
/// variant": a string is a path, a table is read as [`OutputTable`] (unknown
/// keys named), anything else is told what is expected.
impl<'de> Deserialize<'de> for OutputSpec {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = OutputSpec;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str(
                    "`output` as a path string (output = \"x.ply\") or a table \
                     ([output] with optional path = \"x.ply\" and attributes = true/false)",
                )
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> std::result::Result<OutputSpec, E> {
                Ok(OutputSpec::Path(PathBuf::from(v)))
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                map: A,
            ) -> std::result::Result<OutputSpec, A::Error> {
                OutputTable::deserialize(serde::de::value::MapAccessDeserializer::new(map))
                    .map(OutputSpec::Table)
            }
        }
        d.deserialize_any(V)
    }
}

/// One `[[constraint]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConstraintSpec {
    pub kind: MetricKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Required for `length`, forbidden otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curve: Option<CurveSpec>,
    /// Required for `area`, forbidden otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<RegionSpec>,
    /// Target = scale * original.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<f64>,
    /// Absolute target. Neither scale nor value: keep the original.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<f64>,
}

/// A curve on the input surface; exactly one of `plane`, `path`, `points`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurveSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<PlaneSpec>,
    /// Vertices the shortest edge path runs through, in order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<Vec<usize>>,
    /// Only with `path`: return to the first vertex.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub closed: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points: Option<Vec<PointSpec>>,
}

/// A plane `{ origin, normal }` (normal need not be unit length).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaneSpec {
    pub origin: [f64; 3],
    pub normal: [f64; 3],
}

/// A surface point: barycentric coordinates in one face.
pub type PointSpec = selection::FacePoint;

/// A set of faces of the input mesh; exactly one field given.
/// `vertices` is only valid for handles.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegionSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub faces: Option<Vec<usize>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub faces_file: Option<PathBuf>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sphere: Option<SphereSpec>,
    #[serde(rename = "box", default, skip_serializing_if = "Option::is_none")]
    pub box_: Option<BoxSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vertices: Option<Vec<usize>>,
}

/// Faces whose centroid lies within `radius` of `center`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SphereSpec {
    pub center: [f64; 3],
    pub radius: f64,
}

/// Faces whose centroid lies inside the axis-aligned box.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

/// One `[[handle]]` (paper Sec. 5.2, E_p): exactly one of `region` / `vertices`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HandleSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<RegionSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vertices: Option<Vec<usize>>,
    /// Displacement of the handle; default zero (hold in place).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub translate: Option<[f64; 3]>,
}

/// One `[[curvature]]` (paper Eq. 21).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurvatureSpec {
    pub region: RegionSpec,
    pub scale: f64,
}

/// `[solver]`: every field optional.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SolverSpec {
    /// `auto` | `cpu` | `gpu`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub backend: Option<String>,
    /// Relative metric error the run must reach (> 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_iterations: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub weights: Option<WeightsSpec>,
    /// `per_kind` | `per_constraint`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub multipliers: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fine_tune_iterations: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scale_threshold: Option<f64>,
    /// `area` | `uniform`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub regulariser: Option<String>,
    /// `scaled` | `literal`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub curvature_target: Option<String>,
    /// `area` | `tetrahedra`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub volume_share: Option<String>,
    /// `auto` | `anderson` | `none` (the scale-driven iteration as in the paper).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub acceleration: Option<String>,
}

/// Energy weights (all >= 0).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WeightsSpec {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_f: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_m: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_l: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_d: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_r: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k_p: Option<f64>,
}

/// Allowed values of the solver's string options.
pub const BACKENDS: &[&str] = &["auto", "cpu", "gpu"];
pub const MULTIPLIERS: &[&str] = &["per_kind", "per_constraint"];
pub const REGULARISERS: &[&str] = &["area", "uniform"];
pub const CURVATURE_TARGETS: &[&str] = &["scaled", "literal"];
pub const VOLUME_SHARES: &[&str] = &["area", "tetrahedra"];
pub const ACCELERATIONS: &[&str] = &["auto", "anderson", "none"];

/// Syntax of a job text.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobFormat {
    Toml,
    Json,
}

impl JobFormat {
    /// Format from a file name's extension (`.toml` / `.json`, any case).
    pub fn from_path(path: &Path) -> Option<JobFormat> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "toml" => Some(JobFormat::Toml),
            "json" => Some(JobFormat::Json),
            _ => None,
        }
    }
}

/// A parsed and validated job.
#[derive(Clone, Debug, PartialEq)]
pub struct Job {
    /// The job file, if it came from one.
    pub path: Option<PathBuf>,
    /// Folder that relative paths in the job are resolved against.
    pub dir: PathBuf,
    pub spec: JobSpec,
    /// What bad-input messages call the job: the job file's path, or the `origin`
    /// given to [`Job::from_str`].
    pub origin: String,
}

impl Job {
    /// Read, parse and validate a job file. A missing/unreadable file is `Error::Io`;
    /// anything wrong with its contents is `Error::BadInput` naming the file.
    pub fn load(path: &Path) -> Result<Job> {
        let origin = path.display().to_string();
        let format = JobFormat::from_path(path).ok_or_else(|| {
            Error::bad(format!(
                "{origin}: unknown job file type (expected a .toml or .json file)"
            ))
        })?;
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let mut job = Job::from_str(&text, format, &dir, &origin)?;
        job.path = Some(path.to_path_buf());
        Ok(job)
    }

    /// Parse and validate job text (e.g. the embedded demo). `dir` is the folder
    /// relative paths are resolved against; `origin` names the text in messages.
    pub fn from_str(text: &str, format: JobFormat, dir: &Path, origin: &str) -> Result<Job> {
        // TOML knows LF and CRLF line ends only: read old Mac files (lone CR) too.
        let text = if text.contains('\r') {
            std::borrow::Cow::Owned(lone_cr_to_lf(text))
        } else {
            std::borrow::Cow::Borrowed(text)
        };
        let text: &str = &text;
        let spec: JobSpec = match format {
            JobFormat::Toml => toml::from_str(text)
                .map_err(|e| Error::bad(format!("{origin}: {}", e.to_string().trim_end())))?,
            JobFormat::Json => {
                serde_json::from_str(text).map_err(|e| Error::bad(format!("{origin}: {e}")))?
            }
        };
        spec.validate()
            .map_err(|msg| Error::bad(format!("{origin}: {msg}")))?;
        Ok(Job {
            path: None,
            dir: dir.to_path_buf(),
            spec,
            origin: origin.to_string(),
        })
    }

    /// `p` resolved against the job file's folder (absolute paths unchanged).
    pub fn resolve_path(&self, p: &Path) -> PathBuf {
        if p.is_absolute() || self.dir.as_os_str().is_empty() || self.dir == Path::new(".") {
            p.to_path_buf()
        } else {
            self.dir.join(p)
        }
    }

    /// The input mesh's path.
    pub fn mesh_path(&self) -> PathBuf {
        self.resolve_path(&self.spec.mesh)
    }

    /// Whether a PLY output carries the per-face and per-vertex attributes
    /// (`[output] attributes`, default true).
    pub fn output_attributes(&self) -> bool {
        self.spec.output.as_ref().is_none_or(OutputSpec::attributes)
    }

    /// The job's `output` path, else `<mesh stem>.deformed.<mesh ext>` beside the job file.
    pub fn output_path(&self) -> PathBuf {
        if let Some(out) = self.spec.output.as_ref().and_then(OutputSpec::path) {
            return self.resolve_path(out);
        }
        let stem = self
            .spec
            .mesh
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "mesh".to_string());
        let name = match self.spec.mesh.extension() {
            Some(ext) => format!("{stem}.deformed.{}", ext.to_string_lossy()),
            None => format!("{stem}.deformed"),
        };
        self.resolve_path(Path::new(&name))
    }

    /// Name of constraint `i` (0-based index) for messages, numbered from 1 as a
    /// user counts the `[[constraint]]` tables: `constraint 2 ('neck girth')` or
    /// `constraint 2 (length)` for `i = 1`.
    pub fn constraint_label(&self, i: usize) -> String {
        constraint_label(i, &self.spec.constraint[i])
    }
}

/// `constraint N ('name')`, or `constraint N (kind)` when unnamed, N = i + 1.
pub fn constraint_label(i: usize, c: &ConstraintSpec) -> String {
    label_of(i, c.name.as_deref(), c.kind)
}

impl Job {
    /// Reads one of the job's `faces_file`s: whitespace-separated face indices,
    /// `#` comments, each index below `faces`. `what` names its owner.
    pub fn read_faces_file(&self, file: &Path, faces: usize, what: &str) -> Result<Vec<usize>> {
        let path = self.resolve_path(file);
        let text = std::fs::read_to_string(&path).map_err(|e| {
            Error::bad(format!(
                "{what}: cannot read faces_file {}: {e}",
                path.display()
            ))
        })?;
        let mut list = Vec::new();
        // Lines end in LF, CRLF or a lone CR (old Mac files).
        for line in text.split(['\n', '\r']) {
            let line = line.split('#').next().unwrap_or("");
            for tok in line.split_whitespace() {
                let f: usize = tok.parse().map_err(|_| {
                    Error::bad(format!(
                        "{what}: faces_file {}: '{tok}' is not a face index \
                         (expected whitespace-separated non-negative integers)",
                        path.display()
                    ))
                })?;
                list.push(f);
            }
        }
        let ctx = format!("face index in {}", path.display());
        check_faces(&list, faces, what, &ctx)?;
        Ok(list)
    }

    /// The job's constraints, handles and curvature regions as typed values
    /// for a mesh of `faces` faces (its `faces_file`s are read now).
    pub fn demands(&self, faces: usize) -> Result<(Vec<Demand>, Vec<Handle>, Vec<Curvature>)> {
        let spec = &self.spec;
        let demands = (spec.constraint.iter().enumerate())
            .map(|(i, c)| {
                let what = constraint_label(i, c);
                c.demand(&what, &mut |f| self.read_faces_file(f, faces, &what))
            })
            .collect::<Result<_>>()?;
        let handles = (spec.handle.iter().enumerate())
            .map(|(i, h)| {
                let what = handle_label(i);
                h.handle(&what, &mut |f| self.read_faces_file(f, faces, &what))
            })
            .collect::<Result<_>>()?;
        let curvature = (spec.curvature.iter().enumerate())
            .map(|(i, c)| {
                let what = curvature_label(i);
                c.curvature(&what, &mut |f| self.read_faces_file(f, faces, &what))
            })
            .collect::<Result<_>>()?;
        Ok((demands, handles, curvature))
    }

    /// A bad-input message that does not name the job file yet gets it in front
    /// (contract: bad-input messages name the job file).
    fn naming(&self, e: Error) -> Error {
        match e {
            Error::BadInput(m) if !self.origin.is_empty() && !m.starts_with(&self.origin) => {
                Error::BadInput(format!("{}: {m}", self.origin))
            }
            Error::Io { path, source } if !self.origin.is_empty() => Error::BadInput(format!(
                "{}: cannot read {}: {source}",
                self.origin,
                path.display()
            )),
            e => e,
        }
    }
}

/// The job file front end of [`Problem::new`].
impl Problem {
    /// Read the job's mesh and resolve every selection on it.
    pub fn load(job: &Job) -> Result<Problem> {
        let mesh_path = job.mesh_path();
        let mesh = crate::mesh::io::read_mesh(&mesh_path).map_err(|e| job.naming(e))?;
        Problem::build(job, mesh, &mesh_path)
    }

    /// Resolve the job's selections on an already loaded mesh. Bad-input messages
    /// name the job file.
    pub fn build(job: &Job, mesh: Mesh, mesh_path: &Path) -> Result<Problem> {
        let (demands, handles, curvature) =
            job.demands(mesh.num_faces()).map_err(|e| job.naming(e))?;
        Problem::new(mesh, mesh_path, &demands, &handles, &curvature).map_err(|e| job.naming(e))
    }
}

/// A job's curve resolved on `mesh` ([`selection::build_curve`] of its typed form).
pub fn build_curve(
    spec: &CurveSpec,
    mesh: &Mesh,
    topo: &Topology,
    what: &str,
) -> Result<SurfaceCurve> {
    spec.validate(what).map_err(Error::bad)?;
    let curve = spec
        .curve()
        .ok_or_else(|| Error::bad(format!("{what}: curve is empty")))?;
    selection::build_curve(&curve, mesh, topo, what)
}

/// A job's region resolved on `mesh` ([`selection::build_region`] of its
/// typed form; a `faces_file` is read relative to the job).
pub fn build_region(spec: &RegionSpec, mesh: &Mesh, job: &Job, what: &str) -> Result<FaceSet> {
    spec.validate(what, false).map_err(Error::bad)?;
    let region = spec.region(&mut |f| job.read_faces_file(f, mesh.num_faces(), what))?;
    selection::build_region(&region, mesh, what)
}

/// A job's handle's vertices on `mesh` ([`selection::build_handle_vertices`]
/// of its typed form).
pub fn build_handle_vertices(
    spec: &HandleSpec,
    mesh: &Mesh,
    job: &Job,
    what: &str,
) -> Result<Vec<u32>> {
    let handle = spec.handle(what, &mut |f| {
        job.read_faces_file(f, mesh.num_faces(), what)
    })?;
    selection::build_handle_vertices(&handle.region, mesh, what)
}

/// A number for messages: plain, or in exponent form when very large or small.
fn num(v: f64) -> String {
    let a = v.abs();
    if a != 0.0 && a.is_finite() && !(1e-3..1e6).contains(&a) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// Every `\r` not followed by `\n` turned into `\n`.
fn lone_cr_to_lf(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '\r' && chars.peek() != Some(&'\n') {
            out.push('\n');
        } else {
            out.push(c);
        }
    }
    out
}

fn check_choice(field: &str, value: &Option<String>, allowed: &[&str]) -> Result<(), String> {
    match value {
        Some(v) if !allowed.contains(&v.as_str()) => Err(format!(
            "solver.{field}: unknown value '{v}' (allowed: {})",
            allowed.join(", ")
        )),
        _ => Ok(()),
    }
}

impl JobSpec {
    /// Checks that need no mesh. The message names the constraint/handle and what
    /// is wrong (without the job file's name, which the caller adds). The file
    /// schema's own rules (exactly one of some fields) are checked here; the
    /// values are checked by the typed selections they become
    /// ([`Demand::validate`], [`Handle::validate`], [`Curvature::validate`]).
    pub fn validate(&self) -> Result<(), String> {
        if self.mesh.as_os_str().is_empty() {
            return Err("`mesh` is empty: give the input mesh's path".into());
        }
        if let Some(p) = self.output.as_ref().and_then(OutputSpec::path) {
            if p.as_os_str().is_empty() {
                return Err(
                    "`output` path is empty: give a file name, or leave it out for \
                     <mesh stem>.deformed.<ext> beside the job file"
                        .into(),
                );
            }
        }
        // A faces_file is read only when the problem is built.
        let mut unread = |_: &Path| Ok(Vec::new());
        let message = |e: Error| match e {
            Error::BadInput(m) => m,
            e => e.to_string(),
        };
        for (i, c) in self.constraint.iter().enumerate() {
            let what = constraint_label(i, c);
            c.validate(&what)?;
            c.demand(&what, &mut unread)
                .map_err(message)?
                .validate(&what)?;
        }
        for (i, h) in self.handle.iter().enumerate() {
            let what = handle_label(i);
            h.validate(&what)?;
            h.handle(&what, &mut unread)
                .map_err(message)?
                .validate(&what)?;
        }
        for (i, c) in self.curvature.iter().enumerate() {
            let what = curvature_label(i);
            c.region.validate(&what, false)?;
            c.curvature(&what, &mut unread)
                .map_err(message)?
                .validate(&what)?;
        }
        self.solver.validate()
    }
}

/// Reads a `faces_file` (its path as the job gives it) into face indices.
pub type FacesFileReader<'a> = dyn FnMut(&Path) -> Result<Vec<usize>> + 'a;

impl ConstraintSpec {
    /// The schema's rules: a curve for a length, a region for an area, neither
    /// for a volume; scale or value, not both. `what` names the constraint.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        if self.scale.is_some() && self.value.is_some() {
            return Err(format!("{what}: give either scale or value, not both"));
        }
        match self.kind {
            MetricKind::Length => {
                if self.region.is_some() {
                    return Err(format!(
                        "{what}: a length constraint takes a curve, not a region"
                    ));
                }
                match &self.curve {
                    None => {
                        return Err(format!(
                            "{what}: a length constraint needs a curve \
                             (curve = {{ plane = ... }}, {{ path = [...] }} or {{ points = [...] }})"
                        ))
                    }
                    Some(curve) => curve.validate(what)?,
                }
            }
            MetricKind::Area => {
                if self.curve.is_some() {
                    return Err(format!(
                        "{what}: an area constraint takes a region, not a curve"
                    ));
                }
                match &self.region {
                    None => {
                        return Err(format!(
                            "{what}: an area constraint needs a region \
                             (faces, faces_file, sphere, box or group)"
                        ))
                    }
                    Some(region) => region.validate(what, false)?,
                }
            }
            MetricKind::Volume => {
                if self.curve.is_some() || self.region.is_some() {
                    return Err(format!(
                        "{what}: a volume constraint applies to the whole mesh; \
                         it takes neither curve nor region"
                    ));
                }
            }
        }
        Ok(())
    }

    /// The typed constraint ([`ConstraintSpec::validate`] first).
    pub fn demand(&self, what: &str, faces_file: &mut FacesFileReader) -> Result<Demand> {
        self.validate(what).map_err(Error::bad)?;
        let metric =
            match self.kind {
                MetricKind::Length => {
                    Metric::Length(self.curve.as_ref().and_then(CurveSpec::curve).ok_or_else(
                        || Error::bad(format!("{what}: a length constraint needs a curve")),
                    )?)
                }
                MetricKind::Area => Metric::Area(
                    self.region
                        .as_ref()
                        .ok_or_else(|| {
                            Error::bad(format!("{what}: an area constraint needs a region"))
                        })?
                        .region(faces_file)?,
                ),
                MetricKind::Volume => Metric::Volume,
            };
        let target = match (self.scale, self.value) {
            (Some(s), _) => Target::Scale(s),
            (None, Some(v)) => Target::Value(v),
            (None, None) => Target::Keep,
        };
        Ok(Demand {
            name: self.name.clone(),
            metric,
            target,
        })
    }
}

impl CurveSpec {
    /// Exactly one of plane/path/points; `closed` only with path.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        let n = self.plane.is_some() as usize
            + self.path.is_some() as usize
            + self.points.is_some() as usize;
        if n != 1 {
            return Err(format!(
                "{what}: a curve needs exactly one of plane, path or points (got {n})"
            ));
        }
        if self.closed.is_some() && self.path.is_none() {
            return Err(format!(
                "{what}: curve `closed` is only allowed with `path`"
            ));
        }
        Ok(())
    }

    /// The typed curve: the first of plane, path, points given.
    pub fn curve(&self) -> Option<Curve> {
        if let Some(p) = &self.plane {
            Some(Curve::Plane {
                origin: p.origin,
                normal: p.normal,
            })
        } else if let Some(path) = &self.path {
            Some(Curve::Path {
                vertices: path.clone(),
                closed: self.closed.unwrap_or(false),
            })
        } else {
            self.points.clone().map(Curve::Points)
        }
    }
}

impl RegionSpec {
    /// Names of the fields that are set, in schema order.
    pub fn given(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if self.faces.is_some() {
            v.push("faces");
        }
        if self.faces_file.is_some() {
            v.push("faces_file");
        }
        if self.sphere.is_some() {
            v.push("sphere");
        }
        if self.box_.is_some() {
            v.push("box");
        }
        if self.group.is_some() {
            v.push("group");
        }
        if self.vertices.is_some() {
            v.push("vertices");
        }
        v
    }

    /// Exactly one kind (`vertices` counted only when `allow_vertices`, for
    /// handles; [`Region::validate`] refuses it elsewhere); a non-empty
    /// `faces_file`.
    pub fn validate(&self, what: &str, allow_vertices: bool) -> Result<(), String> {
        let given = self.given();
        let kinds = if allow_vertices {
            "faces, faces_file, sphere, box, group or vertices"
        } else {
            "faces, faces_file, sphere, box or group"
        };
        if given.is_empty() {
            return Err(format!("{what}: region is empty: give one of {kinds}"));
        }
        if given.len() > 1 {
            return Err(format!(
                "{what}: region gives {}; give exactly one of {kinds}",
                given.join(" and ")
            ));
        }
        if let Some(f) = &self.faces_file {
            if f.as_os_str().is_empty() {
                return Err(format!("{what}: faces_file is empty"));
            }
        }
        Ok(())
    }

    /// The typed region, a `faces_file` read through `faces_file` into
    /// [`Region::Faces`].
    pub fn region(&self, faces_file: &mut FacesFileReader) -> Result<Region> {
        Ok(if let Some(list) = &self.faces {
            Region::Faces(list.clone())
        } else if let Some(file) = &self.faces_file {
            Region::Faces(faces_file(file)?)
        } else if let Some(s) = &self.sphere {
            Region::Sphere {
                center: s.center,
                radius: s.radius,
            }
        } else if let Some(b) = &self.box_ {
            Region::Box {
                min: b.min,
                max: b.max,
            }
        } else if let Some(g) = &self.group {
            Region::Group(g.clone())
        } else if let Some(v) = &self.vertices {
            Region::Vertices(v.clone())
        } else {
            return Err(Error::bad("region is empty"));
        })
    }
}

impl HandleSpec {
    /// Exactly one of region/vertices.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        match (&self.region, &self.vertices) {
            (Some(_), Some(_)) => {
                return Err(format!("{what}: give either region or vertices, not both"))
            }
            (None, None) => return Err(format!("{what}: needs a region or vertices")),
            (Some(r), None) => r.validate(what, true)?,
            (None, Some(_)) => {}
        }
        Ok(())
    }

    /// The translation, zero when not given.
    pub fn translation(&self) -> [f64; 3] {
        self.translate.unwrap_or([0.0; 3])
    }

    /// The typed handle ([`HandleSpec::validate`] first).
    pub fn handle(&self, what: &str, faces_file: &mut FacesFileReader) -> Result<Handle> {
        self.validate(what).map_err(Error::bad)?;
        let region = match (&self.vertices, &self.region) {
            (Some(v), _) => Region::Vertices(v.clone()),
            (None, Some(r)) => r.region(faces_file)?,
            (None, None) => return Err(Error::bad(format!("{what}: needs a region or vertices"))),
        };
        Ok(Handle {
            region,
            translate: self.translation(),
        })
    }
}

impl CurvatureSpec {
    /// The typed curvature region.
    pub fn curvature(&self, what: &str, faces_file: &mut FacesFileReader) -> Result<Curvature> {
        self.region.validate(what, false).map_err(Error::bad)?;
        Ok(Curvature {
            region: self.region.region(faces_file)?,
            scale: self.scale,
        })
    }
}

impl SolverSpec {
    pub fn validate(&self) -> Result<(), String> {
        check_choice("backend", &self.backend, BACKENDS)?;
        check_choice("multipliers", &self.multipliers, MULTIPLIERS)?;
        check_choice("regulariser", &self.regulariser, REGULARISERS)?;
        check_choice(
            "curvature_target",
            &self.curvature_target,
            CURVATURE_TARGETS,
        )?;
        check_choice("volume_share", &self.volume_share, VOLUME_SHARES)?;
        check_choice("acceleration", &self.acceleration, ACCELERATIONS)?;
        if let Some(t) = self.tolerance {
            if !(t.is_finite() && t > 0.0) {
                return Err(format!(
                    "solver.tolerance must be a finite number > 0 (got {t})"
                ));
            }
        }
        if let Some(t) = self.scale_threshold {
            if !(t.is_finite() && t >= 0.0) {
                return Err(format!(
                    "solver.scale_threshold must be a finite number >= 0 (got {t})"
                ));
            }
        }
        if let Some(w) = &self.weights {
            w.validate()?;
        }
        Ok(())
    }
}

/// Largest accepted energy weight: beyond it the systems lose every digit of the
/// other terms (`k_f = 1e300` made the shape system numerically singular).
pub const MAX_WEIGHT: f64 = 1e12;

/// Smallest accepted ratio of the frame weight `k_f` to the largest other shape
/// weight (`k_m`, `k_l`, `k_p`).
pub const MIN_FRAME_RATIO: f64 = 1e-12;

impl WeightsSpec {
    /// Every weight finite, in `[0, MAX_WEIGHT]`; the frame weight `k_f` positive
    /// and not negligible next to the other shape weights. Why `k_f`: the shape
    /// system (Eq. 7) is positive definite (with one vertex per component held)
    /// through E_f alone, a Dirichlet energy; E_m vanishes on harmonic motions of an
    /// open mesh, E_l on tangential ones, E_p away from the handles. The
    /// scale-factor system (Eq. 3) stays positive definite with any `k_d, k_r >= 0`
    /// (`k_r = 0` is replaced by a tiny floor), and the fine-tune keeps its own
    /// weights (1, 100, 100). Unset weights keep their defaults
    /// (`k_f` 1000, `k_m` 1, `k_l` 1, `k_d` 1, `k_r` 0.01, `k_p` 1000).
    pub fn validate(&self) -> Result<(), String> {
        let all = [
            ("k_f", self.k_f),
            ("k_m", self.k_m),
            ("k_l", self.k_l),
            ("k_d", self.k_d),
            ("k_r", self.k_r),
            ("k_p", self.k_p),
        ];
        let bad: Vec<String> = all
            .iter()
            .filter_map(|&(name, v)| {
                let v = v?;
                (!(v.is_finite() && (0.0..=MAX_WEIGHT).contains(&v)))
                    .then(|| format!("{name} = {}", num(v)))
            })
            .collect();
        if !bad.is_empty() {
            return Err(format!(
                "solver.weights: {} (each weight must be a finite number between 0 and \
                 {MAX_WEIGHT:e}; the defaults are k_f = 1000, k_m = 1, k_l = 1, k_d = 1, \
                 k_r = 0.01, k_p = 1000)",
                bad.join(", ")
            ));
        }
        let k_f = self.k_f.unwrap_or(1000.0);
        let others = [
            ("k_m", self.k_m.unwrap_or(1.0)),
            ("k_l", self.k_l.unwrap_or(1.0)),
            ("k_p", self.k_p.unwrap_or(1000.0)),
        ];
        let (big_name, big) =
            others
                .iter()
                .copied()
                .fold(("k_m", 0.0f64), |m, o| if o.1 > m.1 { o } else { m });
        if k_f <= 0.0 {
            let zero: Vec<&str> = all
                .iter()
                .filter(|(_, v)| *v == Some(0.0))
                .map(|(n, _)| *n)
                .collect();
            return Err(format!(
                "solver.weights.k_f = 0 makes the shape system singular{}: the frame \
                 weight k_f must be > 0 (it alone makes the system positive definite; \
                 default 1000)",
                if zero.len() > 1 {
                    format!(" (zero weights: {})", zero.join(", "))
                } else {
                    String::new()
                }
            ));
        }
        if k_f < MIN_FRAME_RATIO * big {
            return Err(format!(
                "solver.weights.k_f = {} is negligible next to {big_name} = {} \
                 (ratio below {MIN_FRAME_RATIO:e}): the shape system is numerically \
                 singular; raise k_f or lower {big_name}",
                num(k_f),
                num(big)
            ));
        }
        Ok(())
    }
}

/// The `[solver]` table's settings.
impl Options {
    /// Defaults overridden by the job's `[solver]` table.
    pub fn from_spec(spec: &SolverSpec) -> Options {
        let mut o = Options::default();
        if let Some(t) = spec.tolerance {
            o.tolerance = t;
        }
        if let Some(m) = spec.max_iterations {
            o.max_iterations = m;
        }
        if let Some(m) = spec.fine_tune_iterations {
            o.fine_tune_iterations = m;
        }
        if let Some(t) = spec.scale_threshold {
            o.scale_threshold = t;
        }
        if let Some(w) = &spec.weights {
            if let Some(v) = w.k_f {
                o.shape.k_f = v;
            }
            if let Some(v) = w.k_m {
                o.shape.k_m = v;
            }
            if let Some(v) = w.k_l {
                o.shape.k_l = v;
            }
            if let Some(v) = w.k_p {
                o.shape.k_p = v;
                o.fine_tune.k_p = v;
            }
            if let Some(v) = w.k_d {
                o.k_d = v;
            }
            if let Some(v) = w.k_r {
                o.k_r = v;
            }
        }
        match spec.multipliers.as_deref() {
            Some("per_kind") => o.multipliers = crate::constrained_step::Multipliers::PerKind,
            _ => o.multipliers = crate::constrained_step::Multipliers::PerConstraint,
        }
        if spec.regulariser.as_deref() == Some("uniform") {
            o.regulariser = crate::scale_factors::Regulariser::Uniform;
        }
        if spec.curvature_target.as_deref() == Some("literal") {
            o.curvature_target = crate::shape::CurvatureTarget::Literal;
        }
        if spec.volume_share.as_deref() == Some("tetrahedra") {
            o.volume_share = crate::metrics::VolumeShare::Tetrahedra;
        }
        match spec.acceleration.as_deref() {
            Some("none") => o.anderson_depth = 0,
            Some("anderson") => o.anderson_from_faces = 0,
            _ => {}
        }
        o
    }
}
