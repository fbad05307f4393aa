"""Keyframe decisions, covisibility, window and random past keyframes on hand-built poses and depths."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from mipslam.keyframes import KeyframeOptions
from mipslam.geometry.se3 import se3_exp
from mipslam.keyframes import (
    covisibility,
    decide_keyframe,
    median_valid_depth,
    select_random_past,
    update_window,
)

H, W, F = 48, 64, 50.0
K = torch.tensor([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]], dtype=torch.float64)


def pose(tx=0.0, ty=0.0, tz=0.0, rx=0.0, ry=0.0, rz=0.0) -> torch.Tensor:
    return se3_exp(torch.tensor([tx, ty, tz, rx, ry, rz], dtype=torch.float64))


def wall(distance: float = 2.0) -> torch.Tensor:
    """Depth of a fronto-parallel wall seen by an unrotated camera."""
    return torch.full((H, W), distance, dtype=torch.float32)


def test_camera_at_rest_sees_everything():
    depth = wall()
    assert covisibility(depth, pose(), K, depth, pose(), pixel_stride=1) == 1.0
    # moving towards the wall keeps every point in view with consistent depth
    assert covisibility(wall(1.8), pose(tz=0.2), K, depth, pose(), pixel_stride=1) == 1.0


def test_sideways_motion_loses_the_columns_that_leave_the_keyframe():
    shift_m = 0.4  # at 2 m with f = 50 this is a 10 pixel shift
    depth = wall()
    covis = covisibility(depth, pose(tx=shift_m), K, depth, pose(), pixel_stride=1)
    # pixel u of the current view lands on u + 10 in the keyframe: columns 54..63 fall outside
    assert covis == pytest.approx((W - 10) / W)
    strided = covisibility(depth, pose(tx=shift_m), K, depth, pose(), pixel_stride=4)
    assert strided == pytest.approx(sum(1 for u in range(0, W, 4) if u + 10 <= W - 1) / len(range(0, W, 4)))


def test_occlusion_and_missing_keyframe_depth_are_not_covisible():
    depth = wall()
    keyframe_depth = wall()
    keyframe_depth[:, :16] = 1.0  # an object in front of the wall hides the left quarter in the keyframe
    keyframe_depth[:12, 16:] = 0.0  # no measurement in the top band
    covis = covisibility(depth, pose(), K, keyframe_depth, pose(), pixel_stride=1)
    assert covis == pytest.approx((W - 16) * (H - 12) / (W * H))


def test_no_valid_depth_gives_nan_and_no_keyframe():
    empty = torch.zeros(H, W)
    assert math.isnan(covisibility(empty, pose(), K, wall(), pose()))
    decision = decide_keyframe(KeyframeOptions(), empty, pose(), K, wall(), pose())
    assert not decision.is_keyframe and decision.reasons == ("no_valid_depth",)
    first = decide_keyframe(KeyframeOptions(), empty, pose(), K, None, None)
    assert not first.is_keyframe and first.reasons == ("no_valid_depth",)


def test_first_frame_is_a_keyframe_and_a_resting_camera_is_not():
    config = KeyframeOptions()
    first = decide_keyframe(config, wall(), pose(), K, None, None)
    assert first.is_keyframe and first.reasons == ("first",)
    rest = decide_keyframe(config, wall(), pose(), K, wall(), pose())
    assert not rest.is_keyframe and rest.reasons == ()
    assert rest.covisibility == 1.0 and rest.translation_m == 0.0 and rest.rotation_deg == pytest.approx(0.0, abs=1e-6)


def test_translation_relative_to_median_depth():
    config = KeyframeOptions(covisibility_threshold=0.9, translation_ratio=0.1, rotation_deg=15.0)
    # 0.3 m forward at a median depth of 2 m: ratio 0.15 > 0.1, everything still covisible
    forward = decide_keyframe(config, wall(1.7), pose(tz=0.3), K, wall(), pose())
    assert forward.is_keyframe and forward.reasons == ("translation",)
    assert forward.median_depth_m == 2.0 and forward.translation_ratio == pytest.approx(0.15)
    assert forward.covisibility == 1.0
    # the same motion in a scene 10 m deep is small
    far = decide_keyframe(config, wall(9.7), pose(tz=0.3), K, wall(10.0), pose())
    assert not far.is_keyframe and far.translation_ratio == pytest.approx(0.03)


def test_rotation_threshold():
    config = KeyframeOptions(covisibility_threshold=0.05, rotation_deg=15.0)
    turned = decide_keyframe(config, wall(), pose(rz=math.radians(20)), K, wall(), pose())
    assert turned.reasons == ("rotation",) and turned.rotation_deg == pytest.approx(20.0)
    slight = decide_keyframe(config, wall(), pose(rz=math.radians(10)), K, wall(), pose())
    assert not slight.is_keyframe and slight.rotation_deg == pytest.approx(10.0)


def test_covisibility_drop_alone_makes_a_keyframe():
    config = KeyframeOptions(covisibility_threshold=0.9)
    keyframe_depth = wall()
    keyframe_depth[:, :16] = 1.0  # a quarter of the view was hidden in the keyframe
    decision = decide_keyframe(config, wall(), pose(), K, keyframe_depth, pose())
    assert decision.reasons == ("covisibility",) and decision.covisibility == pytest.approx(0.75)
    assert decision.translation_m == 0.0


def test_median_valid_depth_ignores_holes():
    depth = torch.tensor([[0.0, 1.0, 2.0], [3.0, float("nan"), 0.0]])
    assert median_valid_depth(depth) == 2.0
    assert math.isnan(median_valid_depth(torch.zeros(2, 2)))


def test_window_keeps_newest_and_drops_non_overlapping():
    overlaps = {9: 0.8, 8: 0.01, 7: 0.5, 6: 0.0, 5: 0.3, 4: 0.9}
    update = update_window([9, 8, 7, 6, 5, 4], 10, overlaps, window_size=8, min_overlap=0.05)
    # 9 is protected (newest two: 10, 9); 8 and 6 no longer overlap
    assert update.window == (10, 9, 7, 5, 4) and set(update.dropped) == {8, 6}
    # bounded: beyond window_size the least overlapping go first
    update = update_window([9, 8, 7, 6, 5, 4], 10, overlaps, window_size=3, min_overlap=0.05)
    assert update.window == (10, 9, 4) and set(update.dropped) == {8, 6, 7, 5}
    # the previous keyframe stays even without overlap (it is what tracking just used)
    update = update_window([9], 10, {9: 0.0}, window_size=4)
    assert update.window == (10, 9) and update.dropped == ()
    # ties: the oldest leaves first
    update = update_window([3, 2, 1], 4, {3: 0.5, 2: 0.5, 1: 0.5}, window_size=3)
    assert update.window == (4, 3, 2) and update.dropped == (1,)
    assert update_window([], 0, {}, window_size=1).window == (0,)


def test_random_past_keyframes_are_deterministic_and_outside_the_window():
    keyframes = list(range(20))
    window = [19, 18, 17, 16]

    def draw(seed: int, count: int = 3) -> tuple[int, ...]:
        return select_random_past(keyframes, window, count, torch.Generator().manual_seed(seed))

    first = draw(0)
    assert first == draw(0)
    assert len(first) == 3 and len(set(first)) == 3 and list(first) == sorted(first)
    assert not set(first) & set(window) and all(0 <= k < 16 for k in first)
    assert len({draw(seed) for seed in range(10)}) > 1
    assert draw(0, count=50) == tuple(range(16))
    assert draw(0, count=0) == ()
    assert select_random_past([1, 2], [1, 2], 2, torch.Generator().manual_seed(0)) == ()


def test_a_view_the_map_covers_too_little_is_a_keyframe_even_at_full_covisibility():
    config = KeyframeOptions(min_map_coverage=0.9)
    # the camera rests on the last keyframe (covisibility 1) but the map renders only 80 % of its depth
    thin = decide_keyframe(config, wall(), pose(), K, wall(), pose(), map_coverage=0.8)
    assert thin.is_keyframe and thin.reasons == ("coverage",)
    covered = decide_keyframe(config, wall(), pose(), K, wall(), pose(), map_coverage=0.95)
    assert not covered.is_keyframe
    unknown = decide_keyframe(config, wall(), pose(), K, wall(), pose())  # no render: the rule cannot fire
    assert not unknown.is_keyframe
    off = decide_keyframe(KeyframeOptions(), wall(), pose(), K, wall(), pose(), map_coverage=0.1)  # default 0: off
    assert not off.is_keyframe


class _Intrinsics:
    def matrix(self):
        return K


class _Keyframes:
    """The part of SLAMState and FrameCache that the keyframe step reads: keyframes at ``poses`` [4, 4] each,
    every one seeing the wall 2 m ahead."""

    def __init__(self, poses):
        from types import SimpleNamespace

        self.records = [SimpleNamespace(index=k, T_wc=p) for k, p in enumerate(poses)]
        self.keyframe_frames = list(range(len(poses)))
        self.window = [len(poses) - 1]  # the mapping window: the last keyframe
        self.frames = [None] * (KeyframeOptions.revisit_min_age + len(poses))  # every keyframe old enough

    def last_keyframe_id(self):
        return len(self.records) - 1

    def keyframe_record(self, k):
        return self.records[k]

    def keyframe_poses(self):
        return torch.stack([r.T_wc for r in self.records])

    def __getitem__(self, index):
        from types import SimpleNamespace

        return SimpleNamespace(depth=wall(), intrinsics=_Intrinsics())


def test_nearest_keyframes_within_the_rule_bounds_nearest_first():
    from mipslam.keyframes import nearest_keyframes

    config = KeyframeOptions(translation_ratio=0.1, rotation_deg=15.0)
    poses = torch.stack([pose(tx=0.15), pose(), pose(tx=0.05), pose(rz=math.radians(20)), pose(tx=0.5)])
    # median depth 2 m: translation bound 0.2 m; 20 degrees and 0.5 m are outside
    assert nearest_keyframes(poses, pose(tx=0.04), 2.0, config, 5) == [2, 1, 0]
    assert nearest_keyframes(poses, pose(tx=0.04), 2.0, config, 1) == [2]
    assert nearest_keyframes(poses, pose(tx=0.04), 2.0, config, 0) == []
    assert nearest_keyframes(poses, pose(tx=0.04), math.nan, config, 3) == []


def test_a_revisit_that_an_older_keyframe_covers_adds_no_keyframe():
    from mipslam.keyframes import keyframe_decision
    from types import SimpleNamespace

    config = KeyframeOptions(covisibility_threshold=0.9, translation_ratio=0.1, rotation_deg=15.0)
    # keyframe 0 at the origin, keyframe 1 (the last, the window) 0.6 m to the side: back at the origin the last
    # keyframe's rule fires (translation, covisibility) but keyframe 0 holds the view
    keyframes = _Keyframes([pose(), pose(tx=0.6)])
    frame = SimpleNamespace(depth=wall(), intrinsics=_Intrinsics())
    back = keyframe_decision(config, keyframes, keyframes, frame, pose(tx=0.01))
    assert not back.is_keyframe and back.covered_by == 0 and back.reasons == ()
    # an old keyframe still in the mapping window stands in too (laps of a room keep the first lap's last
    # keyframes in the window)
    keyframes.window = [1, 0]
    held = keyframe_decision(config, keyframes, keyframes, frame, pose(tx=0.01))
    assert not held.is_keyframe and held.covered_by == 0
    keyframes.window = [1]
    # nor does a recent one (the camera back within revisit_min_age frames)
    young = keyframe_decision(replace(config, revisit_min_age=10**6), keyframes, keyframes, frame, pose(tx=0.01))
    assert young.is_keyframe and young.covered_by == -1
    # off: the last keyframe's rule alone decides
    off = keyframe_decision(replace(config, revisit_candidates=0), keyframes, keyframes, frame, pose(tx=0.01))
    assert off.is_keyframe and "translation" in off.reasons and off.covered_by == -1
    # a new place is still a keyframe
    new = keyframe_decision(config, keyframes, keyframes, frame, pose(tx=-0.6))
    assert new.is_keyframe and new.covered_by == -1
    # the map lacking surfaces there (coverage) makes a keyframe even where an older keyframe's pose is near
    thin = keyframe_decision(replace(config, min_map_coverage=0.95), keyframes, keyframes, frame, pose(tx=0.01),
                             map_coverage=0.5)
    assert thin.is_keyframe and "coverage" in thin.reasons
