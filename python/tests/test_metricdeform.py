"""The Python package against the CLI and the method's guarantees.

Run by `tests/python.rs` (part of `cargo test`), which builds the wheel,
installs it into a virtual environment and sets METRICDEFORM_CLI to the CLI
binary of the same build.
"""

import os
import signal
import subprocess
import threading
import time
import _thread
from pathlib import Path

import numpy as np
import pytest

import metricdeform as md

ROOT = Path(__file__).resolve().parents[2]
SPOT = ROOT / "data" / "meshes" / "spot.obj"
DEMO = ROOT / "examples" / "spot-demo.toml"
BUNNY_EARS = ROOT / "examples" / "bunny-ears.toml"
HOMER = ROOT / "data" / "meshes" / "homer.obj"


def obj_vertices(path):
    """The `v` lines of an OBJ file, as the CLI writes them."""
    rows = []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                rows.append([float(t) for t in line.split()[1:4]])
    return np.array(rows)


def bbox_diagonal(V):
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def test_demo_equals_the_cli(tmp_path):
    cli = os.environ.get("METRICDEFORM_CLI")
    if not cli:
        pytest.skip("METRICDEFORM_CLI is not set (tests/python.rs sets it)")
    out = tmp_path / "spot.deformed.obj"
    subprocess.run(
        [cli, "demo", "--backend", "cpu", "--out", str(out), "--quiet"],
        check=True,
        capture_output=True,
    )
    U, report = md.run_job(DEMO, backend="cpu")
    assert report["satisfied"]
    cli_U = obj_vertices(out)
    assert cli_U.shape == U.shape
    assert np.max(np.abs(cli_U - U)) <= 1e-12
    # And the quick start's classes give the same job as the job file.
    V, F = md.read_mesh(SPOT)
    U2, _ = md.deform(
        V,
        F,
        [
            md.Length(plane=([0.0, -0.1, 0.3], [0.0, 0.0, 1.0]), scale=1.1, name="belly girth"),
            md.Area(sphere=([0.0, 0.55, -0.4], 0.35), scale=1.3, name="head"),
            md.Volume(name="volume"),
        ],
        backend="cpu",
    )
    assert np.max(np.abs(U2 - U)) <= 1e-12


def test_volume_times_8_doubles_spot():
    V, F = md.read_mesh(SPOT)
    U, report = md.deform(V, F, [md.Volume(scale=8)])
    assert report["satisfied"]
    assert report["constraints"][0]["result"] == pytest.approx(8 * report["constraints"][0]["original"], rel=1e-5)
    # The input scaled by 2 about some point: centred, U = 2 V.
    expected = 2.0 * (V - V.mean(axis=0))
    got = U - U.mean(axis=0)
    assert np.max(np.linalg.norm(got - expected, axis=1)) <= 1e-4 * bbox_diagonal(expected)


def test_report_is_shaped_like_the_json_report():
    V, F = md.read_mesh(SPOT)
    U, report = md.deform(V, F, [md.Area(faces=np.arange(100), scale=1.2, name="patch")])
    for key in ("mesh", "backend", "constraints", "satisfied", "iterations", "seconds",
                "distortion", "displacement", "solver"):
        assert key in report, key
    row = report["constraints"][0]
    assert row["name"] == "patch" and row["kind"] == "area" and row["faces"] == 100
    assert row["result"] == pytest.approx(1.2 * row["original"], rel=1e-5)
    fields = report["fields"]
    assert fields["face_scale"].shape == (len(F),)
    assert fields["face_distortion"].shape == (len(F),)
    # The patch grew by sqrt(1.2) in scale on average.
    mean_scale = np.average(fields["face_scale"][:100] ** 2) ** 0.5
    assert 1.0 < mean_scale < 1.3


def test_masks_dicts_and_classes_agree():
    V, F = md.read_mesh(SPOT)
    mask = np.zeros(len(F), dtype=bool)
    mask[10:60] = True
    by_mask = md.measure(V, F, [md.Area(mask)])
    by_dict = md.measure(V, F, [{"kind": "area", "region": {"faces": np.arange(10, 60)}}])
    assert by_mask["constraints"][0]["original"] == by_dict["constraints"][0]["original"]
    assert by_mask["constraints"][0]["faces"] == 50


