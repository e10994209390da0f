"""Conversions too large for one machine, on a Dask distributed cluster.

:func:`convert` splits the root cube into the ``8**region_level`` cells of
level ``region_level``, builds each cell into a *part* on the workers
(:func:`vdag.convert_region`, ``dagtool convert --region``), joins the parts
by a tree reduction of merges on the workers (:func:`vdag.merge`,
``dagtool merge``) and writes the output: byte for byte the file one
``vdag.convert`` / ``dagtool convert`` of the whole input writes with the same
options (spec/VDAG.md § 24).

The same code runs on any Dask deployment; only the client changes::

    client = distributed.Client(distributed.LocalCluster(n_workers=2))
    vdag.distributed.convert("city.laz", "city.vdag", 18, client,
                             region_level=2, bounds=(0, 0, 0, 4096))

The input, the output's directory and ``scratch`` must be paths every worker
sees (a shared file system). Parts go to ``scratch`` (default: a new
directory beside the output), which is removed at the end.

Each worker process parses a mesh input once and keeps it for the next
region it builds (:func:`vdag.convert_region`'s ``cache_input``); a region
then bins and voxelizes only the triangles of its own cell, so the regions
together do the work of one build. The workers free the mesh when the job
ends.

A region task that fails for a reason of the input (a bad file, an
impossible option) is not retried: :func:`convert` raises one
``vdag.ConvertError`` naming the region. A worker that dies (killed, out of
memory) only loses its running tasks, which Dask runs again elsewhere; every
task writes its file atomically and overwrites a leftover of an earlier
attempt, so the output is the same file.

LAS/LAZ tiles: pass a list of tile paths as ``input``; they are read as one
cloud, in that order, and each region task opens every tile's header but
reads the points of only the tiles whose header bounds meet its cell (grown
by ``point_radius``).
"""

from __future__ import annotations

import os
import shutil
import socket
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Optional, Sequence, Union

from . import _vdag
from .errors import ConvertError

_PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["convert"]


def _error(message: str, kind: str, code: Optional[str] = None) -> ConvertError:
    e = ConvertError(message, code)
    e.kind = kind
    return e


def _error_value(region: str, e: BaseException) -> dict[str, Any]:
    return {
        "error": f"{region}: {getattr(e, 'message', str(e))}",
        "code": getattr(e, "code", None),
        "kind": getattr(e, "kind", "input"),
    }


def _where() -> dict[str, Any]:
    """The worker process a task ran in, and that process's peak resident
    bytes so far (a worker's peak is the largest over its tasks)."""
    try:
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peak *= 1 if sys.platform == "darwin" else 1024  # bytes there, KiB on Linux
    except (ImportError, OSError):  # Windows
        peak = None
    return {"worker": f"{socket.gethostname()}:{os.getpid()}", "peak_rss": peak}


def _build_region(
    inputs: list[str],
    part: str,
    depth: int,
    region: tuple[int, int, int, int],
    options: dict[str, Any],
    delay: float,
) -> dict[str, Any]:
    """A worker's task: one region into one part. Errors of the input come
    back as values (Dask would retry an exception, and they would fail
    again); a dying worker is Dask's to retry."""
    if delay:
        time.sleep(delay)
    name = "{}:{},{},{}".format(*region)
    try:
        t = time.perf_counter()
        source = inputs[0] if len(inputs) == 1 else inputs
        info = _vdag.convert_region(source, part, depth, region, force=True, **options)
        info["wall_seconds"] = time.perf_counter() - t
        info["part"] = part
        info.update(_where())
        return info
    except Exception as e:  # noqa: BLE001 - every failure becomes one clear error
        return _error_value(name, e)


def _clear_cache() -> bool:
    """A worker's task: free the mesh its region builds kept."""
    return _vdag.clear_input_cache()


def _merge(infos: list[dict[str, Any]], out: str, memory_limit, format_version: int = 2) -> dict[str, Any]:
    """A worker's task: merge the parts of ``infos`` (or pass an error on).
    It overwrites its output: a leftover of an attempt on a worker that died
    (the final output was checked before the job began). A merge short of
    the whole volume writes a part (format 1); ``format_version`` is that
    of the whole volume."""
    for i in infos:
        if "error" in i:
            return i
    try:
        t = time.perf_counter()
        info = _vdag.merge(
            [i["part"] for i in infos], out, memory_limit=memory_limit, force=True, format_version=format_version
        )
        info["part"] = out
        info["wall_seconds"] = time.perf_counter() - t
        info["inputs"] = len(infos)
        info.update(_where())
        info["merges"] = [m for i in infos for m in i.get("merges", [])] + [
            {
                k: info[k]
                for k in ("wall_seconds", "input_bytes", "file_bytes", "inputs", "cells", "worker", "peak_rss")
            }
        ]
        info["regions"] = [r for i in infos for r in i.get("regions", [i] if "region" in i else [])]
        return info
    except Exception as e:  # noqa: BLE001
        return _error_value("merge of {} parts into {}".format(len(infos), out), e)


