"""Reading a run folder's description files (config.yaml, run.json, frames.json) for evaluation, and naming
the files an evaluation reads (the run's own or those of ``mipslam refine`` in ``refined/``).

One place for the checks and messages, shared by trajectory and render evaluation.
"""
from __future__ import annotations

import json
from pathlib import Path

import yaml

from mipslam.config import Config, config_from_dict
from mipslam.errors import EvaluationError
from mipslam.io.run_folder import RunFolder


def read_run_json(path: Path) -> dict:
    """A JSON file of a run folder; EvaluationError naming the file when missing or malformed."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise EvaluationError(f"{path}: missing; is this a run folder written by 'mipslam run'?") from None
    except json.JSONDecodeError as exc:
        raise EvaluationError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


def read_run_config(folder: RunFolder) -> Config:
    """The resolved config a run wrote into its folder (read with yaml.safe_load, validated)."""
    if not folder.root.is_dir():
        raise EvaluationError(f"{folder.root}: run folder not found")
    try:
        return config_from_dict(yaml.safe_load(folder.config_yaml.read_text(encoding="utf-8")) or {})
    except FileNotFoundError:
        raise EvaluationError(f"{folder.config_yaml}: missing; is this a run folder written by 'mipslam run'?") from None


def run_file(folder: RunFolder, given: str | Path | None, default: Path) -> Path:
    """``given`` (relative to the run folder when relative), or ``default`` when None."""
    if given is None:
        return default
    given = Path(given)
    return given if given.is_absolute() else folder.root / given


def relative_name(folder: RunFolder, path: Path) -> str:
    """``path`` relative to the run folder where it lies inside it (e.g. ``refined/map.ply``), else in full."""
    try:
        return Path(path).resolve().relative_to(folder.root.resolve()).as_posix()
    except ValueError:
        return str(path)
