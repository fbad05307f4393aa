"""Each frame's images moved to its colour image's instant, with the run's own motion estimate.

Two ways a real RGB-D camera's images are not one snapshot, each undone here with the camera's velocity:

- **depth at another instant** (``TrackingOptions.align_depth_time``): where a dataset says that depth and colour
  were taken at different instants (``Frame.depth_time_offset``, from TUM's ``depth.txt`` and ``rgb.txt``
  timestamps), the depth image is resampled into the colour camera at the colour instant
  (:func:`mipslam.geometry.depth_time.depth_at_colour_time`). Off by default: it needs timestamps of the
  capture, and TUM's freiburg1 timestamps do not give them (docs/tracking.md, "Colour and depth at different
  instants");
- **a rolling shutter** (``dataset.rolling_shutter_readout_s``): the colour rows were read top to bottom over
  the read-out time; each row is moved to the frame's instant
  (:func:`mipslam.geometry.rolling_shutter.colour_at_frame_instant`, docs/tracking.md, "A rolling shutter").

The velocity (body frame, :func:`~mipslam.geometry.depth_time.interval_velocity`) comes from the tracked motion:

- for tracking's start (the feature front-end and the judge of the start), the motion model's (the newest
  tracked interval's, as :func:`~mipslam.tracking.constant_velocity_prediction` repeats it):
  :func:`predicted_velocity`, for the depth only; for its refinement, the motion from the previous frame to the
  chosen start pose (:func:`tracked_velocity` at that pose), for the depth and the colour rows: the motion
  model's lags the frame's own by 1.5 intervals, which on a camera that shakes back and forth is often the
  wrong way;
- for everything after tracking (keyframe decision, mapping, loop verification), the frame's own interval,
  from the previous frame's and its tracked poses: :func:`tracked_velocity`; a frame read again (an old
  keyframe, or after a resume) gets the same from the run's records (:func:`recorded_velocity`): tracked
  poses never change after tracking (``T_wc_tracked``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from mipslam.geometry.depth_time import depth_at_colour_time, depth_camera_pose, interval_velocity
from mipslam.geometry.rolling_shutter import colour_at_frame_instant
from mipslam.types import Frame

if TYPE_CHECKING:
    from mipslam.state import FrameRecord, SLAMState


@dataclass(frozen=True)
class SensorTiming:
    """What of a frame's timing the run undoes: the depth image's offset from the colour image
    (``align_depth_time``) and a rolling shutter's read-out (``readout_s`` seconds, 0 = a global shutter)."""

    align_depth_time: bool = False
    readout_s: float = 0.0

    @property
    def active(self) -> bool:
        return self.align_depth_time or self.readout_s > 0

    def moves(self, frame: Frame) -> bool:
        """Whether anything of ``frame`` is moved (a depth offset to undo, or a rolling shutter)."""
        return self.readout_s > 0 or self.moves_depth(frame)

    def moves_depth(self, frame: Frame) -> bool:
        """Whether ``frame``'s depth is moved (a depth offset to undo)."""
        return self.align_depth_time and frame.depth_time_offset != 0

    def moves_colour_only(self, frame: Frame) -> bool:
        """Whether only ``frame``'s colour rows are moved (a rolling shutter, no depth offset to undo)."""
        return self.readout_s > 0 and not self.moves_depth(frame)


def _velocity(earlier: "FrameRecord", T_wc_tracked: torch.Tensor, timestamp: float) -> torch.Tensor | None:
    """The velocity of the interval ``earlier`` -> (``T_wc_tracked`` at ``timestamp``)."""
    if not earlier.tracked:
        return None
    return interval_velocity(earlier.T_wc_tracked, T_wc_tracked, timestamp - earlier.timestamp)


def predicted_velocity(state: "SLAMState", frame: Frame) -> torch.Tensor | None:
    """The camera's velocity at ``frame`` before it is tracked: the newest tracked interval's (the two frames
    before it). None: not known.  -> [6] float64 or None"""
    if len(state.frames) < 2 or not state.frames[-1].tracked:
        return None
    newest = state.frames[-1]
    return _velocity(state.frames[-2], newest.T_wc_tracked, newest.timestamp)


def tracked_velocity(previous: "FrameRecord | None", frame: Frame, T_wc_tracked: torch.Tensor,
                     tracked: bool) -> torch.Tensor | None:
    """The camera's velocity at ``frame``, tracked at ``T_wc_tracked`` [4, 4]: the motion from the previous
    frame's record to it. None: not known.  -> [6] float64 or None"""
    if previous is None or not tracked:
        return None
    return _velocity(previous, T_wc_tracked, frame.timestamp)


def recorded_velocity(state: "SLAMState", frame: Frame) -> torch.Tensor | None:
    """:func:`tracked_velocity` of a frame already recorded in ``state`` (a frame read again); None for a frame
    not tracked yet."""
    k = frame.index
    if not 1 <= k < len(state.frames) or state.frames[k].index != k:
        return None
    record = state.frames[k]
    return tracked_velocity(state.frames[k - 1], frame, record.T_wc_tracked, record.tracked)


def synchronised(frame: Frame, velocity: torch.Tensor | None, timing: SensorTiming) -> Frame:
    """``frame`` with its images moved to its colour instant by ``velocity`` [6] (body frame, m/s and rad/s):
    the depth by its offset where ``timing.align_depth_time`` (:func:`~mipslam.geometry.depth_time.depth_camera_pose`: offsets beyond a
    stream's stay), the colour rows by ``timing.readout_s`` (with the depth at the colour instant). The frame
    itself when nothing moves or the velocity is not known."""
    if velocity is None or not timing.moves(frame):
        return frame
    K = frame.intrinsics.matrix(torch.float64, frame.depth.device)
    changes = {}
    T_cd = depth_camera_pose(velocity, frame.depth_time_offset) if timing.align_depth_time else None
    if T_cd is not None:
        changes["depth"] = depth_at_colour_time(frame.depth, K, T_cd)
    if timing.readout_s > 0:
        changes["color"] = colour_at_frame_instant(frame.color, K, velocity, timing.readout_s,
                                                   changes.get("depth", frame.depth))
    return replace(frame, **changes) if changes else frame
