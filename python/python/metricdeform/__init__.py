"""Deform triangle meshes so that demanded lengths, areas and volumes hold
exactly, while the shape stays as close to the input as it can.

Quick start (spot the cow: belly girth +10 %, head area x1.3, volume kept)::

    import metricdeform as md
    V, F = md.read_mesh("data/meshes/spot.obj")
    U, report = md.deform(V, F, [
        md.Length(plane=([0, -0.1, 0.3], [0, 0, 1]), scale=1.1, name="belly girth"),
        md.Area(sphere=([0, 0.55, -0.4], 0.35), scale=1.3, name="head"),
        md.Volume(name="volume"),
    ])
    print(report["satisfied"], report["constraints"][0]["result"])

``V`` is an (n, 3) float array, ``F`` an (m, 3) integer array of 0-based
vertex indices (``trimesh.load(path, process=False)``'s ``vertices`` and
``faces`` work as they are). Constraints, handles and curvature regions are
the classes below or dicts in the job file's schema (``{"kind": "length",
"curve": {"plane": {...}}, "scale": 1.1}``); see the project's README.

The solve runs in Rust without the GIL; Ctrl-C interrupts it.
"""

from __future__ import annotations

import json
import os
import warnings
from typing import Any, Iterable, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

# As the CLI does: without a device selection configured, Mesa's device-select
# layer is told to stay quiet (it complains about XDG_RUNTIME_DIR on headless
# machines). Read when the GPU backend first looks for an adapter.
if not any(v in os.environ for v in ("NODEVICE_SELECT", "MESA_VK_DEVICE_SELECT", "DRI_PRIME")):
    os.environ["NODEVICE_SELECT"] = "1"

from . import _metricdeform  # noqa: E402

__version__ = _metricdeform.__version__

__all__ = [
    "Length",
    "Area",
    "Volume",
    "Handle",
    "Curvature",
    "deform",
    "measure",
    "read_mesh",
    "load_job",
    "run_job",
    "NotSatisfiedWarning",
    "NotSatisfiedError",
]

Vec3 = Sequence[float]
Selection = Union[Sequence[int], np.ndarray]


class NotSatisfiedWarning(UserWarning):
    """A demand could not be met: the result is the closest the method got."""


class NotSatisfiedError(RuntimeError):
    """Raised by ``deform(..., strict=True)`` when a demand is not met.

    ``positions`` and ``report`` hold the result all the same.
    """

    def __init__(self, message: str, positions: np.ndarray, report: dict):
        super().__init__(message)
        self.positions = positions
        self.report = report


def _indices(sel: Selection, what: str) -> list:
    """A boolean mask or a list of indices as a list of indices."""
    a = np.asarray(sel)
    if a.dtype == bool:
        if a.ndim != 1:
            raise ValueError(f"{what}: a mask must be one-dimensional, got shape {a.shape}")
        return [int(i) for i in np.flatnonzero(a)]
    if a.size == 0:
        return []
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{what}: indices must be integers, got {a.dtype}")
    if a.ndim != 1:
        raise ValueError(f"{what}: indices must be one-dimensional, got shape {a.shape}")
    return [int(i) for i in a]


