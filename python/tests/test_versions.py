"""Format 1.0 and 2.0 files of the same voxels (spec §23) give the same
answers in the vdag package, and vdag.convert / vdag.merge write the version
dagtool does (2.0 by default, 1.0 when asked)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import vdag
from conftest import random_rays, run


@pytest.fixture(scope="module")
def both(tmp_path_factory, sphere_obj, dagtool):
    """The coloured solid sphere at depth 7 written by dagtool as 1.0
    (`--format-version 1`) and by default (2.0)."""
    folder = tmp_path_factory.mktemp("versions")
    v1, v2 = folder / "v1.vdag", folder / "v2.vdag"
    common = ("--depth", "7", "--colors", "--solid", "--quiet")
    run(dagtool, "convert", sphere_obj, "-o", v1, *common, "--format-version", "1")
    run(dagtool, "convert", sphere_obj, "-o", v2, *common)
    return vdag.open(v1), vdag.open(v2)


def test_the_default_is_2_0_and_smaller(both, dagtool):
    v1, v2 = both
    assert v1.version[0] == 1 and v2.version == (2, 0)
    for name in ("depth", "resolution", "voxel_count", "attribute_kind", "root_min", "root_size", "color_format"):
        assert getattr(v1, name) == getattr(v2, name), name
    assert v2.file_size < v1.file_size
    assert len(v2.levels) == len(v1.levels) == v1.depth - 1
    assert [level["kind"] for level in v2.levels] == [level["kind"] for level in v1.levels]
    # The 2.0 file holds fewer records: reflections merge subtrees.
    assert sum(level["nodes"] for level in v2.levels) < sum(level["nodes"] for level in v1.levels)
    assert vdag.validate(v2.path) == []
    # dagtool info agrees on what the 2.0 file is.
    info = json.loads(run(dagtool, "info", "--json", v2.path).stdout)
    assert info["version"] == [2, 0] and info["file_bytes"] == v2.file_size


def test_voxels_colours_and_queries_are_the_same(both):
    v1, v2 = both
    voxels = v1.voxels()
    assert len(voxels) == v1.voxel_count > 1000
    np.testing.assert_array_equal(v2.voxels(), voxels)
    np.testing.assert_array_equal(np.concatenate(list(v2.iter_voxels(chunk=777))), voxels)
    np.testing.assert_array_equal(v2.colors(alpha=True), v1.colors(alpha=True))
    rng = np.random.default_rng(11)
    probes = np.concatenate([voxels[::3], rng.integers(-2, 130, size=(20000, 3))])
    contained = v1.contains(probes)
    assert contained.any() and not contained.all()
    np.testing.assert_array_equal(v2.contains(probes), contained)
    index = v1.attribute_index(probes)
    np.testing.assert_array_equal(v2.attribute_index(probes), index)
    # The index addresses the colours: the same colour through either file.
    hit = index >= 0
    np.testing.assert_array_equal(v2.colors()[v2.attribute_index(probes)[hit]], v1.colors()[index[hit]])


def test_trace_answers_are_the_same(both):
    v1, v2 = both
    origins, directions = random_rays(6000, seed=21)
    for ray in ({}, {"level": 4}, {"tmin": 0.3, "tmax": 0.9}):
        a = v1.trace(origins, directions, **ray)
        b = v2.trace(origins, directions, **ray)
        assert a.hit.any() and not a.hit.all()
        for name in ("hit", "t", "cell", "level", "face", "index"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=f"{name} {ray}")


@pytest.mark.parametrize("shade", ["normal", "color", "depth", "lit"])
def test_renders_are_the_same(both, shade):
    v1, v2 = both
    kwargs = {"samples": 1, "ao_rays": 2} if shade == "lit" else {}
    # An explicit camera: the automatic one frames each version's occupied
    # box as dagtrace render does, from the file's coarse levels.
    view = {"camera_pos": (2.0, 1.5, 2.5), "look_at": (0.0, 0.0, 0.0)}
    a = v1.render(width=48, height=32, shade=shade, **view, **kwargs)
    b = v2.render(width=48, height=32, shade=shade, **view, **kwargs)
    np.testing.assert_array_equal(b, a)


def test_the_gpu_lit_render_of_2_0_equals_that_of_1_0(both):
    v1, v2 = both
    view = {"camera_pos": (2.0, 1.5, 2.5), "look_at": (0.0, 0.0, 0.0), "samples": 1, "ao_rays": 2}
    try:
        a = v1.render(width=48, height=32, backend="gpu", **view)
    except vdag.GpuError as e:
        if os.environ.get("VDAG_REQUIRE_GPU") == "1":
            raise
        pytest.skip(f"no GPU adapter: {e}")
    b = v2.render(width=48, height=32, backend="gpu", **view)
    np.testing.assert_array_equal(b, a)
    assert len(np.unique(a.reshape(-1, 3), axis=0)) > 3, "not a blank image"


def test_convert_format_version_follows_the_cli(sphere_obj, dagtool, tmp_path):
    for version, flags in ((2, []), (1, ["--format-version", "1"]), (2, ["--format-version", "2"])):
        cli = tmp_path / f"cli-{version}-{len(flags)}.vdag"
        run(dagtool, "convert", sphere_obj, "-o", cli, "--depth", "6", "--colors", "--quiet", *flags)
        mine = tmp_path / f"py-{version}-{len(flags)}.vdag"
        kwargs = {"format_version": version} if flags else {}
        vdag.convert(sphere_obj, mine, depth=6, colors=True, **kwargs)
        assert mine.read_bytes() == cli.read_bytes(), flags
        assert vdag.open(mine).version[0] == version
    with pytest.raises(vdag.ConvertError) as raised:
        vdag.convert(sphere_obj, tmp_path / "bad.vdag", depth=6, format_version=3)
    assert raised.value.kind == "usage"
    assert not (tmp_path / "bad.vdag").exists()


def test_merge_writes_the_whole_volume_in_the_version_asked(sphere_obj, dagtool, tmp_path):
    bounds = (-1.5, -1.5, -1.5, 3.0)
    parts = []
    for i, region in enumerate(vdag._vdag.regions(1)):
        part = tmp_path / f"part-{i}.vdag"
        vdag.convert_region(sphere_obj, part, 6, region, bounds=bounds, colors=True)
        assert vdag.open(part).version[0] == 1, "a part is format 1"
        parts.append(part)
    # A partial merge is a part (format 1) whatever the version asked.
    half = vdag.merge(parts[:4], tmp_path / "half.vdag", format_version=2)
    assert not half["complete"] and half["format_version"] == 1
    assert vdag.open(tmp_path / "half.vdag").version[0] == 1
    for version, flags in ((2, []), (1, ["--format-version", "1"])):
        cli = tmp_path / f"whole-{version}.vdag"
        run(dagtool, "convert", sphere_obj, "-o", cli, "--depth", "6", "--colors", "--quiet",
            "--bounds", "-1.5,-1.5,-1.5,3", *flags)
        out = tmp_path / f"merged-{version}.vdag"
        kwargs = {"format_version": version} if flags else {}
        summary = vdag.merge([tmp_path / "half.vdag", *parts[4:]], out, **kwargs)
        assert summary["complete"] and summary["format_version"] == version
        assert out.read_bytes() == cli.read_bytes(), version
