"""Depth images moved to their colour image's instant (mipslam.geometry.depth_time)."""
from __future__ import annotations

import math

import torch

from data_synth import default_intrinsics, make_scene, render_view, trajectory_poses
from mipslam.geometry.depth_time import MAX_OFFSET_S, depth_at_colour_time, depth_camera_motion
from mipslam.geometry.se3 import se3_exp, se3_inverse


def _K(intrinsics) -> torch.Tensor:
    return torch.tensor([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]],
                        dtype=torch.float64)


def test_depth_camera_motion_scales_the_last_interval():
    step = se3_exp(torch.tensor([0.02, -0.01, 0.005, 0.01, 0.03, -0.02], dtype=torch.float64))
    T_prev = se3_exp(torch.tensor([1.0, 2.0, 0.5, 0.3, -0.2, 0.1], dtype=torch.float64))
    T_curr = T_prev @ step
    half = depth_camera_motion(T_prev, T_curr, 1 / 30, 1 / 60)
    torch.testing.assert_close(half @ half, step)  # half an interval twice = the interval
    torch.testing.assert_close(depth_camera_motion(T_prev, T_curr, 1 / 30, -1 / 60), se3_inverse(half))
    assert depth_camera_motion(T_prev, T_curr, 1 / 30, 0.0) is None
    assert depth_camera_motion(T_prev, T_curr, 0.0, 0.01) is None
    assert depth_camera_motion(T_prev, T_curr, 1 / 30, MAX_OFFSET_S * 1.5) is None


def test_depth_taken_later_is_moved_back_to_the_colour_pose():
    scene, intrinsics = make_scene(0), default_intrinsics(96, 72)
    T_colour = trajectory_poses("loop", 300)[40]
    # the depth camera 2 cm and 1.5 deg away: several pixels of motion
    T_cd = se3_exp(torch.tensor([0.02, 0.005, -0.01, 0.0, math.radians(1.5), 0.0], dtype=torch.float64))
    T_depth = T_colour @ T_cd.numpy()
    _, depth_colour = render_view(scene, T_colour, intrinsics, supersample=1)
    _, depth_later = render_view(scene, T_depth, intrinsics, supersample=1)
    depth_colour, depth_later = torch.from_numpy(depth_colour), torch.from_numpy(depth_later)
    moved = depth_at_colour_time(depth_later, _K(intrinsics), T_cd)
    assert moved.shape == depth_later.shape and moved.dtype == depth_later.dtype
    both = (moved > 0) & (depth_colour > 0)
    assert both.float().mean() > 0.85  # only the strip the depth camera did not see is lost
    before = (depth_later - depth_colour)[both].abs()
    after = (moved - depth_colour)[both].abs()
    # nearest-pixel reads: most pixels within a few mm (plus a pixel's step on slanted surfaces), far better than unmoved
    assert after.median() < 0.2 * before.median() and after.median() < 0.005
    assert float(torch.quantile(after, 0.9)) < float(torch.quantile(before, 0.9))
    assert torch.isfinite(moved).all() and (moved >= 0).all()


def test_identity_motion_keeps_the_depth_and_missing_depth_stays_missing():
    depth = torch.rand(20, 30) + 0.5
    depth[5:8, 10:14] = 0
    K = torch.tensor([[40.0, 0, 14.5], [0, 40.0, 9.5], [0, 0, 1]], dtype=torch.float64)
    out = depth_at_colour_time(depth, K, torch.eye(4, dtype=torch.float64))
    torch.testing.assert_close(out, depth)
    assert (out[5:8, 10:14] == 0).all()


def _record(index: int, timestamp: float, T_wc: torch.Tensor, status: str = "ok"):
    from mipslam.state import FrameRecord
    return FrameRecord(index, timestamp, T_wc, torch.zeros(2), status, 0.0, 0, -1, -1, T_wc_tracked=T_wc)


