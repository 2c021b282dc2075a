"""The Rust half of metricdeform (see metricdeform/__init__.py for the API)."""

from typing import Optional, Tuple

import numpy as np
import numpy.typing as npt

__version__: str

def deform(
    vertices: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int64],
    job_json: str,
    origin: str,
) -> Tuple[
    npt.NDArray[np.float64],
    str,
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    Optional[str],
]:
    """Deform (V, F) by a job in the job file's JSON schema: (U, report JSON,
    face scale, face distortion, backend note). Releases the GIL."""

def measure(
    vertices: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int64],
    job_json: str,
    origin: str,
) -> str:
    """The input's metrics as a report JSON."""

def load_job(
    path: str,
) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], str, str]:
    """(V, F, job JSON with faces_file paths resolved, mesh path)."""

def read_mesh(path: str) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """(V, F) of an OBJ, PLY or STL file."""
