"""Benchmark of vdag.distributed.convert against one `dagtool convert`.

    python python/bench/distributed_bench.py MESH DEPTH --bounds X,Y,Z,S \
        [--region-level 2] [--workers 1 2 4] [--repeats 3] [--dagtool PATH]

For each worker count W it runs, alternated with the single conversion, a
LocalCluster of W processes with one thread each (`--threads` to change),
checks that the output is byte-identical, and prints one JSON document:
the medians, their ratio, every region's build time and every merge step's
time and bytes, and the scaling model checked against the measured counts:

    T(W) = greedy makespan of the region times on W workers
           + the critical path of the merge tree (the slowest merge of each
             level of the tree, summed) + a constant overhead c,

c fitted as the median residual of the measurements. Projections for
larger depths scale region and merge times by the voxel count (x4 per level
for surfaces; `--growth`) with 8**K regions kept near 8 per worker.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path


def makespan(times: list[float], workers: int) -> float:
    loads = [0.0] * workers
    for t in sorted(times, reverse=True):
        heapq.heapreplace(loads, loads[0] + t)
    return max(loads)


def critical_path(merges: list[dict]) -> float:
    # Merges are listed bottom-up; a merge covering cells c0..c1 waits for
    # those below it: the slowest merge per distinct span width is summed.
    by_width: dict[int, float] = {}
    for m in merges:
        w = m["cells"][1] - m["cells"][0]
        by_width[w] = max(by_width.get(w, 0.0), m["wall_seconds"])
    return sum(by_width.values())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("input")
    ap.add_argument("depth", type=int)
    ap.add_argument("--bounds", required=True)
    ap.add_argument("--region-level", type=int, default=2)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--growth", type=float, default=4.0)
    ap.add_argument("--dagtool", default=str(Path(__file__).resolve().parents[2] / "target/release/dagtool"))
    ap.add_argument("--extra", nargs="*", default=[])
    a = ap.parse_args()

    import distributed
    import vdag.distributed

    bounds = tuple(float(b) for b in a.bounds.split(","))
    work = Path(tempfile.mkdtemp(prefix="vdag-bench-", dir=os.getcwd()))
    single = work / "single.vdag"
    result: dict = {"input": a.input, "depth": a.depth, "region_level": a.region_level, "runs": {}}
    singles: list[float] = []
    for w in a.workers:
        cluster = distributed.LocalCluster(n_workers=w, threads_per_worker=a.threads, processes=True, dashboard_address=None)
        client = distributed.Client(cluster)
        times, last = [], None
        for _ in range(a.repeats):
            t = time.perf_counter()
            subprocess.run([a.dagtool, "convert", a.input, "-o", single, "--depth", str(a.depth), "--bounds", a.bounds, "--force", "-q", *a.extra], check=True)
            singles.append(time.perf_counter() - t)
            out = work / "dask.vdag"
            t = time.perf_counter()
            last = vdag.distributed.convert(a.input, out, a.depth, client, region_level=a.region_level, bounds=bounds, force=True)
            times.append(time.perf_counter() - t)
            assert out.read_bytes() == single.read_bytes(), "not byte-identical"
        client.close()
        cluster.close()
        regions = [r["seconds"] for r in last["regions"]]
        model = makespan(regions, w * a.threads) + critical_path(last["merges"])
        result["runs"][w] = {
            "median_seconds": statistics.median(times),
            "times": times,
            "model_seconds_without_overhead": model,
            "regions": [{k: r[k] for k in ("region", "seconds", "voxels", "file_bytes")} for r in last["regions"]],
            "merges": last["merges"],
        }
    single_median = statistics.median(singles)
    result["single_median_seconds"] = single_median
    overhead = statistics.median(r["median_seconds"] - r["model_seconds_without_overhead"] for r in result["runs"].values())
    result["model_overhead_seconds"] = overhead
    for w, r in result["runs"].items():
        r["ratio_to_single"] = r["median_seconds"] / single_median
        r["model_seconds"] = r["model_seconds_without_overhead"] + overhead
    base = result["runs"][a.workers[-1]]
    regions = [x["seconds"] for x in base["regions"]]
    merges = base["merges"]
    projections = {}
    for depth in (18, 20):
        g = a.growth ** (depth - a.depth)
        for workers in (8, 64, 512):
            # Regions: the same total work, split into about 8 per worker.
            total = sum(regions) * g
            n = 8 ** max(1, round(__import__("math").log(8 * workers, 8)))
            region_time = makespan([total / n] * n, workers)
            levels = max(1, round(__import__("math").log(n, 8)))
            merge_time = sum(m["wall_seconds"] for m in merges if m["cells"][1] - m["cells"][0] == 8 ** a.region_level) * g
            projections[f"depth {depth}, {workers} workers"] = {
                "regions": n,
                "seconds": region_time + merge_time + levels * overhead,
            }
    result["projections"] = projections
    print(json.dumps(result, indent=1, default=str))


if __name__ == "__main__":
    main()