def _frame(index: int, timestamp: float, offset: float):
    from mipslam.types import Frame, Intrinsics
    depth = torch.full((12, 16), 2.0)
    depth[:, 8:] = 3.0
    return Frame(index, timestamp, torch.zeros(12, 16, 3), depth, Intrinsics(20.0, 20.0, 7.5, 5.5, 16, 12),
                 depth_time_offset=offset)


def test_the_run_moves_depth_with_its_own_tracked_motion():
    from types import SimpleNamespace

    from mipslam.sensor_sync import (SensorTiming, predicted_velocity, recorded_velocity, synchronised,
                                     tracked_velocity)
    step = se3_exp(torch.tensor([0.03, 0.0, 0.0, 0.0, 0.02, 0.0], dtype=torch.float64))
    poses = [torch.eye(4, dtype=torch.float64)]
    for _ in range(2):
        poses.append(poses[-1] @ step)
    records = [_record(k, k / 30, poses[k]) for k in range(3)]
    frame = _frame(2, 2 / 30, 0.5 / 30)
    timing = SensorTiming(align_depth_time=True)
    # before tracking: the last interval (frames 0 -> 1); after: the frame's own (1 -> 2); read again: the same
    state = SimpleNamespace(frames=records[:2])
    predicted = predicted_velocity(state, frame)
    torch.testing.assert_close(se3_exp(predicted * (0.5 / 30)), depth_camera_motion(poses[0], poses[1], 1 / 30, 0.5 / 30))
    after = tracked_velocity(records[1], frame, poses[2], True)
    torch.testing.assert_close(se3_exp(after / 30), step)
    state.frames = records
    again = recorded_velocity(state, frame)
    assert torch.equal(again, after)
    moved = synchronised(frame, after, timing)
    assert torch.equal(moved.depth, synchronised(frame, again, timing).depth)
    assert not torch.equal(moved.depth, frame.depth) and moved.depth_time_offset == frame.depth_time_offset
    assert torch.equal(moved.color, frame.color)  # a global shutter: the colour stays
    # nothing to move: no velocity, no offset, alignment off, an offset beyond a stream's
    assert synchronised(frame, None, timing) is frame
    no_offset = _frame(2, 2 / 30, 0.0)
    assert synchronised(no_offset, after, timing) is no_offset
    assert synchronised(frame, after, SensorTiming()) is frame
    beyond = _frame(2, 2 / 30, 2 * MAX_OFFSET_S)
    assert torch.equal(synchronised(beyond, after, timing).depth, beyond.depth)
    # no velocity: the first frame, a lost previous frame, a frame not tracked yet
    assert recorded_velocity(state, _frame(0, 0.0, 0.01)) is None
    assert tracked_velocity(_record(1, 1 / 30, poses[1], "lost"), frame, poses[2], True) is None
    assert recorded_velocity(state, _frame(3, 3 / 30, 0.01)) is None


def test_frame_cache_adjusts_frames_read_again_as_they_were_put():
    from mipslam.datasets import FrameCache

    class Sequence:
        random_access = True

        def __len__(self):
            return 4

        def __getitem__(self, index):
            return _frame(index, index / 30, 0.01)

    cache = FrameCache(Sequence(), torch.device("cpu"), capacity=1)
    cache.adjust = lambda frame: _with_depth(frame, frame.depth + 1)
    first = cache[0]
    assert torch.equal(first.depth, _frame(0, 0, 0.01).depth + 1)
    cache.put(_with_depth(first, first.depth * 2))
    assert torch.equal(cache[0].depth, (_frame(0, 0, 0.01).depth + 1) * 2)  # the put frame, not a re-read
    cache[1]  # capacity 1: frame 0 leaves the cache and is read (and adjusted) again
    assert torch.equal(cache[0].depth, _frame(0, 0, 0.01).depth + 1)


def _with_depth(frame, depth):
    from dataclasses import replace
    return replace(frame, depth=depth)
