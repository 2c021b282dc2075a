//! The job file (contract: "Job file"): TOML (`.toml`) or JSON (`.json`), same schema.
//!
//! Every struct rejects unknown fields, so a misspelt key is an error and never
//! silently ignored. Paths inside the job are relative to the job file's folder.
//! [`Job::load`] parses and validates everything that can be checked without the
//! mesh; checks against the mesh (indices, empty selections) happen in
//! [`crate::selection`].

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

/// Which metric a constraint demands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MetricKind {
    Length,
    Area,
    Volume,
}

impl fmt::Display for MetricKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MetricKind::Length => "length",
            MetricKind::Area => "area",
            MetricKind::Volume => "volume",
        })
    }
}

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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointSpec {
    pub face: usize,
    pub bary: [f64; 3],
}

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

/// `constraint N ('name')`, or `constraint N (kind)` when unnamed; N = i + 1 is
/// 1-based (the contract: constraints by name or 1-based number).
pub fn constraint_label(i: usize, c: &ConstraintSpec) -> String {
    match &c.name {
        Some(name) => format!("constraint {} ('{name}')", i + 1),
        None => format!("constraint {} ({})", i + 1, c.kind),
    }
}

/// `handle N` for the 0-based index `i`, N 1-based.
pub fn handle_label(i: usize) -> String {
    format!("handle {}", i + 1)
}

/// `curvature N` for the 0-based index `i`, N 1-based.
pub fn curvature_label(i: usize) -> String {
    format!("curvature {}", i + 1)
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

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
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
    /// is wrong (without the job file's name, which the caller adds).
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
        for (i, c) in self.constraint.iter().enumerate() {
            c.validate(&constraint_label(i, c))?;
        }
        for (i, h) in self.handle.iter().enumerate() {
            h.validate(&handle_label(i))?;
        }
        for (i, c) in self.curvature.iter().enumerate() {
            let what = curvature_label(i);
            c.region.validate(&what, false)?;
            if !c.scale.is_finite() {
                return Err(format!("{what}: scale must be a finite number"));
            }
        }
        self.solver.validate()
    }
}

impl ConstraintSpec {
    /// Checks that need no mesh; `what` names the constraint.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        if self.scale.is_some() && self.value.is_some() {
            return Err(format!("{what}: give either scale or value, not both"));
        }
        for (field, v) in [("scale", self.scale), ("value", self.value)] {
            if let Some(v) = v {
                if !v.is_finite() || v <= 0.0 {
                    return Err(format!(
                        "{what}: {field} must be a finite number > 0 (got {v})"
                    ));
                }
            }
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
}

impl CurveSpec {
    /// Exactly one of plane/path/points; `closed` only with path; finite numbers.
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
        if let Some(p) = &self.plane {
            if !finite3(&p.origin) || !finite3(&p.normal) {
                return Err(format!("{what}: plane origin and normal must be finite"));
            }
            if p.normal.iter().all(|&x| x == 0.0) {
                return Err(format!("{what}: plane normal is zero"));
            }
        }
        if let Some(path) = &self.path {
            if path.len() < 2 {
                return Err(format!(
                    "{what}: a path needs at least 2 vertices (got {})",
                    path.len()
                ));
            }
        }
        if let Some(points) = &self.points {
            if points.len() < 2 {
                return Err(format!(
                    "{what}: a curve needs at least 2 points (got {})",
                    points.len()
                ));
            }
        }
        Ok(())
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

    /// Exactly one kind; `vertices` only when `allow_vertices` (handles); sane numbers.
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
        if self.vertices.is_some() && !allow_vertices {
            return Err(format!(
                "{what}: region `vertices` is only allowed for handles; \
                 use one of {kinds}"
            ));
        }
        if let Some(s) = &self.sphere {
            if !finite3(&s.center) {
                return Err(format!("{what}: sphere center must be finite"));
            }
            if !(s.radius.is_finite() && s.radius > 0.0) {
                return Err(format!(
                    "{what}: sphere radius must be a finite number > 0 (got {})",
                    s.radius
                ));
            }
        }
        if let Some(b) = &self.box_ {
            if !finite3(&b.min) || !finite3(&b.max) {
                return Err(format!("{what}: box min and max must be finite"));
            }
            if (0..3).any(|k| b.min[k] > b.max[k]) {
                return Err(format!(
                    "{what}: box min {:?} exceeds max {:?} in some coordinate",
                    b.min, b.max
                ));
            }
        }
        if let Some(f) = &self.faces_file {
            if f.as_os_str().is_empty() {
                return Err(format!("{what}: faces_file is empty"));
            }
        }
        Ok(())
    }
}

impl HandleSpec {
    /// Exactly one of region/vertices; finite translation.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        match (&self.region, &self.vertices) {
            (Some(_), Some(_)) => {
                return Err(format!("{what}: give either region or vertices, not both"))
            }
            (None, None) => return Err(format!("{what}: needs a region or vertices")),
            (Some(r), None) => r.validate(what, true)?,
            (None, Some(_)) => {}
        }
        if let Some(t) = &self.translate {
            if !finite3(t) {
                return Err(format!("{what}: translate must be finite"));
            }
        }
        Ok(())
    }

    /// The translation, zero when not given.
    pub fn translation(&self) -> [f64; 3] {
        self.translate.unwrap_or([0.0; 3])
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