def test_bad_input_raises_value_error():
    V, F = md.read_mesh(SPOT)
    cases = [
        ([md.Area(faces=[len(F)], scale=2, name="ears")], "constraint 1 ('ears')"),
        ([md.Volume(), md.Length(scale=1.2)], "constraint 2 (length)"),
        ([{"kind": "length", "name": "girth", "curv": {}}], "constraint 1 ('girth')"),
        ([md.Area(sphere=([0, 0, 0], -1.0))], "radius"),
        ([md.Volume(scale=float("nan"))], "scale"),
        ([md.Length(plane=([0, 0, 100], [0, 0, 1]), name="far")], "misses the mesh"),
    ]
    for constraints, words in cases:
        with pytest.raises(ValueError) as e:
            md.deform(V, F, constraints)
        assert words in str(e.value), str(e.value)
    with pytest.raises(ValueError, match="negative"):
        md.deform(V, np.where(F == 0, -1, F), [md.Volume()])
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        md.deform(V[:, :2], F, [md.Volume()])
    with pytest.raises(ValueError, match="out of range"):
        md.deform(V[:10], F, [md.Volume()])
    with pytest.raises(ValueError, match="integer"):
        md.deform(V, F.astype(float), [md.Volume()])
    with pytest.raises(ValueError, match="unknown value 'tpu'"):
        md.deform(V, F, [md.Volume()], backend="tpu")


def test_unmet_demand_warns_or_raises():
    V, F = md.read_mesh(SPOT)
    # Two contradictory demands on the same region.
    demands = [md.Area(faces=np.arange(200), scale=2.0), md.Area(faces=np.arange(200), scale=0.5)]
    with pytest.warns(md.NotSatisfiedWarning):
        U, report = md.deform(V, F, demands, solver={"max_iterations": 5, "fine_tune_iterations": 3})
    assert report["satisfied"] is False
    assert U.shape == V.shape
    with pytest.raises(md.NotSatisfiedError) as e:
        md.deform(V, F, demands, solver={"max_iterations": 5, "fine_tune_iterations": 3}, strict=True)
    assert e.value.report["satisfied"] is False
    assert e.value.positions.shape == V.shape


def test_trimesh_round_trip(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    # homer: no texture coordinates, so trimesh keeps the file's vertices
    # (it splits spot's at its UV seams, which opens the mesh).
    mesh = trimesh.load(HOMER, process=False)
    U, report = md.deform(mesh.vertices, mesh.faces, [md.Volume(scale=1.5)])
    assert report["satisfied"]
    out = trimesh.Trimesh(U, mesh.faces, process=False)
    assert out.volume == pytest.approx(1.5 * mesh.volume, rel=1e-5)
    path = tmp_path / "out.ply"
    out.export(path)
    V2, F2 = md.read_mesh(path)
    assert np.array_equal(F2, mesh.faces)
    assert np.allclose(V2, U, rtol=0, atol=1e-6 * bbox_diagonal(U))


def test_solve_releases_the_gil():
    job = md.load_job(BUNNY_EARS)
    ticks = []
    done = threading.Event()

    def count():
        while not done.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.001)

    worker = threading.Thread(target=count)
    worker.start()
    time.sleep(0.05)
    # Solves one after the other for at least a second, long enough to
    # tell (one solve takes about half of it on a 2-core machine).
    start = time.perf_counter()
    solves = 0
    while solves == 0 or time.perf_counter() - start < 1.0:
        md.deform(job["V"], job["F"], job["constraints"], solver=job["solver"], backend="cpu")
        solves += 1
    end = time.perf_counter()
    done.set()
    worker.join()
    during = [t for t in ticks if start <= t <= end]
    # The other thread ran all through the solves: no gap longer than a
    # tenth of one solve (a solve that held the GIL would be one).
    gaps = np.diff([start] + during + [end])
    assert len(during) > 50, len(during)
    solve = (end - start) / solves
    assert gaps.max() < 0.1 * solve, (gaps.max(), solve, solves)


def test_ctrl_c_interrupts_a_solve():
    job = md.load_job(BUNNY_EARS)
    # Ctrl-C as an interactive Python gets it. A process started in the
    # background by a non-interactive shell (`cmd &` in a script) inherits
    # SIGINT ignored; Python then installs no handler of its own, and
    # `interrupt_main` does nothing (the test failed so, "DID NOT RAISE").
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        timer = threading.Timer(0.3, _thread.interrupt_main)
        start = time.perf_counter()
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            md.deform(job["V"], job["F"], job["constraints"], solver=job["solver"], backend="cpu")
        elapsed = time.perf_counter() - start
        timer.join()
    finally:
        signal.signal(signal.SIGINT, previous)
    # Interrupted within an iteration or two, well before the ~2 s solve ends.
    assert elapsed < 1.5, elapsed


def test_load_job_and_run_job_agree():
    job = md.load_job(DEMO)
    assert job["V"].shape[1] == 3 and job["F"].dtype == np.int64
    assert [c["name"] for c in job["constraints"]] == ["belly girth", "head", "volume"]
    U1, r1 = md.run_job(DEMO, backend="cpu")
    U2, r2 = md.deform(job["V"], job["F"], job["constraints"], solver=job["solver"], backend="cpu")
    assert np.max(np.abs(U1 - U2)) <= 1e-12
    assert [c["result"] for c in r1["constraints"]] == pytest.approx(
        [c["result"] for c in r2["constraints"]], rel=1e-12
    )
