"""The exceptions of the vdag package.

Every failure the package reports is a :class:`VdagError`. A file that breaks
a rule of the format raises :class:`InvalidFileError`, whose ``code`` is the
stable error code of spec/VDAG.md (such as ``"E012"``) and ``offset`` the byte
offset of the offending bytes.
"""

from __future__ import annotations

from typing import Optional


class VdagError(Exception):
    """A failure of the vdag package: ``message`` says what, for people;
    ``code`` is the spec's error code (``"E0xx"``) where one applies, else
    None; ``offset`` is the byte offset in the file where known, else None."""

    def __init__(self, message: str, code: Optional[str] = None, offset: Optional[int] = None):
        super().__init__(message)
        self.message = message
        self.code = code
        self.offset = offset


class InvalidFileError(VdagError):
    """The file breaks a rule of the .vdag format; ``code`` and ``offset`` say
    which and where (the first violation, as ``dagtool validate`` lists it)."""


class ConvertError(VdagError):
    """A conversion failed; nothing was written. ``kind`` is ``"input"`` (the
    input file is unusable), ``"usage"`` (impossible options), ``"io"``
    (reading or writing failed) or ``"limit"`` (a memory or format limit)."""

    kind: str = "input"


class TraceError(VdagError):
    """Tracing or rendering failed (a malformed DAG opened without validation,
    a level deeper than the file)."""


class GpuError(VdagError):
    """The GPU tracer is unavailable (no adapter, not even a software one)
    or failed."""


__all__ = ["VdagError", "InvalidFileError", "ConvertError", "TraceError", "GpuError"]
