"""One exception hierarchy for the whole library.

Library code raises these; only ``mipslam.cli`` turns them into a one-line message and an exit
code. Every message says what is wrong and, where it can, which file (and line) and what to do.
"""
from __future__ import annotations

from pathlib import Path


class MipslamError(Exception):
    """Base class of every error mipslam raises on purpose."""


class ConfigError(MipslamError):
    """A configuration file or override is invalid (unknown key, wrong type, out of range)."""


class DatasetError(MipslamError):
    """A dataset folder or file is missing, unreadable or inconsistent.

    The message always starts with the offending path (and line, where there is one).
    """

    def __init__(self, path: str | Path | None, message: str, line: int | None = None):
        self.path = None if path is None else Path(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = f"{self.path}"
            if line is not None:
                where += f":{line}"
            where += ": "
        super().__init__(where + message)


class CheckpointError(MipslamError):
    """A checkpoint is missing, corrupt, from another format version or an incompatible config."""


class EvaluationError(MipslamError):
    """Evaluation cannot be carried out (no matching poses, missing files, bad trajectory)."""


class RenderError(MipslamError):
    """The renderer was called with inputs it cannot handle (wrong shapes, dtypes, devices)."""


class BackendUnavailableError(RenderError):
    """A requested rendering backend (e.g. the compiled CPU extension) is not available."""
