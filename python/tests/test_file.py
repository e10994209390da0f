"""vdag.open and the Dag's queries against dagtool on the same files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import vdag
from conftest import REPO, run


def morton(xyz: np.ndarray) -> np.ndarray:
    """Morton codes of (N, 3) coordinates (x in the lowest bit of each triple)."""
    code = np.zeros(len(xyz), dtype=np.uint64)
    for bit in range(21):
        for axis in range(3):
            b = (xyz[:, axis].astype(np.uint64) >> np.uint64(bit)) & np.uint64(1)
            code |= b << np.uint64(3 * bit + axis)
    return code


@pytest.fixture(scope="module", params=[1, 2], ids=["v1", "v2"])
def voxel_list(request, tmp_path_factory, dagtool):
    """A random voxel list at depth 6 and the .vdag dagtool makes of it, in
    format 1.0 and in format 2.0."""
    rng = np.random.default_rng(45)
    xyz = np.unique(rng.integers(0, 64, size=(3000, 3)), axis=0)
    # A dense block too, so that the DAG has full leaves and shared subtrees.
    block = np.stack(np.meshgrid(*[np.arange(8, 16)] * 3, indexing="ij"), -1).reshape(-1, 3)
    xyz = np.unique(np.concatenate([xyz, block]), axis=0)
    folder = tmp_path_factory.mktemp("list")
    listing = folder / "voxels.txt"
    listing.write_text("".join(f"{x} {y} {z}\n" for x, y, z in xyz))
    out = folder / "voxels.vdag"
    run(dagtool, "convert", listing, "-o", out, "--depth", "6", "--quiet", "--format-version", request.param)
    return xyz, out


def test_header_and_levels_are_those_of_dagtool_info(voxel_list, dagtool):
    _, path = voxel_list
    info = json.loads(run(dagtool, "info", "--json", path).stdout)
    dag = vdag.open(path)
    assert dag.depth == info["depth"] == 6
    assert dag.resolution == info["resolution"] == 64
    assert dag.voxel_count == info["voxel_count"]
    assert dag.section_count == info["section_count"]
    assert dag.attribute_kind == info["attribute_kind"]
    assert list(dag.root_min) == info["root_min"]
    assert dag.root_size == info["root_size"]
    assert dag.file_size == info["file_bytes"] == path.stat().st_size
    assert dag.required_features == info["required_features"]
    assert dag.optional_features == info["optional_features"]
    assert list(dag.version) == info["version"]
    assert dag.color_format is None
    if dag.version[0] == 1:
        keys = ("level", "kind", "nodes", "bytes", "pointer_width")
        mine = [{k: level[k] for k in keys} for level in dag.levels]
        theirs = [{k: level[k] for k in keys} for level in info["levels"]]
        assert all(level["widths"] is None for level in dag.levels)
        assert info["v2_levels"] is None
    else:
        # A 2.0 file's levels are info's v2_levels (its levels describe the
        # DAG of the same voxels in 1.0 form).
        assert dag.version == (2, 0)
        mine = [(level["kind"], level["nodes"], level["bytes"], list(level["widths"])) for level in dag.levels]
        theirs = [(level["kind"], level["items"], level["bytes"], level["widths"]) for level in info["v2_levels"]]
        assert [level["level"] for level in dag.levels] == list(range(dag.depth - 1))
        assert all(level["pointer_width"] is None for level in dag.levels)
        assert sum(level["bytes"] for level in dag.levels) == info["level_bytes"]
    assert mine == theirs
    # The sections lie in the file in level order, 8-byte aligned.
    offsets = [level["offset"] for level in dag.levels]
    assert offsets == sorted(offsets) and all(o % 8 == 0 for o in offsets)


def test_voxels_are_the_listed_voxels_in_morton_order(voxel_list):
    xyz, path = voxel_list
    dag = vdag.open(path)
    voxels = dag.voxels()
    assert voxels.dtype == np.uint32 and voxels.shape == (len(xyz), 3)
    assert dag.voxel_count == len(xyz)
    expected = xyz[np.argsort(morton(xyz))]
    np.testing.assert_array_equal(voxels, expected)


def test_chunked_voxels_concatenate_to_all_voxels(voxel_list):
    _, path = voxel_list
    dag = vdag.open(path)
    chunks = list(dag.iter_voxels(chunk=1000))
    assert [len(c) for c in chunks[:-1]] == [1000] * (len(chunks) - 1)
    assert 0 < len(chunks[-1]) <= 1000
    np.testing.assert_array_equal(np.concatenate(chunks), dag.voxels())
    # Dropping an iterator half-way stops its thread; the file stays usable.
    it = dag.iter_voxels(chunk=10)
    next(it)
    del it
    with pytest.raises(ValueError):
        dag.iter_voxels(chunk=0)


def test_contains_and_attribute_index_agree_with_the_voxels(voxel_list):
    xyz, path = voxel_list
    dag = vdag.open(path)
    voxels = dag.voxels()
    rng = np.random.default_rng(7)
    probes = np.concatenate([voxels, rng.integers(-3, 67, size=(5000, 3))])
    inside = set(map(tuple, xyz.tolist()))
    expected = np.array([tuple(p) in inside for p in probes.tolist()])
    np.testing.assert_array_equal(dag.contains(probes), expected)
    rank = {tuple(v): i for i, v in enumerate(voxels.tolist())}
    expected_index = np.array([rank.get(tuple(p), -1) for p in probes.tolist()])
    index = dag.attribute_index(probes)
    assert index.dtype == np.int64
    np.testing.assert_array_equal(index, expected_index)
    # uint32 input, and a wrong shape.
    np.testing.assert_array_equal(dag.contains(voxels.astype(np.uint32)), np.ones(len(voxels), bool))
    with pytest.raises(ValueError):
        dag.contains(np.zeros((4, 2), dtype=np.int64))


def test_colors_are_in_voxel_order(sphere_vdag, dagtool, tmp_path):
    dag = vdag.open(sphere_vdag)
    assert dag.color_format == "raw"
    rgb = dag.colors()
    rgba = dag.colors(alpha=True)
    assert rgb.shape == (dag.voxel_count, 3) and rgb.dtype == np.uint8
    assert rgba.shape == (dag.voxel_count, 4)
    np.testing.assert_array_equal(rgba[:, :3], rgb)
    # The upper half's surface is red, the lower's blue (the solid interior
    # white): row i is the colour of voxel i.
    voxels = dag.voxels().astype(np.int64)
    red = (rgb[:, 0] > 128) & (rgb[:, 2] < 64)
    blue = (rgb[:, 2] > 128) & (rgb[:, 0] < 64)
    white = (rgb == 255).all(axis=1)
    assert red.any() and blue.any() and white.any()
    assert (red | blue | white).all()
    middle = dag.resolution // 2
    assert (voxels[red, 1] >= middle - 4).all() and (voxels[blue, 1] < middle + 4).all()
    # Packed colours (lossless) decode to the same colours.
    packed = tmp_path / "packed.vdag"
    run(dagtool, "recompress", sphere_vdag, "-o", packed, "--color-error", "0")
    dag_packed = vdag.open(packed)
    assert dag_packed.color_format == "packed"
    np.testing.assert_array_equal(dag_packed.colors(alpha=True), rgba)


def test_colors_is_none_without_colors(voxel_list):
    assert vdag.open(voxel_list[1]).colors() is None


def test_the_transport_form_opens_to_the_same_voxels(voxel_list, dagtool, tmp_path):
    _, path = voxel_list
    packed = tmp_path / "voxels.vdag.zst"
    run(dagtool, "pack", path, "-o", packed)
    np.testing.assert_array_equal(vdag.open(packed).voxels(), vdag.open(path).voxels())


VALIDATE_CASES = sorted((REPO / "conformance" / "cases" / "validate").glob("*.vdag"))


def test_validate_lists_what_dagtool_validate_lists(dagtool):
    assert VALIDATE_CASES, "the conformance cases are committed"
    done = run_json(dagtool, "validate", "--json", *VALIDATE_CASES)
    reports = {Path(r["file"]).name: r for r in done["files"]}
    for case in VALIDATE_CASES:
        mine = vdag.validate(case)
        theirs = [(e["code"], e["offset"], e["message"]) for e in reports[case.name]["errors"]]
        assert mine == theirs, case.name
        # A case is named after the code its file breaks, or `valid-`.
        if case.name.startswith("valid-"):
            assert mine == [], case.name
        else:
            assert case.name[:4] in [code for code, _, _ in mine], case.name


def run_json(*args):
    import subprocess

    done = subprocess.run([str(a) for a in args], capture_output=True, text=True)
    assert done.returncode in (0, 1), done.stderr
    return json.loads(done.stdout)


def test_open_raises_the_spec_code_of_an_invalid_file():
    case = next(c for c in VALIDATE_CASES if c.name.startswith("E002"))
    with pytest.raises(vdag.InvalidFileError) as raised:
        vdag.open(case)
    assert raised.value.code == "E002"
    assert raised.value.offset == 0
    assert str(case) in str(raised.value)
    assert isinstance(raised.value, vdag.VdagError)


def test_validate_of_a_valid_file_is_empty(voxel_list):
    assert vdag.validate(voxel_list[1]) == []


def test_a_missing_file_is_a_vdag_error(tmp_path):
    with pytest.raises(vdag.VdagError) as raised:
        vdag.open(tmp_path / "missing.vdag")
    assert raised.value.code is None
    assert "missing.vdag" in str(raised.value)
    with pytest.raises(vdag.VdagError):
        vdag.validate(tmp_path / "missing.vdag")


@pytest.mark.parametrize("case", VALIDATE_CASES, ids=lambda p: p.name)
def test_damaged_files_opened_without_validation_raise_vdag_errors_never_panic(case):
    """Every query on every malformed case either answers or raises a
    VdagError (a Rust panic would surface as pyo3's PanicException)."""
    try:
        dag = vdag.open(case, validate=False)
    except vdag.InvalidFileError as e:
        assert e.code and e.code.startswith("E")
        return
    rng = np.random.default_rng(1)
    probes = rng.integers(0, dag.resolution, size=(200, 3))
    origins = rng.uniform(-1, 2, size=(200, 3)) * dag.root_size + np.asarray(dag.root_min)
    directions = rng.normal(size=(200, 3))
    queries = [
        dag.voxels,
        lambda: list(dag.iter_voxels(chunk=16)),
        lambda: dag.contains(probes),
        lambda: dag.attribute_index(probes),
        dag.colors,
        lambda: dag.trace(origins, directions),
        lambda: dag.levels,
    ]
    for query in queries:
        try:
            query()
        except vdag.VdagError:
            pass