def _plain(value: Any, key: str = "") -> Any:
    """numpy arrays and scalars inside a dict turned into JSON values; masks
    under ``faces`` and ``vertices`` into indices."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v, str(k)) for k, v in value.items()}
    if key in ("faces", "vertices", "path") and not isinstance(value, (str, bytes)):
        if isinstance(value, np.ndarray) or (
            isinstance(value, (list, tuple)) and all(isinstance(v, (bool, np.bool_)) for v in value) and value
        ):
            return _indices(value, key)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _target(scale: Optional[float], value: Optional[float], name: Optional[str]) -> dict:
    d: dict = {}
    if name is not None:
        d["name"] = name
    if scale is not None:
        d["scale"] = float(scale)
    if value is not None:
        d["value"] = float(value)
    return d


def _region(
    faces: Optional[Selection] = None,
    sphere: Optional[Tuple[Vec3, float]] = None,
    box: Optional[Tuple[Vec3, Vec3]] = None,
    group: Optional[str] = None,
    faces_file: Optional[str] = None,
    vertices: Optional[Selection] = None,
) -> dict:
    r: dict = {}
    if faces is not None:
        r["faces"] = _indices(faces, "faces")
    if sphere is not None:
        center, radius = sphere
        r["sphere"] = {"center": _plain(center), "radius": float(radius)}
    if box is not None:
        lo, hi = box
        r["box"] = {"min": _plain(lo), "max": _plain(hi)}
    if group is not None:
        r["group"] = group
    if faces_file is not None:
        r["faces_file"] = str(faces_file)
    if vertices is not None:
        r["vertices"] = _indices(vertices, "vertices")
    return r


class _Spec:
    """A constraint, handle or curvature region: ``.to_dict()`` is its job-file form."""

    def __init__(self, spec: dict):
        self._spec = spec

    def to_dict(self) -> dict:
        return dict(self._spec)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._spec!r})"


class Length(_Spec):
    """The length of a curve on the surface (paper Sec. 3.1).

    Give exactly one of ``plane=(origin, normal)`` (the plane section; where it
    cuts several loops, the one closest to ``origin``), ``path=[v0, v1, ...]``
    (the shortest edge path through these vertices; ``closed=True`` returns to
    the first) or ``points=[(face, (b0, b1, b2)), ...]`` (barycentric points,
    consecutive ones sharing a face). Target: ``scale`` times the input's
    length, or ``value``; neither keeps it.
    """

    def __init__(
        self,
        plane: Optional[Tuple[Vec3, Vec3]] = None,
        path: Optional[Selection] = None,
        points: Optional[Sequence[Tuple[int, Vec3]]] = None,
        *,
        closed: Optional[bool] = None,
        scale: Optional[float] = None,
        value: Optional[float] = None,
        name: Optional[str] = None,
    ):
        curve: dict = {}
        if plane is not None:
            origin, normal = plane
            curve["plane"] = {"origin": _plain(origin), "normal": _plain(normal)}
        if path is not None:
            curve["path"] = _indices(path, "path")
        if closed is not None:
            curve["closed"] = bool(closed)
        if points is not None:
            curve["points"] = [{"face": int(f), "bary": _plain(b)} for f, b in points]
        super().__init__({"kind": "length", "curve": curve, **_target(scale, value, name)})


class Area(_Spec):
    """The area of a set of faces (paper Sec. 3.2).

    Give exactly one of ``faces`` (indices, or a boolean mask over the faces),
    ``sphere=(center, radius)`` or ``box=(min, max)`` (the faces whose centroid
    lies inside), ``group`` (an OBJ group's name) or ``faces_file``. Target:
    ``scale`` times the input's area, or ``value``; neither keeps it.
    """

    def __init__(
        self,
        faces: Optional[Selection] = None,
        *,
        sphere: Optional[Tuple[Vec3, float]] = None,
        box: Optional[Tuple[Vec3, Vec3]] = None,
        group: Optional[str] = None,
        faces_file: Optional[str] = None,
        scale: Optional[float] = None,
        value: Optional[float] = None,
        name: Optional[str] = None,
    ):
        region = _region(faces, sphere, box, group, faces_file)
        super().__init__({"kind": "area", "region": region, **_target(scale, value, name)})


class Volume(_Spec):
    """The volume the closed, consistently oriented mesh encloses (paper
    Sec. 3.3). Target: ``scale`` times the input's volume, or ``value``;
    neither keeps it."""

    def __init__(
        self,
        *,
        scale: Optional[float] = None,
        value: Optional[float] = None,
        name: Optional[str] = None,
    ):
        super().__init__({"kind": "volume", **_target(scale, value, name)})


class Handle(_Spec):
    """Vertices held at their input position plus ``translate`` (paper Sec.
    5.2): ``vertices`` (indices or a mask), or a region as for :class:`Area`
    (all vertices of its faces)."""

    def __init__(
        self,
        vertices: Optional[Selection] = None,
        *,
        faces: Optional[Selection] = None,
        sphere: Optional[Tuple[Vec3, float]] = None,
        box: Optional[Tuple[Vec3, Vec3]] = None,
        group: Optional[str] = None,
        translate: Optional[Vec3] = None,
    ):
        spec: dict = {}
        if vertices is not None:
            spec["vertices"] = _indices(vertices, "vertices")
        region = _region(faces, sphere, box, group)
        if region:
            spec["region"] = region
        if translate is not None:
            spec["translate"] = _plain(translate)
        super().__init__(spec)


class Curvature(_Spec):
    """A region whose mean curvature is multiplied by ``scale`` (paper Eq. 21);
    the region as for :class:`Area`."""

    def __init__(
        self,
        faces: Optional[Selection] = None,
        *,
        scale: float,
        sphere: Optional[Tuple[Vec3, float]] = None,
        box: Optional[Tuple[Vec3, Vec3]] = None,
        group: Optional[str] = None,
    ):
        super().__init__({"region": _region(faces, sphere, box, group), "scale": float(scale)})


Spec = Union[_Spec, Mapping[str, Any]]


def _non_finite(value: Any, path: str) -> Optional[str]:
    """The path of the first NaN or infinity inside `value`, if any."""
    if isinstance(value, float) and not np.isfinite(value):
        return f"{path} = {value}"
    if isinstance(value, Mapping):
        for k, v in value.items():
            found = _non_finite(v, f"{path}.{k}" if path else str(k))
            if found:
                return found
    if isinstance(value, list):
        for i, v in enumerate(value):
            found = _non_finite(v, f"{path}[{i}]")
            if found:
                return found
    return None


def _as_dict(item: Spec, what: str) -> dict:
    if isinstance(item, _Spec):
        d = item.to_dict()
    elif isinstance(item, Mapping):
        d = _plain(item)
    else:
        d = None
    if d is not None:
        bad = _non_finite(d, "")
        if bad:
            name = d.get("name")
            label = f"{what} ('{name}')" if isinstance(name, str) else what
            raise ValueError(f"metricdeform: {label}: {bad}; numbers must be finite")
        return d
    raise ValueError(
        f"{what}: expected a dict in the job file's schema or a metricdeform "
        f"class (Length, Area, Volume, Handle, Curvature), got {type(item).__name__}"
    )


def _job(
    constraints: Iterable[Spec],
    handles: Iterable[Spec],
    curvature: Iterable[Spec],
    solver: Optional[Mapping[str, Any]],
    backend: Optional[str],
    tolerance: Optional[float],
) -> str:
    table = _plain(dict(solver or {}))
    if backend is not None:
        table["backend"] = backend
    if tolerance is not None:
        table["tolerance"] = float(tolerance)
    job = {
        "mesh": "(V, F)",
        "constraint": [_as_dict(c, f"constraint {i + 1}") for i, c in enumerate(constraints)],
        "handle": [_as_dict(h, f"handle {i + 1}") for i, h in enumerate(handles)],
        "curvature": [_as_dict(c, f"curvature {i + 1}") for i, c in enumerate(curvature)],
        "solver": table,
    }
    bad = _non_finite(table, "solver")
    if bad:
        raise ValueError(f"metricdeform: {bad}; numbers must be finite")
    try:
        return json.dumps(job, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"metricdeform: a constraint holds a value JSON cannot carry: {e}") from None


def _arrays(V: Any, F: Any) -> Tuple[np.ndarray, np.ndarray]:
    V = np.asarray(V)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1:] != (3,):
        raise ValueError(f"V must be an (n, 3) array of vertex positions, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1:] != (3,):
        raise ValueError(f"F must be an (m, 3) array of triangles, got shape {F.shape}")
    if not np.issubdtype(V.dtype, np.number) or np.issubdtype(V.dtype, np.complexfloating):
        raise ValueError(f"V must hold real numbers, got {V.dtype}")
    if F.size and not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"F must hold integer vertex indices, got {F.dtype}")
    return (
        np.ascontiguousarray(V, dtype=np.float64),
        np.ascontiguousarray(F, dtype=np.int64),
    )


def deform(
    V: Any,
    F: Any,
    constraints: Iterable[Spec] = (),
    handles: Iterable[Spec] = (),
    curvature: Iterable[Spec] = (),
    *,
    backend: Optional[str] = None,
    tolerance: Optional[float] = None,
    solver: Optional[Mapping[str, Any]] = None,
    strict: bool = False,
) -> Tuple[np.ndarray, dict]:
    """Deform the mesh (V, F) so that every constraint holds.

    Returns ``(U, report)``: the deformed (n, 3) positions in the input's
    vertex order, and a dict shaped like the CLI's JSON report
    (``report["constraints"][i]`` has the ``original``, ``target`` and
    ``result`` of constraint i; ``report["satisfied"]``), plus
    ``report["fields"]`` with the per-face arrays ``face_scale``
    (sqrt(area out / area in)) and ``face_distortion`` (quasi-conformal).

    ``backend``: ``"auto"`` (default), ``"cpu"`` or ``"gpu"``; ``tolerance``:
    the relative metric error allowed (default 1e-5); ``solver``: any other key
    of the job file's ``[solver]`` table. Bad input raises ``ValueError``
    naming the constraint. A demand the method cannot meet gives the result
    with ``report["satisfied"] == False`` and a :class:`NotSatisfiedWarning`,
    or raises :class:`NotSatisfiedError` with ``strict=True``.
    """
    V, F = _arrays(V, F)
    job = _job(constraints, handles, curvature, solver, backend, tolerance)
    U, text, face_scale, face_distortion, _note = _metricdeform.deform(V, F, job, "metricdeform.deform")
    report = json.loads(text)
    report["fields"] = {"face_scale": face_scale, "face_distortion": face_distortion}
    if not report["satisfied"] and not report.get("preview", False):
        reason = report.get("reason") or "a constraint is not met within the tolerance"
        if strict:
            raise NotSatisfiedError(reason, U, report)
        warnings.warn(reason, NotSatisfiedWarning, stacklevel=2)
    return U, report


def measure(V: Any, F: Any, constraints: Iterable[Spec], *, tolerance: Optional[float] = None) -> dict:
    """The input's metrics: a report dict whose ``constraints[i]["original"]``
    is constraint i's length, area or volume (``met``: whether the input
    already meets its target)."""
    V, F = _arrays(V, F)
    job = _job(constraints, (), (), None, None, tolerance)
    return json.loads(_metricdeform.measure(V, F, job, "metricdeform.measure"))


def read_mesh(path: str) -> Tuple[np.ndarray, np.ndarray]:
    """Read an OBJ, PLY or STL file as (V, F), exactly as the CLI reads it
    (vertex i is the file's i-th vertex; polygons fan-triangulated in order)."""
    return _metricdeform.read_mesh(str(path))


def load_job(path: str) -> dict:
    """Read a job file (TOML or JSON) and its mesh.

    Returns a dict with ``V``, ``F``, ``constraints``, ``handles``,
    ``curvature`` (lists of dicts in the job's schema, ``faces_file`` paths
    resolved against the job's folder) and ``solver`` (the ``[solver]``
    table), plus ``mesh`` (the mesh's path) and ``output`` (as in the job).
    ``deform(job["V"], job["F"], job["constraints"], job["handles"],
    job["curvature"], solver=job["solver"])`` is :func:`run_job`.
    """
    V, F, text, mesh = _metricdeform.load_job(str(path))
    spec = json.loads(text)
    return {
        "V": V,
        "F": F,
        "constraints": spec.get("constraint", []),
        "handles": spec.get("handle", []),
        "curvature": spec.get("curvature", []),
        "solver": spec.get("solver", {}),
        "mesh": mesh,
        "output": spec.get("output"),
    }


def run_job(path: str, *, backend: Optional[str] = None, strict: bool = False) -> Tuple[np.ndarray, dict]:
    """Run a job file as ``metricdeform deform JOB`` does, but write nothing:
    returns ``(U, report)`` as :func:`deform`."""
    job = load_job(path)
    return deform(
        job["V"],
        job["F"],
        job["constraints"],
        job["handles"],
        job["curvature"],
        backend=backend,
        solver=job["solver"],
        strict=strict,
    )
