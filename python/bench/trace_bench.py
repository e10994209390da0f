"""Dag.trace against the Rust batch API on the same file and rays.

    cargo build --release -p dagtrace --example batch_time
    pip install ./python          # a release build (maturin's default profile)
    python python/bench/trace_bench.py FILE.vdag [--rays 1000000] [--rounds 5] [--runs 3]

Random rays through the file's root cube (origins on a sphere around it,
directions towards points inside it), float32, C-contiguous: the layout that
Dag.trace reads in place. Each round runs the Rust example (one untimed run,
then --runs timed runs of Tracer::trace_batch) and then as many timed runs of
Dag.trace (after an untimed one), so that a loaded machine slows both alike;
the figures are the medians over all timed runs, and the median of the
per-round ratios.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import vdag

REPO = Path(__file__).resolve().parents[2]


def write_binary_rays(path: Path, origins, directions) -> Path:
    """A VRAY batch (spec/VDAG.md §21.3) over [0, inf] at full depth."""
    record = np.dtype([("o", "<f4", 3), ("d", "<f4", 3), ("tmin", "<f4"), ("tmax", "<f4"), ("level", "<u4"), ("flags", "<u4")])
    rays = np.zeros(len(origins), dtype=record)
    rays["o"], rays["d"], rays["tmax"], rays["level"] = origins, directions, np.inf, 0xFFFFFFFF
    with open(path, "wb") as f:
        f.write(b"VRAY" + np.array([1], "<u4").tobytes() + np.array([len(rays)], "<u8").tobytes() + rays.tobytes())
    return path


def rays_through(dag: vdag.Dag, count: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    center = np.asarray(dag.root_min) + dag.root_size / 2
    start = rng.normal(size=(count, 3))
    start *= dag.root_size / np.linalg.norm(start, axis=1, keepdims=True)
    target = rng.uniform(-0.5, 0.5, size=(count, 3)) * dag.root_size
    return (center + start).astype(np.float32), (target - start).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("file")
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--example", default=str(Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target")) / "release/examples/batch_time"))
    args = parser.parse_args()

    dag = vdag.open(args.file)
    origins, directions = rays_through(dag, args.rays)
    rust_times, python_times, ratios = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        rays = write_binary_rays(Path(tmp) / "rays.vray", origins, directions)
        result = dag.trace(origins, directions)  # untimed: pages in, pool started
        for _ in range(args.rounds):
            out = subprocess.run([args.example, args.file, str(rays), str(args.runs)], capture_output=True, text=True, check=True)
            rust = [float(line) for line in out.stdout.split()]
            py = []
            for _ in range(args.runs):
                del result
                start = time.perf_counter()
                result = dag.trace(origins, directions)
                py.append(time.perf_counter() - start)
            rust_times += rust
            python_times += py
            ratios.append(statistics.median(py) / statistics.median(rust))
    rust_median, python_median = statistics.median(rust_times), statistics.median(python_times)
    print(f"{args.file}: {args.rays} rays, {int(result.hit.sum())} hits, {os.cpu_count()} CPUs")
    print(f"Rust Tracer::trace_batch: median {rust_median * 1e3:.1f} ms ({args.rays / rust_median / 1e6:.2f} Mrays/s) over {len(rust_times)} runs")
    print(f"Python Dag.trace:         median {python_median * 1e3:.1f} ms ({args.rays / python_median / 1e6:.2f} Mrays/s) over {len(python_times)} runs")
    print(f"ratio Python / Rust: {python_median / rust_median:.3f} (medians); per-round ratios {', '.join(f'{r:.3f}' for r in ratios)}, median {statistics.median(ratios):.3f}")


if __name__ == "__main__":
    main()
