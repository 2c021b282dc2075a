//! `metricdeform._metricdeform`: the Rust half of the Python package. The
//! Python half (`python/metricdeform/__init__.py`) turns its arguments into a
//! job in the job file's JSON schema, so that constraints, handles and
//! curvature regions are checked here exactly as in a job file, with the same
//! messages.

use metricdeform::job::{ConstraintSpec, CurvatureSpec, HandleSpec, Job, JobFormat, RegionSpec};
use metricdeform::mesh::io::read_mesh as read_mesh_file;
use metricdeform::pipeline::{choose_backend, Options};
use metricdeform::problem::{curvature_label, handle_label};
use metricdeform::{Error, Mesh, Problem};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2};
use pyo3::exceptions::{PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// What messages call a mesh given as arrays.
const ARRAYS: &str = "mesh (V, F)";

fn to_py(e: Error) -> PyErr {
    match e {
        Error::BadInput(m) => PyValueError::new_err(m),
        e @ Error::Io { .. } => PyOSError::new_err(e.to_string()),
        e => PyRuntimeError::new_err(e.to_string()),
    }
}

/// `V` (n, 3) float64 and `F` (m, 3) int64 as a mesh.
fn mesh_of(v: &PyReadonlyArray2<f64>, f: &PyReadonlyArray2<i64>) -> PyResult<Mesh> {
    let (v, f) = (v.as_array(), f.as_array());
    if v.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "V must have shape (n, 3), got {:?}",
            v.shape()
        )));
    }
    if f.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "F must have shape (m, 3) (triangles), got {:?}",
            f.shape()
        )));
    }
    let positions: Vec<[f64; 3]> = v.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect();
    let mut triangles = Vec::with_capacity(f.nrows());
    for (i, r) in f.rows().into_iter().enumerate() {
        let mut t = [0usize; 3];
        for k in 0..3 {
            t[k] = usize::try_from(r[k]).map_err(|_| {
                PyValueError::new_err(format!(
                    "F[{i}, {k}] = {} is negative: vertex indices are 0-based and >= 0",
                    r[k]
                ))
            })?;
        }
        triangles.push(t);
    }
    Mesh::from_arrays(&positions, &triangles).map_err(to_py)
}

/// Each constraint, handle and curvature entry read on its own, so that a
/// schema error (an unknown key, a wrong type) names the entry; a whole-job
/// parse would give a position in the JSON text instead.
fn check_entries(job_json: &str, origin: &str) -> PyResult<()> {
    let job: serde_json::Value = serde_json::from_str(job_json)
        .map_err(|e| PyValueError::new_err(format!("{origin}: {e}")))?;
    fn each<T: serde::de::DeserializeOwned>(
        job: &serde_json::Value,
        key: &str,
        origin: &str,
        label: impl Fn(usize, &serde_json::Value) -> String,
    ) -> PyResult<()> {
        let Some(list) = job.get(key).and_then(|v| v.as_array()) else {
            return Ok(());
        };
        for (i, entry) in list.iter().enumerate() {
            if let Err(e) = serde_json::from_value::<T>(entry.clone()) {
                return Err(PyValueError::new_err(format!(
                    "{origin}: {}: {e}",
                    label(i, entry)
                )));
            }
        }
        Ok(())
    }
    each::<ConstraintSpec>(&job, "constraint", origin, |i, entry| {
        match entry.get("name").and_then(|n| n.as_str()) {
            Some(name) => format!("constraint {} ('{name}')", i + 1),
            None => format!("constraint {}", i + 1),
        }
    })?;
    each::<HandleSpec>(&job, "handle", origin, |i, _| handle_label(i))?;
    each::<CurvatureSpec>(&job, "curvature", origin, |i, _| curvature_label(i))
}

/// The job (JSON, the job file's schema) on the mesh (V, F).
fn problem_of(
    v: &PyReadonlyArray2<f64>,
    f: &PyReadonlyArray2<i64>,
    job_json: &str,
    origin: &str,
) -> PyResult<(Job, Problem)> {
    let mesh = mesh_of(v, f)?;
    check_entries(job_json, origin)?;
    let job = Job::from_str(job_json, JobFormat::Json, Path::new("."), origin).map_err(to_py)?;
    let problem = Problem::build(&job, mesh, Path::new(ARRAYS)).map_err(to_py)?;
    Ok((job, problem))
}

fn positions_array(x: &[glam::DVec3]) -> Array2<f64> {
    let flat: Vec<f64> = x.iter().flat_map(|p| p.to_array()).collect();
    Array2::from_shape_vec((x.len(), 3), flat).expect("n x 3")
}

