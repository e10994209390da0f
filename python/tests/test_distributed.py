"""vdag.distributed.convert on a LocalCluster of 2 worker processes: the
output is byte-identical to `dagtool convert` of the whole input (a mesh, a
mesh with colours, a point cloud, LAS tiles), a failing region is one clear
error, and a worker killed in the middle of the job changes nothing."""

from __future__ import annotations

import math
import os
import threading
import time
from pathlib import Path

import pytest

import vdag

distributed = pytest.importorskip("distributed")
import vdag.distributed  # noqa: E402

from conftest import run  # noqa: E402

BOUNDS = (-1.25, -1.25, -1.25, 2.5)


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    )
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()


def whole(dagtool, input, out, depth, *extra):
    bounds = ",".join(str(b) for b in BOUNDS)
    inputs = input if isinstance(input, list) else [input]
    run(dagtool, "convert", *inputs, "-o", out, "--depth", depth, "--bounds", bounds, "--quiet", *extra)
    return Path(out).read_bytes()


def write_cloud(path: Path, n: int = 4000) -> Path:
    lines = [
        "ply", "format ascii 1.0", f"element vertex {n}",
        "property double x", "property double y", "property double z",
        "property uchar red", "property uchar green", "property uchar blue", "end_header",
    ]
    for i in range(n):
        t = i * 0.0131
        lines.append(
            f"{math.sin(t) * 0.9!r} {math.cos(t * 1.3) * 0.8!r} {math.sin(t * 0.37) * 0.9!r} "
            f"{i % 256} {(i * 7) % 256} {(i * 13) % 256}"
        )
    path.write_text("\n".join(lines) + "\n")
    return path


def test_mesh_is_byte_identical(client, tmp_path, sphere_obj, dagtool):
    want = whole(dagtool, sphere_obj, tmp_path / "cli.vdag", 7)
    out = tmp_path / "dask.vdag"
    summary = vdag.distributed.convert(sphere_obj, out, 7, client, region_level=1, bounds=BOUNDS)
    assert out.read_bytes() == want
    assert vdag.open(out).version == (2, 0), "the default format, as dagtool convert's"
    assert len(summary["regions"]) == 8 and sum(r["voxels"] for r in summary["regions"]) == summary["voxels"]
    # Where each region's time went, and which worker ran it.
    assert all("parse_seconds" in r and "build_seconds" in r and r["worker"] for r in summary["regions"])
    assert all(m["worker"] and m["input_bytes"] > 0 for m in summary["merges"])
    assert summary["merges"] and summary["merges"][-1]["cells"] == (0, 8)
    # Nothing is left of the parts.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cli.vdag", "dask.vdag"]


def test_region_builds_keep_the_mesh_for_the_next_region(tmp_path, sphere_obj):
    # A process parses a mesh once for all its regions (cache_input); the
    # parts are those of builds without the cache, and the cache is freed.
    vdag.clear_input_cache()
    first = vdag.convert_region(sphere_obj, tmp_path / "a.part", 6, "1:0,0,0", bounds=BOUNDS)
    for key in ("parse_seconds", "bin_seconds", "load_seconds", "build_seconds", "write_seconds"):
        assert 0 <= first[key] <= first["seconds"], key
    cached = vdag.convert_region(sphere_obj, tmp_path / "b.part", 6, "1:1,1,1", bounds=BOUNDS)
    fresh = vdag.convert_region(sphere_obj, tmp_path / "c.part", 6, "1:1,1,1", bounds=BOUNDS, cache_input=False)
    assert cached["voxels"] == fresh["voxels"] > 0
    assert (tmp_path / "b.part").read_bytes() == (tmp_path / "c.part").read_bytes()
    assert vdag.clear_input_cache() is True
    assert vdag.clear_input_cache() is False


def test_coloured_mesh_is_byte_identical(client, tmp_path, sphere_obj, dagtool):
    for extra, name in [((), "raw"), (("--color-error", "2"), "packed")]:
        want = whole(dagtool, sphere_obj, tmp_path / f"cli-{name}.vdag", 6, "--colors", *extra)
        out = tmp_path / f"dask-{name}.vdag"
        vdag.distributed.convert(
            sphere_obj, out, 6, client, region_level=2, bounds=BOUNDS, colors=True,
            color_error=2 if extra else None, fan_in=4,
        )
        assert out.read_bytes() == want, name


