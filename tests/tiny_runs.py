"""Tiny SLAM runs for the tests: settings that take a few seconds on 2 cores, and a one-frame map."""
from __future__ import annotations

from pathlib import Path

import torch

from mipslam.config import load_config
from mipslam.datasets import make_sequence
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.mapping import Mapper, MappingView

REPO = Path(__file__).resolve().parent.parent

# Small enough for a few seconds per run on 2 cores, large enough for tracking to be meaningful.
TINY = [
    "mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
    "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
]


def tiny_config(sequence: Path, *extra: str):
    """The built-in synthetic config on ``sequence`` with the TINY settings and ``extra`` overrides."""
    return load_config("synthetic", overrides=[f"dataset.path={sequence}", *TINY, *extra])


def map_of_first_frame(sequence_path: Path, iterations: int):
    """The map of frame 0 at its ground-truth pose after ``iterations`` mapping steps:
    (config, sequence, map, first loss, last loss)."""
    config = tiny_config(sequence_path)
    sequence = make_sequence(config.dataset)
    frame = sequence[0]
    T_wc = sequence.gt_T_wc[0]
    gmap = GaussianMap.empty()
    optimizer = GaussianOptimizer.from_config(gmap, config.mapping)
    mapper = Mapper(config.mapping, config.render)
    view = MappingView(0, frame.color, frame.depth, T_wc, torch.zeros(2), frame.intrinsics, optimize_pose=False)
    mapper.densify(gmap, optimizer, view, frame_index=0)
    first, last, _ = mapper.optimize(gmap, optimizer, [view], iterations, torch.Generator().manual_seed(0))
    return config, sequence, gmap, first, last