/// Deform (V, F) by `job_json`; returns (U, report JSON, face scale, face
/// distortion, backend note). The GIL is released during the solve; a
/// signal (Ctrl-C) raises its exception at the next iteration.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn deform<'py>(
    py: Python<'py>,
    vertices: PyReadonlyArray2<'py, f64>,
    faces: PyReadonlyArray2<'py, i64>,
    job_json: &str,
    origin: &str,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    String,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    Option<String>,
)> {
    let (job, problem) = problem_of(&vertices, &faces, job_json, origin)?;
    let mut options = Options::from_spec(&job.spec.solver);
    let name = job.spec.solver.backend.as_deref().unwrap_or("auto");
    let choice = choose_backend(name, problem.mesh.num_faces()).map_err(to_py)?;
    options.backend = choice.backend;
    let flag = Arc::new(AtomicBool::new(false));
    options.interrupt = Some(flag.clone());
    let mut raised: Option<PyErr> = None;
    let result = py.detach(|| {
        let mut progress = |_| {
            if let Err(e) = Python::attach(|py| py.check_signals()) {
                raised = Some(e);
                flag.store(true, Ordering::Relaxed);
            }
        };
        metricdeform::run::deform_with_progress(&problem, &options, &mut progress)
    });
    let d = match result {
        Ok(d) => d,
        Err(Error::Interrupted) => {
            return Err(raised.unwrap_or_else(|| PyRuntimeError::new_err("interrupted")))
        }
        Err(e) => return Err(to_py(e)),
    };
    let report = serde_json::to_string(&d.report)
        .map_err(|e| PyRuntimeError::new_err(format!("report: {e}")))?;
    Ok((
        positions_array(&d.positions).into_pyarray(py),
        report,
        d.face_scale.into_pyarray(py),
        d.face_distortion.into_pyarray(py),
        choice.note,
    ))
}

/// The input's metrics for `job_json`'s constraints; returns the report JSON.
#[pyfunction]
fn measure(
    vertices: PyReadonlyArray2<'_, f64>,
    faces: PyReadonlyArray2<'_, i64>,
    job_json: &str,
    origin: &str,
) -> PyResult<String> {
    let (job, problem) = problem_of(&vertices, &faces, job_json, origin)?;
    let options = Options::from_spec(&job.spec.solver);
    let report = metricdeform::run::measure(&problem, options.tolerance);
    serde_json::to_string(&report).map_err(|e| PyRuntimeError::new_err(format!("report: {e}")))
}

/// Read a job file and its mesh: returns (V, F, the job as JSON with every
/// `faces_file` resolved against the job's folder, the mesh's path).
#[pyfunction]
#[allow(clippy::type_complexity)]
fn load_job<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<i64>>,
    String,
    String,
)> {
    let job = Job::load(&path).map_err(to_py)?;
    let mesh_path = job.mesh_path();
    let mesh = read_mesh_file(&mesh_path).map_err(to_py)?;
    let mut spec = job.spec.clone();
    let resolve = |r: &mut RegionSpec| {
        if let Some(f) = &r.faces_file {
            r.faces_file = Some(job.resolve_path(f));
        }
    };
    for c in &mut spec.constraint {
        c.region.as_mut().map(resolve);
    }
    for h in &mut spec.handle {
        h.region.as_mut().map(resolve);
    }
    for c in &mut spec.curvature {
        resolve(&mut c.region);
    }
    let json =
        serde_json::to_string(&spec).map_err(|e| PyRuntimeError::new_err(format!("job: {e}")))?;
    let (v, f) = arrays_of(py, &mesh);
    Ok((v, f, json, mesh_path.display().to_string()))
}

/// Read a mesh file (OBJ, PLY, STL) as (V, F).
#[pyfunction]
fn read_mesh(py: Python<'_>, path: std::path::PathBuf) -> PyResult<Arrays<'_>> {
    let mesh = read_mesh_file(&path).map_err(to_py)?;
    Ok(arrays_of(py, &mesh))
}

/// (V, F) as numpy arrays.
type Arrays<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<i64>>);

/// (V, F) of a mesh.
fn arrays_of<'py>(py: Python<'py>, mesh: &Mesh) -> Arrays<'py> {
    let flat: Vec<i64> = mesh.faces.iter().flatten().map(|&i| i as i64).collect();
    let f = Array2::from_shape_vec((mesh.faces.len(), 3), flat).expect("m x 3");
    (
        positions_array(&mesh.positions).into_pyarray(py),
        f.into_pyarray(py),
    )
}

#[pymodule]
fn _metricdeform(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(deform, m)?)?;
    m.add_function(wrap_pyfunction!(measure, m)?)?;
    m.add_function(wrap_pyfunction!(load_job, m)?)?;
    m.add_function(wrap_pyfunction!(read_mesh, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
