"""Type stubs of the vdag package."""

from ._vdag import (
    Dag as Dag,
    TraceResult as TraceResult,
    VoxelChunks as VoxelChunks,
    __version__ as __version__,
    clear_input_cache as clear_input_cache,
    convert as convert,
    convert_region as convert_region,
    merge as merge,
    open as open,
    render as render,
    validate as validate,
)
from .errors import (
    ConvertError as ConvertError,
    GpuError as GpuError,
    InvalidFileError as InvalidFileError,
    TraceError as TraceError,
    VdagError as VdagError,
)

__all__: list[str]
