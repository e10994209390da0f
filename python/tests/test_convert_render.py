"""vdag.convert against `dagtool convert`, vdag.render against `dagtrace render`."""

from __future__ import annotations

import os

import numpy as np
import pytest

import vdag
from conftest import run

PIL = pytest.importorskip("PIL.Image", reason="Pillow reads dagtrace's PNG")


@pytest.mark.parametrize(
    "options, flags",
    [
        ({}, []),
        ({"colors": True, "solid": True}, ["--colors", "--solid"]),
        ({"colors": True, "color_error": 2, "memory_limit": "256M"}, ["--colors", "--color-error", "2", "--memory-limit", "256M"]),
        ({"bounds": (-2.0, -2.0, -2.0, 4.0)}, ["--bounds", "-2,-2,-2,4"]),
    ],
)
def test_convert_writes_the_bytes_dagtool_convert_writes(sphere_obj, dagtool, tmp_path, options, flags):
    cli = tmp_path / "cli.vdag"
    run(dagtool, "convert", sphere_obj, "-o", cli, "--depth", "6", "--quiet", *flags)
    mine = tmp_path / "py.vdag"
    summary = vdag.convert(sphere_obj, mine, depth=6, **options)
    assert mine.read_bytes() == cli.read_bytes()
    assert summary["file_bytes"] == mine.stat().st_size
    assert summary["voxels"] == vdag.open(mine).voxel_count


def test_progress_is_called_in_order(sphere_obj, tmp_path):
    calls = []
    vdag.convert(sphere_obj, tmp_path / "p.vdag", depth=8, progress=lambda *a: calls.append(a))
    phases = [c[0] for c in calls]
    assert phases[-1] == "written" and calls[-1] == ("written", 1, 1)
    assert "finishing" in phases
    voxelizing = [c for c in calls if c[0] == "voxelizing"]
    assert voxelizing, "a mesh reports its chunks"
    assert all(0 < done <= total for _, done, total in voxelizing)
    assert voxelizing[-1][1] == voxelizing[-1][2], "every chunk done"
    assert phases.index("finishing") > max(i for i, p in enumerate(phases) if p == "voxelizing")


def test_an_exception_in_progress_is_raised(sphere_obj, tmp_path):
    seen = []

    def progress(phase, done, total):
        seen.append(phase)
        raise KeyError("stop")

    with pytest.raises(KeyError):
        vdag.convert(sphere_obj, tmp_path / "e.vdag", depth=6, progress=progress)
    assert len(seen) == 1, "not called again after raising"


def test_convert_errors_name_the_problem_and_write_nothing(sphere_obj, tmp_path):
    out = tmp_path / "o.vdag"
    out.write_bytes(b"keep")
    with pytest.raises(vdag.ConvertError) as raised:
        vdag.convert(sphere_obj, out, depth=6)
    assert "--force" in str(raised.value) or "exists" in str(raised.value)
    assert out.read_bytes() == b"keep"
    vdag.convert(sphere_obj, out, depth=6, force=True)
    assert vdag.validate(out) == []
    with pytest.raises(vdag.ConvertError) as raised:
        vdag.convert(tmp_path / "none.obj", tmp_path / "n.vdag", depth=6)
    assert raised.value.kind == "io" and "none.obj" in str(raised.value)
    assert not (tmp_path / "n.vdag").exists()
    with pytest.raises(vdag.ConvertError) as raised:
        vdag.convert(sphere_obj, tmp_path / "d.vdag", depth=40)
    assert raised.value.kind == "usage"
    with pytest.raises(ValueError):
        vdag.convert(sphere_obj, tmp_path / "m.vdag", depth=6, memory_limit="lots")


def process_peak_bytes() -> int:
    """This process's peak resident size (VmHWM), in bytes."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM in /proc/self/status")


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads Linux's VmHWM")
def test_memory_limit_counts_the_conversion_not_the_process_peak(sphere_obj, tmp_path):
    """A process that peaked above the limit before (a large numpy array,
    allocated and freed) still converts within a small limit that the
    conversion itself fits: the limit is on the conversion's own memory,
    whatever ran before it in this process."""
    limit = 256 << 20
    big = np.ones((limit + (128 << 20)) // 8)  # written, so resident
    assert big[:: 1 << 12].sum() > 0
    del big
    assert process_peak_bytes() > limit + (64 << 20)
    out = tmp_path / "small.vdag"
    summary = vdag.convert(sphere_obj, out, depth=8, memory_limit=limit)
    assert 0 < summary["peak_rss"] <= limit
    unlimited = tmp_path / "default.vdag"
    vdag.convert(sphere_obj, unlimited, depth=8)
    assert out.read_bytes() == unlimited.read_bytes()


def cli_render(dagtrace, path, out, *flags):
    run(dagtrace, "render", path, "-o", out, "--force", *flags)
    return np.asarray(PIL.open(out).convert("RGB"))


@pytest.mark.parametrize(
    "kwargs, flags",
    [
        ({"shade": "normal"}, ["--shade", "normal"]),
        ({"shade": "color", "level": 5}, ["--shade", "color", "--level", "5"]),
        ({"shade": "depth", "camera_pos": (2.0, 1.5, 2.5), "look_at": (0, 0, 0), "fov": 30.0},
         ["--shade", "depth", "--camera-pos=2,1.5,2.5", "--look-at=0,0,0", "--fov", "30"]),
        ({}, []),
        ({"samples": 2, "ao_rays": 4, "sun": (1.0, 1.0, 0.0)}, ["--samples", "2", "--ao-rays", "4", "--sun=1,1,0"]),
    ],
)
def test_render_gives_the_pixels_of_dagtrace_render(sphere_vdag, dagtrace, tmp_path, kwargs, flags):
    expected = cli_render(dagtrace, sphere_vdag, tmp_path / "cli.png", "--width", "64", "--height", "48", *flags)
    image = vdag.render(sphere_vdag, width=64, height=48, **kwargs)
    assert image.shape == (48, 64, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, expected)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 3, "not a blank image"


def test_render_on_the_gpu_gives_the_pixels_of_dagtrace_render_gpu(sphere_vdag, dagtrace, tmp_path):
    dag = vdag.open(sphere_vdag)
    try:
        image = dag.render(width=64, height=48, shade="normal", backend="gpu")
    except vdag.GpuError as e:
        if os.environ.get("VDAG_REQUIRE_GPU") == "1":
            raise
        pytest.skip(f"no GPU adapter: {e}")
    expected = cli_render(dagtrace, sphere_vdag, tmp_path / "g.png", "--width", "64", "--height", "48",
                          "--shade", "normal", "--backend", "gpu")
    np.testing.assert_array_equal(image, expected)


def test_render_refuses_bad_options(sphere_vdag):
    dag = vdag.open(sphere_vdag)
    with pytest.raises(ValueError, match="look_at"):
        dag.render(camera_pos=(1, 1, 1))
    with pytest.raises(ValueError, match="lit"):
        dag.render(shade="normal", samples=4)
    with pytest.raises(ValueError, match="shade"):
        dag.render(shade="glossy")
    with pytest.raises(ValueError):
        dag.render(width=0)
