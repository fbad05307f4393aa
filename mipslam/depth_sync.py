"""Each frame's depth image moved to its colour image's instant, with the run's own motion estimate.

Where a dataset says that depth and colour were taken at different instants (``Frame.depth_time_offset``,
from TUM's ``depth.txt`` and ``rgb.txt`` timestamps), the depth image is resampled into the colour camera
at the colour instant (:func:`mipslam.geometry.depth_time.depth_at_colour_time`):

- for tracking, with the motion model's velocity (the last interval's tracked motion, as
  :func:`~mipslam.tracking.constant_velocity_prediction` repeats it): :func:`predicted_depth_motion`;
- for everything after tracking (keyframe decision, mapping, loop verification), with the velocity of
  the frame's own interval, from the previous frame's and its tracked poses: :func:`tracked_depth_motion`;
  a frame read again (an old keyframe, or after a resume) gets the same from the run's records
  (:func:`recorded_depth_motion`): tracked poses never change after tracking (``T_wc_tracked``).

``tracking.align_depth_time: true`` turns this on; the default reads depth as if taken with the colour
image, because it needs timestamps of the capture, and TUM's freiburg1 timestamps do not give them
(docs/tracking.md, "Colour and depth at different instants").
"""
from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from mipslam.geometry.depth_time import depth_at_colour_time, depth_camera_motion
from mipslam.types import Frame

if TYPE_CHECKING:
    from mipslam.state import FrameRecord, SLAMState


def _motion(earlier: "FrameRecord", T_wc_tracked: torch.Tensor, timestamp: float, offset_s: float) -> torch.Tensor | None:
    """T_cd from the interval ``earlier`` -> (``T_wc_tracked`` at ``timestamp``)."""
    if not earlier.tracked:
        return None
    return depth_camera_motion(earlier.T_wc_tracked, T_wc_tracked, timestamp - earlier.timestamp, offset_s)


def predicted_depth_motion(state: "SLAMState", frame: Frame) -> torch.Tensor | None:
    """Depth camera in the colour camera's frame for ``frame`` before it is tracked: the newest tracked
    interval's motion (the two frames before it). None: nothing to move.  -> T_cd [4, 4] float64 or None"""
    if frame.depth_time_offset == 0 or len(state.frames) < 2 or not state.frames[-1].tracked:
        return None
    newest = state.frames[-1]
    return _motion(state.frames[-2], newest.T_wc_tracked, newest.timestamp, frame.depth_time_offset)


def tracked_depth_motion(previous: "FrameRecord | None", frame: Frame, T_wc_tracked: torch.Tensor,
                         tracked: bool) -> torch.Tensor | None:
    """Depth camera in the colour camera's frame for ``frame``, tracked at ``T_wc_tracked`` [4, 4]: the motion
    from the previous frame's record to it. None: nothing to move.  -> T_cd [4, 4] float64 or None"""
    if frame.depth_time_offset == 0 or previous is None or not tracked:
        return None
    return _motion(previous, T_wc_tracked, frame.timestamp, frame.depth_time_offset)


def recorded_depth_motion(state: "SLAMState", frame: Frame) -> torch.Tensor | None:
    """:func:`tracked_depth_motion` of a frame already recorded in ``state`` (a frame read again); None for a
    frame not tracked yet."""
    k = frame.index
    if frame.depth_time_offset == 0 or not 1 <= k < len(state.frames) or state.frames[k].index != k:
        return None
    record = state.frames[k]
    return tracked_depth_motion(state.frames[k - 1], frame, record.T_wc_tracked, record.tracked)


def with_depth_at_colour_time(frame: Frame, T_cd: torch.Tensor | None) -> Frame:
    """``frame`` with its depth moved by ``T_cd`` [4, 4] (the depth camera in the colour camera's frame);
    the frame itself when ``T_cd`` is None."""
    if T_cd is None:
        return frame
    K = frame.intrinsics.matrix(torch.float64, frame.depth.device)
    return replace(frame, depth=depth_at_colour_time(frame.depth, K, T_cd))
