"""Helpers the scenarios share: the built-in configs (mipslam/configs/), the source checkout (tests/) and the
record's parameters.

``loop_closure``, ``pgo`` and ``scaling`` build their inputs with helpers of the test suite
(``tests/fault_injection.py``, ``tests/synthetic_pose_graphs.py``): fault injection and synthetic pose graphs
are test code, not part of the installed package. They are imported from the checkout the package runs from;
an installed copy without ``tests/`` gets a one-line error saying so.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any, Sequence

from mipslam.config import CONFIG_DIR as CONFIGS
from mipslam.errors import MipslamError

REPO = Path(__file__).resolve().parents[3]  # the checkout: mipslam/bench/scenarios/ -> the repository root
SHARED_DATA = REPO.parent / "shared" / "data"  # the real clips beside the checkout (not part of it)

__all__ = ["CONFIGS", "REPO", "SHARED_DATA", "import_test_helper", "optional_path", "parameters",
           "sequence_config", "synth_sequence"]


def import_test_helper(name: str) -> ModuleType:
    """``tests/<name>.py`` of the source checkout, as module ``name``."""
    if name in sys.modules:
        return sys.modules[name]
    path = REPO / "tests" / f"{name}.py"
    if not path.is_file():
        raise MipslamError(f"{path}: not found; this scenario uses a helper of the test suite and runs only from a "
                           "source checkout of mipslam (git clone), not from an installed package")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # before exec: dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def parameters(options: Any) -> dict[str, Any]:
    """A scenario's options as the record's ``parameters`` (tuples as lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(options).items()}


def optional_path(text: str) -> Path | None:
    """An option that names a file or folder, "" for none."""
    return Path(text).expanduser() if text else None


def sequence_config(config: str, overrides: Sequence[str]) -> str:
    """The config a scenario reads its sequence with: ``config`` when given (a YAML file or a built-in's name), else
    the built-in config of the kind of the folder the last ``dataset.path=`` override names (data_synth, Replica or
    TUM, as ``mipslam bench SEQUENCE`` chooses), else the built-in ``tum`` (which then needs ``dataset.path``)."""
    if config:
        return config
    paths = [item.split("=", 1)[1] for item in overrides if item.startswith("dataset.path=")]
    folder = Path(paths[-1]).expanduser() if paths else None
    if folder is None or not folder.is_dir():
        return str(CONFIGS / "tum.yaml")
    from mipslam.bench.spec import resolve_target

    return str(resolve_target(folder, CONFIGS).config_path)


def synth_sequence(out_dir: Path, size: str, frames: int, *, trajectory: str = "loop", supersample: int = 2) -> Path:
    """A data_synth sequence (Replica layout, seed 0) of ``frames`` frames at ``size`` ("WIDTHxHEIGHT"), written
    to ``out_dir/sequence``; returns that folder."""
    import data_synth

    width, height = (int(v) for v in size.lower().split("x"))
    sequence_dir = out_dir / "sequence"
    data_synth.generate(sequence_dir, layout="replica", trajectory=trajectory, width=width, height=height,
                        frames=frames, seed=0, supersample=supersample)
    return sequence_dir