def convert(
    input: Union[_PathLike, Sequence[_PathLike]],
    output: _PathLike,
    depth: int,
    client: Any,
    region_level: int = 1,
    *,
    bounds: Sequence[float],
    colors: bool = False,
    solid: bool = False,
    color_error: Optional[int] = None,
    point_radius: float = 0.0,
    memory_limit: Optional[Union[int, str]] = None,
    force: bool = False,
    scratch: Optional[_PathLike] = None,
    fan_in: int = 8,
    format_version: int = 2,
    _task_delay: float = 0.0,
) -> dict[str, Any]:
    """Converts ``input`` to ``output`` at ``depth`` on the Dask ``client``'s
    workers, split into the ``8**region_level`` cells of level
    ``region_level`` (at most ``depth - 2``), and returns a summary dict:
    ``voxels``, ``file_bytes``, ``seconds``, ``regions`` (one dict per
    region: ``region``, ``voxels``, ``file_bytes``, ``seconds`` and its
    parts ``parse_seconds``, ``bin_seconds``, ``build_seconds``,
    ``write_seconds``; ``wall_seconds``, ``worker``, ``peak_rss``)
    and ``merges`` (one dict per merge step: ``wall_seconds``,
    ``input_bytes``, ``file_bytes``, ``inputs``, ``cells``).

    ``bounds`` ``(xmin, ymin, zmin, size)`` is the root cube, required: every
    region must use the same one. ``colors``, ``solid``, ``color_error``,
    ``point_radius`` and ``format_version`` (2, the default, or 1) are those
    of :func:`vdag.convert`; ``memory_limit`` is each task's. ``input`` may be a list of LAS/LAZ tiles. Merges take up to
    ``fan_in`` parts each. Raises ``vdag.ConvertError`` (nothing written)
    when a region or a merge fails, naming it.
    """
    start = time.perf_counter()
    output = os.path.abspath(os.fspath(output))
    if os.path.exists(output) and not force:
        raise _error(f"output {output} already exists (use force=True to overwrite it)", "usage")
    if bounds is None or len(bounds) != 4:
        raise _error("bounds (xmin, ymin, zmin, size) is required: every region needs the same root cube", "usage")
    if fan_in < 2:
        raise _error("fan_in must be at least 2", "usage")
    tiles = not isinstance(input, (str, os.PathLike))
    inputs = [os.path.abspath(os.fspath(p)) for p in (input if tiles else [input])]
    regions = _vdag.regions(region_level)
    own_scratch = scratch is None
    scratch = Path(scratch) if scratch is not None else Path(output).parent / f".vdag-parts-{uuid.uuid4().hex}"
    scratch.mkdir(parents=True, exist_ok=True)
    options = {
        "bounds": tuple(float(b) for b in bounds),
        "colors": colors,
        "solid": solid,
        "color_error": color_error,
        "point_radius": point_radius,
        "memory_limit": memory_limit,
    }
    token = uuid.uuid4().hex[:8]
    try:
        level = [
            client.submit(
                _build_region,
                inputs,
                str(scratch / f"region-{i}.part"),
                depth,
                r,
                options,
                _task_delay,
                key=f"vdag-region-{region_level}-{i}-{token}",
                pure=False,
            )
            for i, r in enumerate(regions)
        ]
        step = 0
        while True:
            groups = [level[i : i + fan_in] for i in range(0, len(level), fan_in)]
            final = len(groups) == 1
            step += 1
            level = [
                client.submit(
                    _merge,
                    g,
                    output if final else str(scratch / f"merge-{step}-{j}.part"),
                    memory_limit,
                    format_version,
                    key=f"vdag-merge-{step}-{j}-{token}",
                    pure=False,
                )
                for j, g in enumerate(groups)
            ]
            if final:
                break
        info = level[0].result()
    finally:
        if own_scratch:
            shutil.rmtree(scratch, ignore_errors=True)
        try:
            # The workers parsed the mesh once each and kept it for their
            # next region (convert_region's cache_input); free it now.
            client.run(_clear_cache)
        except Exception:  # noqa: BLE001 - a worker that is gone holds nothing
            pass
    if "error" in info:
        raise _error(info["error"], info.get("kind") or "input", info.get("code"))
    if not info.get("complete"):
        raise _error(f"the merge of every region of {output} does not cover the root cube", "input")
    return {
        "voxels": info["voxels"],
        "file_bytes": info["file_bytes"],
        "seconds": time.perf_counter() - start,
        "regions": info["regions"],
        "merges": info["merges"],
    }
