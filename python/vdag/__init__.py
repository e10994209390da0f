"""Read, trace, render and build .vdag sparse voxel DAGs with numpy.

>>> import vdag
>>> dag = vdag.open("bunny.vdag")        # format 1.x or 2.0, memory-mapped, validated
>>> dag.version, dag.depth, dag.voxel_count
>>> xyz = dag.voxels()                    # (N, 3) uint32, Morton order
>>> hits = dag.trace(origins, directions) # (N, 3) float arrays
>>> hits.hit, hits.t, hits.cell, hits.face, hits.index

The format is specified in spec/VDAG.md; the command-line tools ``dagtool``
and ``dagtrace`` give the same answers as this package.
"""

from ._vdag import (
    Dag,
    TraceResult,
    VoxelChunks,
    __version__,
    clear_input_cache,
    convert,
    convert_region,
    merge,
    open,
    render,
    validate,
)
from .errors import ConvertError, GpuError, InvalidFileError, TraceError, VdagError

__all__ = [
    "Dag",
    "TraceResult",
    "VoxelChunks",
    "open",
    "validate",
    "convert",
    "convert_region",
    "clear_input_cache",
    "merge",
    "render",
    "VdagError",
    "InvalidFileError",
    "ConvertError",
    "TraceError",
    "GpuError",
    "__version__",
]
