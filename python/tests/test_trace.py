"""Dag.trace against `dagtrace trace` on the same files and rays."""

from __future__ import annotations

import math
import os
import threading

import numpy as np
import pytest

import vdag
from conftest import random_rays, read_binary_hits, run, write_binary_rays

COLUMNS = ("hit", "t", "cell", "level", "face", "index")


def cli_hits(dagtrace, path, tmp_path, origins, directions, backend="cpu", **ray):
    rays = write_binary_rays(tmp_path / "rays.vray", origins, directions, **ray)
    out = tmp_path / "hits.vhit"
    run(dagtrace, "trace", path, "--rays", rays, "-o", out, "--format", "binary", "--backend", backend, "--force")
    return read_binary_hits(out)


def assert_same(result: vdag.TraceResult, expected: dict):
    for name in COLUMNS:
        np.testing.assert_array_equal(getattr(result, name), expected[name], err_msg=name)


def test_trace_answers_as_dagtrace_trace(sphere_vdag, dagtrace, tmp_path):
    origins, directions = random_rays(4000, seed=1)
    expected = cli_hits(dagtrace, sphere_vdag, tmp_path, origins, directions)
    assert 0.2 < expected["hit"].mean() < 0.95, "the rays both hit and miss"
    dag = vdag.open(sphere_vdag)
    result = dag.trace(origins, directions)
    assert len(result) == 4000
    assert result.hit.dtype == np.bool_ and result.t.dtype == np.float32
    assert result.cell.dtype == np.uint32 and result.cell.shape == (4000, 3)
    assert result.face.dtype == np.uint8 and result.index.dtype == np.int64
    assert_same(result, expected)
    # float64 input holding the same values, a Fortran-ordered copy and a
    # strided view (converted by numpy) give the same answers.
    assert_same(dag.trace(origins.astype(np.float64), directions.astype(np.float64)), expected)
    assert_same(dag.trace(np.asfortranarray(origins), directions), expected)
    wide = np.zeros((4000, 6), np.float32)
    wide[:, ::2] = directions
    assert_same(dag.trace(origins, wide[:, ::2]), expected)
    assert set(result.as_dict()) == set(COLUMNS)


def test_segments_and_levels_as_dagtrace_trace(sphere_vdag, dagtrace, tmp_path):
    origins, directions = random_rays(3000, seed=2)
    dag = vdag.open(sphere_vdag)
    for ray in ({"tmin": 0.3, "tmax": 0.6}, {"level": 4}, {"level": 7, "tmax": 0.5}):
        expected = cli_hits(dagtrace, sphere_vdag, tmp_path, origins, directions, **ray)
        got = dag.trace(origins, directions, **ray)
        assert_same(got, expected)
    coarse = dag.trace(origins, directions, level=4)
    assert coarse.hit.any()
    assert (coarse.level[coarse.hit] == 4).all() and (coarse.cell[coarse.hit] < 16).all()


def test_the_conformance_cases_rays_as_dagtrace_trace(dagtrace, tmp_path):
    from conftest import REPO

    case = REPO / "conformance" / "cases" / "trace" / "checker-d3.vdag"
    rng = np.random.default_rng(3)
    origins = rng.uniform(-0.5, 1.5, size=(2000, 3)).astype(np.float32)
    directions = rng.normal(size=(2000, 3)).astype(np.float32)
    expected = cli_hits(dagtrace, case, tmp_path, origins, directions)
    assert_same(vdag.open(case).trace(origins, directions), expected)


def test_empty_batches_and_bad_arguments(sphere_vdag):
    dag = vdag.open(sphere_vdag)
    empty = dag.trace(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert len(empty) == 0 and empty.cell.shape == (0, 3)
    o, d = random_rays(10, seed=4)
    with pytest.raises(ValueError, match="rows"):
        dag.trace(o, d[:5])
    with pytest.raises(ValueError, match="shape"):
        dag.trace(o[:, :2], d[:, :2])
    with pytest.raises(ValueError, match="level"):
        dag.trace(o, d, level=8)
    with pytest.raises(ValueError, match="backend"):
        dag.trace(o, d, backend="tpu")
    with pytest.raises(ValueError, match="NaN"):
        dag.trace(o, d, tmin=math.nan)


def test_traces_from_threads_at_once_agree(sphere_vdag):
    """The GIL is released while tracing: threads trace at the same time and
    get the answers they would alone."""
    dag = vdag.open(sphere_vdag)
    batches = [random_rays(20000, seed=s) for s in range(4)]
    alone = [dag.trace(o, d).t for o, d in batches]
    together = [None] * 4

    def work(i):
        together[i] = dag.trace(*batches[i]).t

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a, b)


def test_gpu_backend_as_dagtrace_trace_gpu(sphere_vdag, dagtrace, tmp_path):
    origins, directions = random_rays(3000, seed=5)
    dag = vdag.open(sphere_vdag)
    try:
        result = dag.trace(origins, directions, backend="gpu")
    except vdag.GpuError as e:
        if os.environ.get("VDAG_REQUIRE_GPU") == "1":
            raise
        assert "adapter" in str(e) or "GPU" in str(e)
        pytest.skip(f"no GPU adapter: {e}")
    expected = cli_hits(dagtrace, sphere_vdag, tmp_path, origins, directions, backend="gpu")
    assert_same(result, expected)
    # And the CPU's answers on the hits (the GPU's t may differ by the
    # spec's tolerance; the cells may differ only on exact ties).
    cpu = dag.trace(origins, directions)
    assert (cpu.hit == result.hit).mean() > 0.99


def test_the_gil_is_released_while_tracing(sphere_vdag):
    """Python code runs in another thread while a batch is traced."""
    dag = vdag.open(sphere_vdag)
    origins, directions = random_rays(400_000, seed=6)
    spins = 0
    done = threading.Event()

    def work():
        dag.trace(origins, directions)
        done.set()

    started = threading.Thread(target=work)
    started.start()
    while not done.is_set():
        spins += 1
    started.join()
    # Holding the GIL, the trace would let this loop run only between Python
    # bytecodes of the other thread: a handful of switch intervals at most.
    assert spins > 10_000, spins