def test_format_1_is_byte_identical(client, tmp_path, sphere_obj, dagtool):
    want = whole(dagtool, sphere_obj, tmp_path / "cli.vdag", 6, "--colors", "--format-version", "1")
    out = tmp_path / "dask.vdag"
    vdag.distributed.convert(sphere_obj, out, 6, client, region_level=1, bounds=BOUNDS, colors=True, format_version=1)
    assert out.read_bytes() == want
    assert vdag.open(out).version[0] == 1


def test_point_cloud_is_byte_identical(client, tmp_path, dagtool):
    cloud = write_cloud(tmp_path / "cloud.ply")
    want = whole(dagtool, cloud, tmp_path / "cli.vdag", 7, "--colors")
    out = tmp_path / "dask.vdag"
    vdag.distributed.convert(str(cloud), out, 7, client, region_level=1, bounds=BOUNDS, colors=True)
    assert out.read_bytes() == want


def test_a_failing_region_is_one_clear_error(client, tmp_path, sphere_obj):
    # The sphere does not fit in these bounds: every region fails the same
    # way, at once, and no retry or hang follows.
    out = tmp_path / "never.vdag"
    t = time.monotonic()
    with pytest.raises(vdag.ConvertError) as e:
        vdag.distributed.convert(sphere_obj, out, 6, client, region_level=1, bounds=(0, 0, 0, 0.5))
    assert "extends beyond --bounds" in str(e.value) and str(e.value).startswith("1:")
    assert e.value.kind == "input"
    assert not out.exists()
    assert time.monotonic() - t < 60
    # Missing bounds: refused before any work.
    with pytest.raises(vdag.ConvertError) as e:
        vdag.distributed.convert(sphere_obj, out, 6, client, region_level=1, bounds=None)
    assert e.value.kind == "usage"


def test_a_killed_worker_changes_nothing(client, tmp_path, sphere_obj, dagtool):
    want = whole(dagtool, sphere_obj, tmp_path / "cli.vdag", 6, "--colors")
    out = tmp_path / "dask.vdag"
    scratch = tmp_path / "parts"
    done = {}

    def job():
        try:
            done["summary"] = vdag.distributed.convert(
                sphere_obj, out, 6, client, region_level=2, bounds=BOUNDS, colors=True,
                scratch=scratch, _task_delay=0.1,
            )
        except BaseException as e:  # noqa: BLE001
            done["error"] = e

    thread = threading.Thread(target=job)
    thread.start()
    # Once some regions are built, kill one worker process outright; its
    # nanny starts a new one and the scheduler reruns the lost tasks.
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(list(scratch.glob("region-*.part"))) < 6:
        time.sleep(0.05)
    workers = list(client.scheduler_info()["workers"])
    pids = client.run(os.getpid, workers=[workers[0]])
    os.kill(pids[workers[0]], 9)
    thread.join(120)
    assert not thread.is_alive()
    assert "error" not in done, done.get("error")
    parts = len(list(scratch.glob("region-*.part")))
    assert parts == 64, parts
    assert out.read_bytes() == want


def test_las_tiles_are_byte_identical(client, tmp_path, dagtool):
    laspy = pytest.importorskip("laspy")
    tiles = []
    for q, (sx, sy) in enumerate([(1, 1), (-1, 1), (-1, -1), (1, -1)]):
        n = 600
        header = laspy.LasHeader(point_format=2, version="1.2")
        header.scales = [0.001] * 3
        las = laspy.LasData(header)
        ts = [i * 0.011 + q for i in range(n)]
        las.x = [sx * (0.05 + 0.9 * abs(math.sin(t * 1.7))) for t in ts]
        las.y = [sy * (0.05 + 0.9 * abs(math.cos(t * 0.9))) for t in ts]
        las.z = [0.8 * math.sin(t * 2.3) for t in ts]
        las.red = [(i * 977) % 65536 for i in range(n)]
        las.green = [q * 20000] * n
        las.blue = [(i * 131) % 65536 for i in range(n)]
        path = tmp_path / f"tile{q}.las"
        las.write(path)
        tiles.append(str(path))
    want = whole(dagtool, tiles, tmp_path / "cli.vdag", 6, "--colors")
    out = tmp_path / "dask.vdag"
    vdag.distributed.convert(tiles, out, 6, client, region_level=1, bounds=BOUNDS, colors=True)
    assert out.read_bytes() == want
