"""Read back what :func:`data_synth.generate` wrote: the description, the scene, the camera."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from data_synth.scene import Scene
from data_synth.trajectories import trajectory_poses
from mipslam.errors import DatasetError, MipslamError
from mipslam.types import Intrinsics

SUPPORTED_FORMAT_VERSION = 1
REQUIRED_KEYS = ("format_version", "generator", "layout", "trajectory", "seed", "frames", "intrinsics",
                 "depth_scale", "fps", "scene", "sensor")


def _json_path(folder_or_json: str | Path) -> Path:
    path = Path(folder_or_json)
    if path.is_dir():
        path = path / "synth.json"
    if not path.is_file():
        raise DatasetError(path, "no synth.json here; pass a folder written by data_synth (mipslam synth) or its synth.json")
    return path


def read_synth_json(folder_or_json: str | Path) -> dict[str, Any]:
    """The parsed ``synth.json`` of a generated folder, checked for the keys of the contract."""
    path = _json_path(folder_or_json)
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(path, f"cannot read: {error}") from error
    except json.JSONDecodeError as error:
        raise DatasetError(path, f"not valid JSON ({error.msg}); regenerate the folder", line=error.lineno) from error
    if not isinstance(info, dict):
        raise DatasetError(path, "synth.json must hold a JSON object")
    missing = [k for k in REQUIRED_KEYS if k not in info]
    if missing:
        raise DatasetError(path, f"synth.json lacks {', '.join(missing)}; regenerate the folder with mipslam synth")
    if info["generator"] != "data_synth":
        raise DatasetError(path, f"generator is {info['generator']!r}, expected 'data_synth'")
    if info["format_version"] != SUPPORTED_FORMAT_VERSION:
        raise DatasetError(path, f"format_version {info['format_version']!r} is not supported (this data_synth "
                                 f"reads version {SUPPORTED_FORMAT_VERSION}); regenerate the folder")
    return info


def load_scene(folder_or_json: str | Path) -> Scene:
    """The exact scene of a generated folder (or of its ``synth.json``), for :func:`render_view`."""
    path = _json_path(folder_or_json)
    info = read_synth_json(path)
    try:
        return Scene.from_dict(info["scene"])
    except (KeyError, TypeError, ValueError) as error:
        raise DatasetError(path, f"the 'scene' entry is invalid ({type(error).__name__}: {error}); "
                                 "regenerate the folder") from error


def synth_intrinsics(folder_or_json: str | Path) -> Intrinsics:
    """The camera the folder was rendered with (use ``.scaled(f)`` for other resolutions)."""
    path = _json_path(folder_or_json)
    k = read_synth_json(path)["intrinsics"]
    try:
        return Intrinsics(fx=float(k["fx"]), fy=float(k["fy"]), cx=float(k["cx"]), cy=float(k["cy"]),
                          width=int(k["width"]), height=int(k["height"]))
    except (KeyError, TypeError, ValueError) as error:
        raise DatasetError(path, f"'intrinsics' needs fx, fy, cx, cy, width, height: {error}") from error


def ground_truth_poses(folder_or_json: str | Path) -> np.ndarray:
    """Exact camera-to-world poses of every frame, recomputed from the trajectory's name, or for a replayed
    file as stored in synth.json (free of the rounding in traj.txt / groundtruth.txt).  -> [frames, 4, 4] float64"""
    path = _json_path(folder_or_json)
    info = read_synth_json(path)
    if "poses" in info:
        try:
            poses = np.asarray(info["poses"], dtype=np.float64).reshape(-1, 4, 4)
        except (TypeError, ValueError) as error:
            raise DatasetError(path, f"'poses' must hold 16 numbers per frame: {error}") from error
        if len(poses) != int(info["frames"]) or not np.isfinite(poses).all():
            raise DatasetError(path, f"'poses' holds {len(poses)} finite poses for {info['frames']} frames; "
                                     "regenerate the folder")
        return poses
    laps = int(info.get("trajectory_options", {}).get("laps", 1))
    try:
        return trajectory_poses(info["trajectory"], int(info["frames"]), laps=laps)
    except MipslamError as error:
        raise DatasetError(path, f"cannot rebuild the trajectory: {error}") from error
