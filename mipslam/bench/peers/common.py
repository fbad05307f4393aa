"""What every peer shares: the frames as 8-bit RGB + metric depth, and the result of a peer run.

Peers read the sequence through mipslam's own readers (:func:`mipslam.datasets.make_sequence`),
so they see the same rgb-depth association, the same frame selection (``first_frame``, ``stride``,
``max_frames``) and the same timestamps as a ``mipslam run``; only the resolution differs: peers
get the images at the resolution on disk (``dataset.downscale=1``), the one their defaults are
tuned for.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np
import torch

from mipslam.types import Frame

__all__ = ["PeerFrame", "PeerRun", "peer_frames"]


@dataclass(frozen=True)
class PeerFrame:
    """One frame for a peer. color: uint8 RGB [H, W, 3]; depth: float32 metres [H, W] (0 = none)."""

    position: int  # index in the (selected) sequence
    timestamp: float  # seconds (TUM) or the frame number (Replica)
    color: np.ndarray
    depth: np.ndarray


def peer_frames(sequence) -> Iterator[tuple[PeerFrame, float]]:
    """Every frame of ``sequence`` as a :class:`PeerFrame`, with the seconds spent reading it."""
    for position in range(len(sequence)):
        start = time.perf_counter()
        frame: Frame = sequence[position]
        color = (frame.color.clamp(0.0, 1.0) * 255.0).round().to(dtype=torch.uint8).numpy()
        depth = np.ascontiguousarray(frame.depth.numpy(), dtype=np.float32)
        yield PeerFrame(position, float(frame.timestamp), np.ascontiguousarray(color), depth), time.perf_counter() - start


@dataclass(frozen=True)
class PeerRun:
    """What a peer produced on a sequence of N frames.

    timestamps: float64 [M] of the frames with a pose; T_wc: float64 [M, 4, 4] camera-to-world;
    positions: int64 [M] sequence indices of those frames (the other N - M frames are lost);
    frame_seconds: float64 [N] the peer's processing time per frame (reading images excluded);
    start_seconds: set-up before the first frame (vocabulary loading, allocation).
    """

    frames: int
    timestamps: np.ndarray
    T_wc: np.ndarray
    positions: np.ndarray
    frame_seconds: np.ndarray
    start_seconds: float
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def lost_positions(self) -> list[int]:
        return sorted(set(range(self.frames)) - set(int(p) for p in self.positions))

    def summary(self) -> dict[str, Any]:
        busy = float(np.sum(self.frame_seconds))
        return {
            "frames": self.frames, "poses": int(len(self.positions)), "lost_frames": len(self.lost_positions),
            "lost_positions": self.lost_positions, "start_s": self.start_seconds, "processing_s": busy,
            "frames_per_second": self.frames / busy if busy > 0 else None,
            "ms_per_frame_median": 1000.0 * float(np.median(self.frame_seconds)) if self.frames else None,
            **self.details,
        }
