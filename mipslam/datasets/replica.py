"""Replica in the NICE-SLAM layout.

Folder::

    results/frame000000.jpg     colour (8-bit; .png is accepted too and preferred when both exist)
    results/depth000000.png     depth, uint16, metres = value / depth_scale (6553.5)
    traj.txt                    one camera-to-world pose per line: 16 numbers, row-major 4x4;
                                line k (comments and blank lines skipped) is the pose of frame k
    cam_params.json             optional: {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}

Frames are the ``frameNNNNNN`` files sorted by their number; the number is the frame's original
index (``source_indices``) and its timestamp (``timestamp_kind == "index"``). Intrinsics come from
``cam_params.json`` where present, each value overridden by the config (``dataset.fx`` ...);
without the file ``fx, fy, cx, cy`` must be configured. Width and height come from the file or
the config, else from the first image; every image is checked against them. ``traj.txt`` is
optional (a warning is logged and ``gt_T_wc`` is None without it); where present, every line is
validated (16 finite numbers, a rigid transform) and it must cover every frame number.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import torch

from mipslam.config import DatasetConfig
from mipslam.datasets.base import (
    RIGIDITY_TOLERANCE,
    FrameRecord,
    SequenceBase,
    parse_float,
    read_json,
    read_text_rows,
)
from mipslam.errors import DatasetError
from mipslam.geometry import rigidity_error

logger = logging.getLogger(__name__)

REPLICA_DEPTH_SCALE = 6553.5
_FRAME_NAME = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)
_EXTENSION_PREFERENCE = {"png": 0, "jpg": 1, "jpeg": 1}


def read_cam_params(path: Path) -> dict[str, float]:
    """The ``camera`` section of a NICE-SLAM ``cam_params.json`` (keys w, h, fx, fy, cx, cy, scale; any subset)."""
    data = read_json(path)
    camera = data.get("camera") if isinstance(data, dict) else None
    if not isinstance(camera, dict):
        raise DatasetError(path, 'expected an object {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}')
    out: dict[str, float] = {}
    for key in ("w", "h", "fx", "fy", "cx", "cy", "scale"):
        if key not in camera:
            continue
        value = camera[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise DatasetError(path, f"camera.{key} must be a finite number, got {value!r}")
        if key in ("fx", "fy", "scale") and value <= 0:
            raise DatasetError(path, f"camera.{key} must be positive, got {value!r}")
        if key in ("w", "h") and (value < 1 or value != int(value)):
            raise DatasetError(path, f"camera.{key} must be a whole number of pixels >= 1, got {value!r}")
        out[key] = float(value)
    return out


def read_replica_trajectory(path: Path) -> tuple[torch.Tensor, list[int]]:
    """Poses of a NICE-SLAM ``traj.txt``.  -> (T_wc [M, 4, 4] float64, line number of each pose)

    Raises DatasetError (file and line) for a line without exactly 16 numbers, a non-finite value
    or a pose that is not rigid.
    """
    rows = read_text_rows(path)
    values = []
    lines = []
    for line, fields in rows:
        if len(fields) != 16:
            raise DatasetError(path, f"expected 16 numbers (a row-major 4x4 camera-to-world pose), got {len(fields)}", line)
        values.append([parse_float(f, path, line, "pose entry") for f in fields])
        lines.append(line)
    if not values:
        raise DatasetError(path, "trajectory file has no poses")
    T_wc = torch.tensor(values, dtype=torch.float64).reshape(-1, 4, 4)
    errors = rigidity_error(T_wc)
    bad = torch.nonzero(errors > RIGIDITY_TOLERANCE).flatten()
    if bad.numel() > 0:
        k = int(bad[0])
        raise DatasetError(
            path,
            f"pose is not a rigid transform (deviation {float(errors[k]):.3g} > {RIGIDITY_TOLERANCE:g}: the rotation "
            "must be orthonormal with det +1 and the last row 0 0 0 1)",
            lines[k],
        )
    return T_wc, lines


def list_replica_frames(results: Path) -> list[tuple[int, Path, Path]]:
    """(frame number, colour file, depth file) sorted by number; depth files need not exist yet."""
    chosen: dict[int, Path] = {}
    for entry in results.iterdir():
        match = _FRAME_NAME.match(entry.name)
        if not match:
            continue
        number = int(match.group(1))
        previous = chosen.get(number)
        if previous is not None:
            rank_new = _EXTENSION_PREFERENCE[match.group(2).lower()]
            rank_old = _EXTENSION_PREFERENCE[previous.suffix[1:].lower()]
            if rank_new == rank_old:
                raise DatasetError(entry, f"frame {number} appears twice ({previous.name} and {entry.name}); remove one")
            if rank_new > rank_old:
                continue
        chosen[number] = entry
    frames = []
    for number in sorted(chosen):
        color = chosen[number]
        digits = _FRAME_NAME.match(color.name).group(1)
        frames.append((number, color, results / f"depth{digits}.png"))
    return frames


class ReplicaSequence(SequenceBase):
    """A Replica (NICE-SLAM layout) folder as an :class:`~mipslam.datasets.RGBDSequence`."""

    timestamp_kind = "index"

    def __init__(self, root: str | Path, cfg: DatasetConfig | None = None, *, name: str | None = None):
        cfg = cfg or DatasetConfig(kind="replica", path=str(root))
        self.root = Path(root)
        self.name = name or f"replica:{self.root.name}"
        if not self.root.is_dir():
            raise DatasetError(self.root, "dataset folder not found; set dataset.path to a Replica folder (results/, traj.txt)")
        results = self.root / "results"
        if not results.is_dir():
            raise DatasetError(results, "folder not found; a Replica folder holds results/frameNNNNNN.jpg and depthNNNNNN.png")
        frames = list_replica_frames(results)
        if not frames:
            raise DatasetError(results, "no colour frames (frameNNNNNN.jpg or .png) in this folder; the sequence is empty")

        cam_path = self.root / "cam_params.json"
        cam = read_cam_params(cam_path) if cam_path.is_file() else {}
        config_values = {"fx": cfg.fx, "fy": cfg.fy, "cx": cfg.cx, "cy": cfg.cy, "w": cfg.width, "h": cfg.height,
                         "scale": cfg.depth_scale}
        merged = {key: (value if value is not None else cam.get(key)) for key, value in config_values.items()}
        missing = [key for key in ("fx", "fy", "cx", "cy") if merged[key] is None]
        if missing:
            names = ", ".join(f"dataset.{k}" for k in missing)
            raise DatasetError(
                cam_path,
                f"intrinsics {', '.join(missing)} unknown: {'the file lacks them' if cam_path.is_file() else 'file not found'}; "
                f"add them to cam_params.json or set {names}",
            )
        depth_scale = merged["scale"] if merged["scale"] is not None else REPLICA_DEPTH_SCALE

        records = [FrameRecord(color, depth, float(number), number) for number, color, depth in frames]

        traj_path = self.root / "traj.txt"
        gt_T_wc = gt_valid = None
        if traj_path.exists():
            poses, _ = read_replica_trajectory(traj_path)
            last = frames[-1][0]
            if poses.shape[0] <= last:
                raise DatasetError(
                    traj_path, f"has {poses.shape[0]} poses but the folder has frame {last} (needs at least {last + 1} lines)"
                )
            gt_T_wc = poses[torch.tensor([number for number, _, _ in frames], dtype=torch.long)]
            gt_valid = np.ones(len(frames), dtype=bool)
        else:
            logger.warning("%s: no traj.txt; the sequence has no ground truth (evaluation will be unavailable)", self.root)

        expected_size = None
        if merged["w"] is not None and merged["h"] is not None:
            expected_size = (int(merged["w"]), int(merged["h"]))
        elif merged["w"] is not None or merged["h"] is not None:
            raise DatasetError(cam_path, "width and height must be given together (w and h, or dataset.width and dataset.height)")
        source = "dataset.width/height" if cfg.width is not None else f"{cam_path} (w, h)"
        self._setup(
            records=records, gt_T_wc=gt_T_wc, gt_valid=gt_valid,
            camera=(merged["fx"], merged["fy"], merged["cx"], merged["cy"]),
            expected_size=expected_size, size_source=source, depth_scale=depth_scale,
            first_frame=cfg.first_frame, stride=cfg.stride, max_frames=cfg.max_frames, downscale=cfg.downscale,
            where=results, distortion=tuple(cfg.distortion or ()),
            depth_intrinsics=tuple(cfg.depth_intrinsics or ()), depth_extrinsics=tuple(cfg.depth_extrinsics or ()),
        )

    @classmethod
    def from_config(cls, cfg: DatasetConfig) -> "ReplicaSequence":
        return cls(cfg.path, cfg)
