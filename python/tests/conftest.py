"""Fixtures of the vdag tests: the command-line tools to compare against and
small generated inputs.

The tools are the `dagtool` and `dagtrace` binaries that `cargo test
--workspace` (or `cargo build`) leaves in the workspace's target folder:
`$VDAG_BIN_DIR`, else `$CARGO_TARGET_DIR/debug`, else `<repo>/target/debug`.
Without them the tests that need them are skipped with a message (under CI
they fail instead).
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def bin_dir() -> Path:
    if "VDAG_BIN_DIR" in os.environ:
        return Path(os.environ["VDAG_BIN_DIR"])
    target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
    return target / "debug"


def tool(name: str) -> Path:
    path = bin_dir() / name
    if not path.exists():
        message = f"{name} is not built in {path.parent} (run cargo build --workspace)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture(scope="session")
def dagtool() -> Path:
    return tool("dagtool")


@pytest.fixture(scope="session")
def dagtrace() -> Path:
    return tool("dagtrace")


def run(*args: object) -> subprocess.CompletedProcess:
    """Runs a command; a failure shows its stderr."""
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True)
    assert done.returncode == 0, f"{args}: {done.stderr}"
    return done


def write_sphere_obj(path: Path, segments: int = 24) -> Path:
    """A closed UV sphere of radius 1 at the origin, the upper half in
    material `red`, the lower in `blue` (an .mtl beside it)."""
    rings = segments // 2
    vertices = [(0.0, 1.0, 0.0)]
    for i in range(1, rings):
        phi = math.pi * i / rings
        for j in range(segments):
            theta = 2 * math.pi * j / segments
            vertices.append((math.sin(phi) * math.cos(theta), math.cos(phi), math.sin(phi) * math.sin(theta)))
    vertices.append((0.0, -1.0, 0.0))
    bottom = len(vertices)  # 1-based index of the south pole

    def ring(i: int, j: int) -> int:
        return 2 + (i - 1) * segments + j % segments

    upper, lower = [], []
    for j in range(segments):
        upper.append((1, ring(1, j + 1), ring(1, j)))
        lower.append((bottom, ring(rings - 1, j), ring(rings - 1, j + 1)))
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            (upper if i < rings // 2 else lower).extend([(a, b, d), (a, d, c)])
    path.with_suffix(".mtl").write_text("newmtl red\nKd 0.9 0.1 0.1\nnewmtl blue\nKd 0.1 0.2 0.9\n")
    lines = [f"mtllib {path.with_suffix('.mtl').name}"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines.append("usemtl red")
    lines += [f"f {a} {b} {c}" for a, b, c in upper]
    lines.append("usemtl blue")
    lines += [f"f {a} {b} {c}" for a, b, c in lower]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="session")
def sphere_obj(tmp_path_factory) -> Path:
    return write_sphere_obj(tmp_path_factory.mktemp("mesh") / "sphere.obj")


@pytest.fixture(scope="session", params=[1, 2], ids=["v1", "v2"])
def sphere_vdag(request, tmp_path_factory, sphere_obj, dagtool) -> Path:
    """The sphere at depth 7 with its colours, converted by dagtool, in
    format 1.0 and in format 2.0 (each test that takes it runs on both)."""
    out = tmp_path_factory.mktemp("vdag") / f"sphere-v{request.param}.vdag"
    run(dagtool, "convert", sphere_obj, "-o", out, "--depth", "7", "--colors", "--solid", "--quiet",
        "--format-version", request.param)
    return out


def random_rays(count: int, seed: int, center=(0.0, 0.0, 0.0), radius: float = 2.5):
    """Rays from points on a sphere around `center` towards points near it."""
    rng = np.random.default_rng(seed)
    start = rng.normal(size=(count, 3))
    start *= radius / np.linalg.norm(start, axis=1, keepdims=True)
    target = rng.uniform(-0.9, 0.9, size=(count, 3))
    origins = (np.asarray(center) + start).astype(np.float32)
    directions = (target - start).astype(np.float32)
    return origins, directions


def write_binary_rays(path: Path, origins, directions, tmin=0.0, tmax=math.inf, level=None) -> Path:
    """A VRAY batch (spec/VDAG.md §21.3)."""
    n = len(origins)
    record = np.dtype(
        [("o", "<f4", 3), ("d", "<f4", 3), ("tmin", "<f4"), ("tmax", "<f4"), ("level", "<u4"), ("flags", "<u4")]
    )
    rays = np.zeros(n, dtype=record)
    rays["o"], rays["d"] = origins, directions
    rays["tmin"], rays["tmax"] = tmin, tmax
    rays["level"] = 0xFFFFFFFF if level is None else level
    with open(path, "wb") as f:
        f.write(b"VRAY" + np.array([1], "<u4").tobytes() + np.array([n], "<u8").tobytes())
        f.write(rays.tobytes())
    return path


def read_binary_hits(path: Path) -> dict:
    """A VHIT batch (spec/VDAG.md §21.4) as columns named as TraceResult's."""
    data = Path(path).read_bytes()
    assert data[:4] == b"VHIT"
    n = int(np.frombuffer(data[8:16], "<u8")[0])
    record = np.dtype(
        [("flags", "<u4"), ("t", "<f4"), ("cell", "<u4", 3), ("level", "u1"), ("face", "u1"), ("reserved", "<u2"), ("index", "<u8")]
    )
    hits = np.frombuffer(data[16:], dtype=record, count=n)
    return {
        "hit": (hits["flags"] & 1).astype(bool),
        "t": hits["t"],
        "cell": hits["cell"],
        "level": hits["level"],
        "face": hits["face"],
        "index": hits["index"].astype(np.int64),  # 0xFFFF... (none) becomes -1
    }
