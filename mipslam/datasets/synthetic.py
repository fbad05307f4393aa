"""Sequences written by ``data_synth``: a Replica or TUM folder plus ``synth.json`` at its root.

``synth.json`` (format_version 1) names the layout ("replica" | "tum"), the exact intrinsics
(fx, fy, cx, cy, width, height) and the depth scale; this reader checks it and hands the folder
to :class:`ReplicaSequence` or :class:`TUMSequence` with those values (config values still
override them, as for every reader). Everything else in the file (trajectory name, seed, scene,
sensor options) is kept in :attr:`SyntheticSequence.meta` for evaluation and reports.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mipslam.config import DatasetConfig
from mipslam.datasets.base import SequenceBase, read_json
from mipslam.datasets.replica import ReplicaSequence
from mipslam.datasets.tum import TUMSequence
from mipslam.errors import DatasetError
from mipslam.types import Frame, Intrinsics

SYNTH_FORMAT_VERSION = 1
SYNTH_FILE = "synth.json"


def read_synth_meta(path: Path) -> dict[str, Any]:
    """Parse and check ``synth.json``; DatasetError (file, and line for JSON syntax) when it is unusable."""
    if not path.is_file():
        raise DatasetError(
            path, "file not found; a synthetic sequence is a data_synth folder with synth.json "
            "(use dataset.kind=replica or tum for other folders, or regenerate it with `mipslam synth`)"
        )
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise DatasetError(path, "expected a JSON object")
    version = meta.get("format_version")
    if version != SYNTH_FORMAT_VERSION:
        raise DatasetError(
            path, f"format_version {version!r} is not supported (this mipslam reads {SYNTH_FORMAT_VERSION}); regenerate the sequence"
        )
    if meta.get("layout") not in ("replica", "tum"):
        raise DatasetError(path, f"layout must be 'replica' or 'tum', got {meta.get('layout')!r}")
    intrinsics = meta.get("intrinsics")
    if not isinstance(intrinsics, dict):
        raise DatasetError(path, 'missing "intrinsics": {"fx", "fy", "cx", "cy", "width", "height"}')
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        value = intrinsics.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise DatasetError(path, f"intrinsics.{key} must be a finite number, got {value!r}")
        if key in ("fx", "fy") and value <= 0:
            raise DatasetError(path, f"intrinsics.{key} must be positive, got {value!r}")
        if key in ("width", "height") and (value < 1 or value != int(value)):
            raise DatasetError(path, f"intrinsics.{key} must be a whole number of pixels >= 1, got {value!r}")
    scale = meta.get("depth_scale")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise DatasetError(path, f"depth_scale must be a positive number, got {scale!r}")
    return meta


class SyntheticSequence:
    """A data_synth folder as an :class:`~mipslam.datasets.RGBDSequence` (delegates to the layout's reader)."""

    random_access = True

    def __init__(self, root: str | Path, cfg: DatasetConfig | None = None):
        cfg = cfg or DatasetConfig(kind="synthetic", path=str(root))
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "dataset folder not found; generate one with `mipslam synth --out DIR`")
        self.meta: dict[str, Any] = read_synth_meta(self.root / SYNTH_FILE)
        k = self.meta["intrinsics"]

        def pick(config_value, file_value):
            return config_value if config_value is not None else file_value

        inner_cfg = dataclasses.replace(
            cfg,
            fx=pick(cfg.fx, float(k["fx"])), fy=pick(cfg.fy, float(k["fy"])),
            cx=pick(cfg.cx, float(k["cx"])), cy=pick(cfg.cy, float(k["cy"])),
            # The image size is checked against synth.json below (so an error names that file, not the config).
            width=cfg.width, height=cfg.height,
            depth_scale=pick(cfg.depth_scale, float(self.meta["depth_scale"])),
        )
        name = f"synthetic:{self.root.name}"
        reader = ReplicaSequence if self.meta["layout"] == "replica" else TUMSequence
        self.inner: SequenceBase = reader(self.root, inner_cfg, name=name)
        size = (self.inner.full_intrinsics.width, self.inner.full_intrinsics.height)
        if cfg.width is None and cfg.height is None and size != (int(k["width"]), int(k["height"])):
            raise DatasetError(
                self.root / SYNTH_FILE,
                f"intrinsics say {int(k['width'])}x{int(k['height'])} but the images are {size[0]}x{size[1]} "
                f"({self.inner.frame_paths[0][0].name}); regenerate the sequence or fix synth.json",
            )
        self.name = name
        self.layout: str = self.meta["layout"]
        self.timestamp_kind = self.inner.timestamp_kind

    @classmethod
    def from_config(cls, cfg: DatasetConfig) -> "SyntheticSequence":
        return cls(cfg.path, cfg)

    @property
    def intrinsics(self) -> Intrinsics:
        return self.inner.intrinsics

    @property
    def full_intrinsics(self) -> Intrinsics:
        return self.inner.full_intrinsics

    @property
    def depth_scale(self) -> float:
        return self.inner.depth_scale

    @property
    def downscale(self) -> int:
        return self.inner.downscale

    @property
    def timestamps(self) -> np.ndarray:
        return self.inner.timestamps

    @property
    def source_indices(self) -> np.ndarray:
        return self.inner.source_indices

    @property
    def gt_T_wc(self) -> torch.Tensor | None:
        return self.inner.gt_T_wc

    @property
    def gt_valid(self) -> np.ndarray:
        return self.inner.gt_valid

    @property
    def frame_paths(self) -> list[tuple[Path, Path]]:
        return self.inner.frame_paths

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, index: int) -> Frame:
        return self.inner[index]

    def __iter__(self):
        return iter(self.inner)

    def __repr__(self) -> str:
        return f"SyntheticSequence({self.layout}, {self.inner!r})"
