"""Optional packages (extras): import one, or raise an error that says which extra installs it."""
from __future__ import annotations

import importlib
from types import ModuleType
from typing import Callable

from mipslam.errors import MipslamError


def import_optional(module: str, *, needed_by: str, install: str, package: str | None = None,
                    make_error: Callable[[str], Exception] = MipslamError) -> ModuleType:
    """``module``, or ``make_error("<needed_by> needs the optional package <package> (<why>); <install>")``.

    needed_by: what asked for it (a feature, a flag); install: the command(s) that install it; package: the
    name to show (default: ``module``)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise make_error(f"{needed_by} needs the optional package {package or module} ({exc}); {install}") from None
