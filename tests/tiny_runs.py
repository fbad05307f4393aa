"""Tiny SLAM runs for the tests: settings that take a few seconds on 2 cores, and a one-frame map."""
from __future__ import annotations

from pathlib import Path

import torch

from mipslam.config import load_config, parse_override, retired_key_message
from mipslam.datasets import make_sequence
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.mapping import Mapper, MappingOptions, MappingView

REPO = Path(__file__).resolve().parent.parent

# Small enough for a few seconds per run on 2 cores, large enough for tracking to be meaningful.
TINY = [
    "mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
    "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
]


def split_settings(items) -> tuple[list[str], dict]:
    """``section.key=value`` items split into config overrides and stage constants (the internal constants a
    test replaces, for :class:`mipslam.pipeline.PipelineHooks` ``constants``: ``{"loop.min_keyframe_gap": 6}``)."""
    overrides, constants = [], {}
    for item in items:
        parts, value = parse_override(item)
        key = ".".join(parts)
        if retired_key_message(key) is not None and "internal constant" in retired_key_message(key):
            if isinstance(value, str):  # YAML 1.1 reads 5e-4 as a string; the constant is the number
                try:
                    value = float(value)
                except ValueError:
                    pass
            constants[key] = tuple(value) if isinstance(value, list) else value
        else:
            overrides.append(item)
    return overrides, constants


def tiny_config(sequence: Path, *extra: str):
    """The built-in synthetic config on ``sequence`` with the TINY settings and ``extra`` overrides."""
    return load_config("synthetic", overrides=[f"dataset.path={sequence}", *TINY, *extra])


def tiny_tracking(sequence: Path, *extra: str):
    """The tracking options of :func:`tiny_config` with ``extra`` settings, config keys or tracking constants
    (``tracking.dense_start=false``), as the pipeline builds them."""
    from mipslam.pipeline import PipelineHooks
    from mipslam.tracking import TrackingOptions

    overrides, constants = split_settings(extra)
    config = tiny_config(sequence, *overrides)
    options = TrackingOptions.from_config(config.tracking, depth_noise_power=config.dataset.depth_noise_power)
    return PipelineHooks(constants=constants).options("tracking", options)


def map_of_first_frame(sequence_path: Path, iterations: int):
    """The map of frame 0 at its ground-truth pose after ``iterations`` mapping steps:
    (config, sequence, map, first loss, last loss)."""
    config = tiny_config(sequence_path)
    sequence = make_sequence(config.dataset)
    frame = sequence[0]
    T_wc = sequence.gt_T_wc[0]
    gmap = GaussianMap.empty()
    options = MappingOptions.from_config(config.mapping)
    optimizer = GaussianOptimizer.from_config(gmap, options)
    mapper = Mapper(options, config.render)
    view = MappingView(0, frame.color, frame.depth, T_wc, torch.zeros(2), frame.intrinsics, optimize_pose=False)
    mapper.densify(gmap, optimizer, view, frame_index=0)
    first, last, _ = mapper.optimize(gmap, optimizer, [view], iterations, torch.Generator().manual_seed(0))
    return config, sequence, gmap, first, last
