"""Benchmark of vdag.distributed.convert against one `dagtool convert`, and
the scaling model of BENCHMARKS.md ("Conversions on a Dask cluster").

    python python/bench/distributed_bench.py overhead MESH DEPTH \
        [--workers 2] [--region-level 2] [--pairs 2] [--worker-memory 4GiB]
    python python/bench/distributed_bench.py scaling MESH DEPTH \
        [--workers 1 2 4] [--region-level 2] [--repeats 2]
    python python/bench/distributed_bench.py model RESULT.json... \
        [--bandwidth 1e9] [--cores 2]

`overhead` alternates one `dagtool convert` (release build, the same
`--bounds`, the same `--format-version`, 2 by default) with a Dask `LocalCluster` of W worker processes (one thread
each, `--worker-memory` each: Dask's nanny restarts a worker above it),
checks that the outputs are byte-identical, and reports the medians, their
ratio, each worker's peak resident memory (the task processes' high-water
marks), the single build's peak, and the load average before and after each
run. The cluster is started before the timed runs (its start-up, a few
seconds, is not counted: a cluster serves many conversions).

`scaling` runs the distributed convert on 1, 2 and 4 workers (a new cluster
each), alternated with the single build, and keeps every region's time
(parse, bin, build, write) and every merge step's time and bytes.

`model` fits the model below on those records and checks it against the
measured wall times, then projects depth 18 and 20 on 8, 64 and 512 workers.
Each prints one JSON document (and writes it to `--json`).

The model: T(W) = P + R(W) + M + X + c, where
  P    = parsing the input, once per worker process (the region builds of a
         worker keep the mesh), in parallel: the largest parse of a region;
  R(W) = the regions: list scheduling of the region build times r_i (parse
         excluded; measured alone on one worker) on W workers, in Dask's
         submission (Morton) order, each slowed by f(W) = max(1, W u / C)
         when W workers share C cores and one build keeps u cores busy
         (u = CPU seconds / wall seconds of the single build);
  M    = the merge tree's critical path: per level, the slowest merge,
         a merge costing m0 + beta * (bytes read), fitted on every merge;
  X    = transfer: the bytes read on the critical path / bandwidth (zero on
         one machine, where the parts are on the local disk: the merge's
         time includes reading them);
  c    = a constant (Dask scheduling, task start-up), the median residual.
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def fitted_bounds(mesh: str, depth: int) -> tuple[float, float, float, float]:
    """The root cube `dagtool convert` fits to an OBJ mesh at `depth`
    (GridMapping::fit), so that the distributed build, which needs the cube
    given, converts the same volume."""
    lo = [math.inf] * 3
    hi = [-math.inf] * 3
    with open(mesh, "rb") as f:
        for line in f:
            if line.startswith(b"v "):
                p = [float(w) for w in line.split()[1:4]]
                for a in range(3):
                    lo[a] = min(lo[a], p[a])
                    hi[a] = max(hi[a], p[a])
    extent = max(hi[a] - lo[a] for a in range(3))
    res = float(1 << depth)
    size = extent * res / (res - 1.0)
    mn = [0.5 * (lo[a] + hi[a]) - 0.5 * size for a in range(3)]
    return (mn[0], mn[1], mn[2], size)


def loadavg() -> list[float]:
    return list(os.getloadavg())


def single(dagtool: str, mesh: str, out: Path, depth: int, bounds: str, version: int) -> dict:
    """One `dagtool convert`: wall seconds, peak RSS, CPU seconds and its
    summary's time line."""
    t = time.perf_counter()
    p = subprocess.Popen(
        [dagtool, "convert", mesh, "-o", str(out), "--depth", str(depth), "--bounds", bounds, "--force",
         "--format-version", str(version)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    text = p.stdout.read().decode()
    err = p.stderr.read().decode()
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise SystemExit(f"dagtool convert failed: {err.strip()}")
    times = re.search(r"time:\s+(.*)", text)
    return {
        "seconds": wall,
        "peak_rss": usage.ru_maxrss * 1024,
        "cpu_seconds": usage.ru_utime + usage.ru_stime,
        "time_line": times.group(1) if times else None,
    }


def cluster(workers: int, memory: str):
    import distributed

    c = distributed.LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, memory_limit=memory
    )
    return c, distributed.Client(c)


def distributed_run(client, mesh: str, out: Path, depth: int, bounds, k: int, task_memory, fan_in: int,
                    version: int) -> dict:
    import vdag.distributed

    t = time.perf_counter()
    info = vdag.distributed.convert(
        mesh, out, depth, client, region_level=k, bounds=bounds, force=True, memory_limit=task_memory, fan_in=fan_in,
        format_version=version,
    )
    info["wall_seconds"] = time.perf_counter() - t
    peaks: dict[str, int] = {}
    for r in info["regions"] + info["merges"]:
        if r.get("peak_rss") is not None:
            peaks[r["worker"]] = max(peaks.get(r["worker"], 0), r["peak_rss"])
    info["worker_peak_rss"] = peaks
    return info


def same(a: Path, b: Path) -> bool:
    with open(a, "rb") as f, open(b, "rb") as g:
        while True:
            x, y = f.read(1 << 24), g.read(1 << 24)
            if x != y:
                return False
            if not x:
                return True


def slim(info: dict) -> dict:
    keys = ("region", "seconds", "parse_seconds", "bin_seconds", "build_seconds", "write_seconds",
            "wall_seconds", "voxels", "file_bytes", "worker", "peak_rss")
    return {
        "wall_seconds": info["wall_seconds"],
        "worker_peak_rss": info["worker_peak_rss"],
        "regions": [{k: r.get(k) for k in keys} for r in info["regions"]],
        "merges": info["merges"],
        "file_bytes": info["file_bytes"],
    }


def cmd_overhead(a) -> dict:
    bounds = fitted_bounds(a.input, a.depth)
    btext = ",".join(repr(b) for b in bounds)
    work = Path(tempfile.mkdtemp(prefix="vdag-bench-", dir=a.dir))
    one, many = work / "single.vdag", work / "dask.vdag"
    c, client = cluster(a.workers, a.worker_memory)
    res: dict = {"input": a.input, "depth": a.depth, "bounds": bounds, "workers": a.workers,
                 "worker_memory": a.worker_memory, "task_memory": a.task_memory,
                 "region_level": a.region_level, "fan_in": a.fan_in, "pairs": []}
    try:
        for i in range(a.pairs):
            pair = {}
            order = ("single", "dask") if i % 2 == 0 else ("dask", "single")
            for what in order:
                before = loadavg()
                if what == "single":
                    pair["single"] = single(a.dagtool, a.input, one, a.depth, btext, a.format_version)
                else:
                    pair["dask"] = slim(distributed_run(client, a.input, many, a.depth, bounds, a.region_level,
                                                       a.task_memory, a.fan_in, a.format_version))
                pair[what]["load_before"] = before
                pair[what]["load_after"] = loadavg()
                print(f"# pair {i} {what}: {pair[what].get('seconds', pair[what].get('wall_seconds')):.1f} s, "
                      f"load {pair[what]['load_after'][0]:.1f}", file=sys.stderr, flush=True)
            assert same(one, many), "the distributed output is not byte-identical"
            pair["ratio"] = pair["dask"]["wall_seconds"] / pair["single"]["seconds"]
            res["pairs"].append(pair)
    finally:
        client.close()
        c.close()
        for f in (one, many):
            f.unlink(missing_ok=True)
        work.rmdir()
    s = statistics.median(p["single"]["seconds"] for p in res["pairs"])
    d = statistics.median(p["dask"]["wall_seconds"] for p in res["pairs"])
    res["single_median_seconds"] = s
    res["dask_median_seconds"] = d
    res["ratio_of_medians"] = d / s
    res["median_of_ratios"] = statistics.median(p["ratio"] for p in res["pairs"])
    res["max_worker_peak_rss"] = max(v for p in res["pairs"] for v in p["dask"]["worker_peak_rss"].values())
    res["single_peak_rss"] = max(p["single"]["peak_rss"] for p in res["pairs"])
    return res


def cmd_scaling(a) -> dict:
    bounds = fitted_bounds(a.input, a.depth)
    btext = ",".join(repr(b) for b in bounds)
    work = Path(tempfile.mkdtemp(prefix="vdag-bench-", dir=a.dir))
    one, many = work / "single.vdag", work / "dask.vdag"
    res: dict = {"input": a.input, "depth": a.depth, "bounds": bounds, "region_level": a.region_level,
                 "fan_in": a.fan_in, "worker_memory": a.worker_memory, "singles": [], "runs": {}}
    try:
        for w in a.workers:
            c, client = cluster(w, a.worker_memory)
            runs = []
            try:
                for _ in range(a.repeats):
                    s = single(a.dagtool, a.input, one, a.depth, btext, a.format_version)
                    s["load_after"] = loadavg()
                    res["singles"].append(s)
                    info = slim(distributed_run(client, a.input, many, a.depth, bounds, a.region_level,
                                                a.task_memory, a.fan_in, a.format_version))
                    info["load_after"] = loadavg()
                    assert same(one, many), "the distributed output is not byte-identical"
                    runs.append(info)
                    print(f"# {w} workers: single {s['seconds']:.1f} s, dask {info['wall_seconds']:.1f} s, "
                          f"load {info['load_after'][0]:.1f}", file=sys.stderr, flush=True)
            finally:
                client.close()
                c.close()
            res["runs"][str(w)] = runs
    finally:
        for f in (one, many):
            f.unlink(missing_ok=True)
        work.rmdir()
    return res


def list_schedule(times: list[float], workers: int) -> float:
    """Dask's greedy assignment in submission order: each task to the first
    worker free."""
    free = [0.0] * workers
    for t in times:
        heapq.heapreplace(free, free[0] + t)
    return max(free)


def fit_line(xs: list[float], ys: list[float]) -> tuple[float, float]:
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    if sxx == 0:
        # One size of merge only: the cost taken as proportional to the bytes.
        return 0.0, my / mx if mx else 0.0
    b = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx
    return my - b * mx, b


def merge_path(merges: list[dict], m0: float, beta: float) -> tuple[float, float]:
    """The merge tree's critical path by the fitted cost, and the bytes read
    on it: per level (merges are listed bottom-up; a level is the width of
    the cell range a merge covers), the merge with most bytes."""
    by_width: dict[int, int] = {}
    for m in merges:
        w = m["cells"][1] - m["cells"][0]
        by_width[w] = max(by_width.get(w, 0), m["input_bytes"])
    return sum(m0 + beta * b for b in by_width.values()), float(sum(by_width.values()))


def cmd_model(a) -> dict:
    docs = [json.loads(Path(p).read_text()) for p in a.results]
    scaling = [d for d in docs if "runs" in d]
    if not scaling:
        raise SystemExit("model needs the JSON of a `scaling` run")
    d = scaling[0]
    singles = d["singles"]
    u = statistics.median(s["cpu_seconds"] / s["seconds"] for s in singles)
    base = d["runs"]["1"]
    # Region build times alone on one worker (parse excluded), median over repeats.
    # (The records are in Morton order, Dask's submission order.)
    names = [r["region"] for r in base[0]["regions"]]
    r_alone = {n: statistics.median(run["regions"][i]["seconds"] - run["regions"][i]["parse_seconds"]
                                    for run in base) for i, n in enumerate(names)}
    parse = statistics.median(max(r["parse_seconds"] for r in run["regions"]) for run in base)
    merges = [m for runs in d["runs"].values() for run in runs for m in run["merges"]]
    m0, beta = fit_line([m["input_bytes"] for m in merges], [m["wall_seconds"] for m in merges])
    by_index = [r_alone[n] for n in names]

    def predict(w: int, cores: float, regions: list[float], merges_: list[dict], bandwidth: float) -> dict:
        f = max(1.0, w * u / cores) if cores else 1.0
        R = list_schedule([t * f for t in regions], w)
        M, path_bytes = merge_path(merges_, m0, beta)
        X = path_bytes / bandwidth if bandwidth else 0.0
        return {"P": parse * f, "R": R, "M": M, "X": X, "slowdown": f}

    check = {}
    residuals = []
    for w, runs in d["runs"].items():
        p = predict(int(w), a.cores, by_index, runs[0]["merges"], 0.0)
        measured = statistics.median(r["wall_seconds"] for r in runs)
        p["measured"] = measured
        p["without_c"] = p["P"] + p["R"] + p["M"] + p["X"]
        residuals.append(measured - p["without_c"])
        check[w] = p
    c = statistics.median(residuals)
    for p in check.values():
        p["model"] = p["without_c"] + c
        p["error"] = p["model"] / p["measured"] - 1
    # Growth per depth level of the region work and the bytes: fitted on the
    # single builds of the depths given (the `overhead` JSONs), else 4 (a
    # surface: 4x the voxels per level).
    growth = a.growth
    depth0 = d["depth"]
    total_r = sum(by_index)
    part_bytes = sum(r["file_bytes"] for r in base[0]["regions"])
    out_bytes = base[0]["file_bytes"]
    proj = {}
    k0 = d["region_level"]
    r_max = max(by_index)
    for depth in (18, 20):
        g = growth ** (depth - depth0)
        for w in (8, 64, 512):
            k = max(1, math.ceil(math.log(8 * w, 8)))  # at least 8 regions per worker
            k = min(k, depth - 2)
            n = 8 ** k
            # The regions: the work spread over W workers, but no faster than
            # the largest region (a surface cell's work shrinks 4x per level).
            largest = r_max * g / 4 ** (k - k0)
            R = max(total_r * g / w, largest)
            # The merge tree: k levels of fan-in 8; the level j below the top
            # reads about the parts' bytes / 8^j in one merge.
            level_bytes = [part_bytes * a.byte_growth ** (depth - depth0) / 8 ** j for j in range(k)]
            M = sum(m0 + beta * b for b in level_bytes)
            X = sum(level_bytes) / a.bandwidth
            proj[f"d{depth} W={w}"] = {
                "regions": n, "region_level": k, "P": parse, "R": R, "M": M, "X": X, "c": c,
                "seconds": parse + R + M + X + c, "output_bytes": out_bytes * a.byte_growth ** (depth - depth0),
            }
    return {
        "input": d["input"], "depth": depth0, "u_cores_per_build": u, "parse_seconds": parse,
        "region_seconds_total": total_r, "region_seconds_max": r_max, "merge_m0": m0, "merge_beta_s_per_byte": beta,
        "c": c, "growth_per_level": growth, "byte_growth_per_level": a.byte_growth, "bandwidth": a.bandwidth, "cores": a.cores,
        "check": check, "projections": proj, "single_median_seconds": statistics.median(s["seconds"] for s in singles),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("overhead", "scaling"):
        p = sub.add_parser(name)
        p.add_argument("input")
        p.add_argument("depth", type=int)
        p.add_argument("--region-level", type=int, default=2)
        p.add_argument("--fan-in", type=int, default=8)
        p.add_argument("--format-version", type=int, default=2, choices=(1, 2),
                       help="the version both the single build and the distributed one write")
        p.add_argument("--worker-memory", default="4GiB")
        p.add_argument("--task-memory", default=None, help="each task's memory_limit (default: the converter's)")
        p.add_argument("--dagtool", default=str(ROOT / "target/release/dagtool"))
        p.add_argument("--dir", default=os.getcwd(), help="where the outputs go")
        p.add_argument("--json")
        if name == "overhead":
            p.add_argument("--workers", type=int, default=2)
            p.add_argument("--pairs", type=int, default=2)
        else:
            p.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
            p.add_argument("--repeats", type=int, default=2)
    p = sub.add_parser("model")
    p.add_argument("results", nargs="+")
    p.add_argument("--bandwidth", type=float, default=1e9, help="bytes/s between workers and the shared storage")
    p.add_argument("--cores", type=float, default=os.cpu_count())
    p.add_argument("--growth", type=float, default=4.0, help="region work per depth level (a surface: 4)")
    p.add_argument("--byte-growth", type=float, default=2.92,
                   help="file bytes per depth level (the dragon: 172 MB at d14, 1.47 GB at d16)")
    p.add_argument("--json")
    a = ap.parse_args()
    res = {"overhead": cmd_overhead, "scaling": cmd_scaling, "model": cmd_model}[a.cmd](a)
    text = json.dumps(res, indent=1, default=str)
    if a.json:
        Path(a.json).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
