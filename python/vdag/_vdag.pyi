"""Type stubs of the native module vdag._vdag (python/src/)."""

import os
from typing import Any, Callable, Iterator, Literal, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

__version__: str

_Path = Union[str, os.PathLike[str]]
_Points = npt.ArrayLike
_Backend = Literal["cpu", "gpu"]
_Shade = Literal["lit", "normal", "depth", "color"]
_Vec3 = Union[Sequence[float], npt.ArrayLike]

class Dag:
    """A .vdag file of format 1.x or 2.0 opened for reading (memory-mapped);
    made by :func:`open`. Every method answers alike for both versions."""

    @property
    def path(self) -> str:
        """The path the file was opened from."""
    @property
    def version(self) -> tuple[int, int]:
        """The format version as (major, minor): (1, minor) or (2, 0)."""
    @property
    def depth(self) -> int:
        """The depth D: 2**D voxels along each axis."""
    @property
    def resolution(self) -> int:
        """Voxels along each axis, 2**depth."""
    @property
    def attribute_kind(self) -> int:
        """0 (no attribute) or 1 (voxel counts: the attribute index)."""
    @property
    def voxel_count(self) -> int:
        """The number of set voxels, from the header."""
    @property
    def root_min(self) -> tuple[float, float, float]:
        """The world-space minimum corner of the root cube."""
    @property
    def root_size(self) -> float:
        """The world-space edge of the root cube."""
    @property
    def file_size(self) -> int:
        """The file's size in bytes, from the header."""
    @property
    def required_features(self) -> int:
        """The required feature bits of the header."""
    @property
    def optional_features(self) -> int:
        """The optional feature bits of the header."""
    @property
    def section_count(self) -> int:
        """The number of entries of the section table."""
    @property
    def color_format(self) -> Optional[Literal["raw", "packed"]]:
        """The colour section's kind, or None without colours."""
    @property
    def levels(self) -> list[dict[str, Any]]:
        """One dict per level section, root first: level, kind ("node" or
        "leaf"), nodes, bytes, offset, pointer_width (1.x: bytes per pointer;
        2.0: None) and widths (2.0: the three reference widths in bits;
        1.x: None)."""
    def voxels(self) -> npt.NDArray[np.uint32]:
        """Every set voxel as an (N, 3) uint32 array, in Morton order."""
    def iter_voxels(self, chunk: int = 1 << 20) -> "VoxelChunks":
        """The set voxels in Morton order, as (<= chunk, 3) uint32 arrays."""
    def contains(self, xyz: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Whether each voxel of an (N, 3) integer array is set."""
    def attribute_index(self, xyz: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """The Morton rank of each voxel of an (N, 3) integer array among the
        set voxels; -1 where it is not set or lies outside the grid."""
    def colors(self, alpha: bool = False) -> Optional[npt.NDArray[np.uint8]]:
        """The voxel colours in voxel order: (N, 3) RGB, or (N, 4) RGBA with
        alpha=True; None without colours."""
    def trace(
        self,
        origins: _Points,
        directions: _Points,
        tmin: float = 0.0,
        tmax: float = float("inf"),
        level: Optional[int] = None,
        backend: _Backend = "cpu",
    ) -> "TraceResult":
        """Traces N rays ((N, 3) float arrays; C-contiguous float32/float64
        read in place) on all cores without the GIL, or on the GPU."""
    def render(
        self,
        width: int = 1280,
        height: int = 720,
        camera_pos: Optional[_Vec3] = None,
        look_at: Optional[_Vec3] = None,
        fov: float = 40.0,
        shade: _Shade = "lit",
        sun: Optional[_Vec3] = None,
        ao_rays: Optional[int] = None,
        ao_radius: Optional[float] = None,
        samples: Optional[int] = None,
        level: Optional[int] = None,
        backend: _Backend = "cpu",
    ) -> npt.NDArray[np.uint8]:
        """The (height, width, 3) uint8 image `dagtrace render` writes."""

class VoxelChunks(Iterator[npt.NDArray[np.uint32]]):
    """Iterator of (<= chunk, 3) uint32 arrays of voxel coordinates."""

    def __iter__(self) -> "VoxelChunks": ...
    def __next__(self) -> npt.NDArray[np.uint32]: ...

class TraceResult:
    """The answers of Dag.trace, one row per ray; a miss has hit False, t 0,
    cell (0, 0, 0), level 0, face 0 and index -1."""

    @property
    def hit(self) -> npt.NDArray[np.bool_]:
        """Whether each ray hit an occupied cell."""
    @property
    def t(self) -> npt.NDArray[np.float32]:
        """The ray parameter where it enters the cell."""
    @property
    def cell(self) -> npt.NDArray[np.uint32]:
        """(N, 3) cell coordinates at the traced level."""
    @property
    def level(self) -> npt.NDArray[np.uint8]:
        """The traced level."""
    @property
    def face(self) -> npt.NDArray[np.uint8]:
        """Entry face: 0 = started inside, 1..6 = -X +X -Y +Y -Z +Z."""
    @property
    def index(self) -> npt.NDArray[np.int64]:
        """The attribute index of the cell's first voxel, -1 for none."""
    def as_dict(self) -> dict[str, npt.NDArray[Any]]:
        """The answers as a dict of arrays."""
    def __len__(self) -> int: ...

def open(path: _Path, validate: bool = True) -> Dag:
    """Opens (memory-maps) a .vdag or .vdag.zst file of format 1.x or 2.0;
    validates it unless validate=False (InvalidFileError with the spec's
    code)."""

def validate(path: _Path) -> list[tuple[str, int, str]]:
    """Every violation of the format as (code, offset, message); [] if valid."""

def convert(
    input: _Path,
    output: _Path,
    depth: Optional[int] = None,
    *,
    colors: bool = False,
    solid: bool = False,
    color_error: Optional[int] = None,
    memory_limit: Optional[Union[int, str]] = None,
    bounds: Optional[tuple[float, float, float, float]] = None,
    point_radius: float = 0.0,
    force: bool = False,
    tmp_dir: Optional[_Path] = None,
    progress: Optional[Callable[[str, int, int], object]] = None,
    format_version: Literal[1, 2] = 2,
) -> dict[str, Any]:
    """dagtool convert: the same output bytes for the same options (format
    2.0 by default, 1.0 with format_version=1); progress is called as
    progress(phase, done, total)."""

def render(
    path: _Path,
    width: int = 1280,
    height: int = 720,
    camera_pos: Optional[_Vec3] = None,
    look_at: Optional[_Vec3] = None,
    fov: float = 40.0,
    shade: _Shade = "lit",
    sun: Optional[_Vec3] = None,
    ao_rays: Optional[int] = None,
    ao_radius: Optional[float] = None,
    samples: Optional[int] = None,
    level: Optional[int] = None,
    backend: _Backend = "cpu",
) -> npt.NDArray[np.uint8]:
    """Opens path and renders it: the pixels of dagtrace render's PNG."""

def convert_region(
    input: Union[_Path, Sequence[_Path]],
    output: _Path,
    depth: int,
    region: Union[str, tuple[int, int, int, int]],
    *,
    bounds: tuple[float, float, float, float],
    colors: bool = False,
    solid: bool = False,
    color_error: Optional[int] = None,
    memory_limit: Optional[Union[int, str]] = None,
    point_radius: float = 0.0,
    force: bool = False,
    tmp_dir: Optional[_Path] = None,
    cache_input: bool = True,
) -> dict[str, Any]:
    """dagtool convert --region: one cell ("K:X,Y,Z" or (K, X, Y, Z)) of the
    root cube into a part (spec §24; always format 1); input may be a list of point-cloud
    tiles read as one. With cache_input a mesh stays in this process for the
    next region of the same file (clear_input_cache frees it). The dict
    gives where the time went: parse_seconds, bin_seconds, load_seconds,
    build_seconds, write_seconds, seconds."""

def clear_input_cache() -> bool:
    """Frees the mesh convert_region keeps in this process; whether one was kept."""

def merge(
    parts: Sequence[_Path],
    output: _Path,
    *,
    memory_limit: Optional[Union[int, str]] = None,
    force: bool = False,
    tmp_dir: Optional[_Path] = None,
    format_version: Literal[1, 2] = 2,
) -> dict[str, Any]:
    """dagtool merge: parts into a larger part (format 1) or, covering the
    cube, the whole conversion's file byte for byte, of format_version;
    errors carry E090-E098."""

def regions(level: int) -> list[tuple[int, int, int, int]]:
    """The regions (K, X, Y, Z) of level K in Morton order."""
