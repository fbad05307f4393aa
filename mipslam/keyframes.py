"""Keyframe decision, the bounded keyframe window and random past keyframes (pure functions).

Covisibility (our choice: geometric, from depth and poses, so it does not depend on the
renderer or on how well the map is trained yet). For frames a (current) and b (keyframe):
the fraction of a's valid-depth pixels (on a ``pixel_stride`` grid) whose back-projected point
``p_b = inv(T_wc_b) T_wc_a z_a K_a^-1 (u, v, 1)`` (b's camera frame, depth ``z_b``) lies in front
of b, projects inside b's image, lands on a pixel with valid depth ``d_b`` and agrees with it:
``|z_b - d_b| <= depth_tolerance * d_b``. Points hidden behind b's surface (z_b much larger) or
in front of it (b saw free space there) are not covisible. The measure is asymmetric and is 1
for a camera at rest.

Keyframe rule (thresholds from :class:`KeyframeOptions`): the first frame is a
keyframe; afterwards a frame is one when covisibility with the last keyframe drops below
``covisibility_threshold``, or the translation from the last keyframe exceeds
``translation_ratio`` times the scene's median depth (the last keyframe's median valid depth),
or the rotation exceeds ``rotation_deg``, or the map covers less than ``min_map_coverage`` of
the frame's valid-depth pixels (tracking's render at the tracked pose: the view shows surfaces
no keyframe has mapped, which covisibility with the last keyframe alone misses when the view
drifts slowly away from it). A frame without any valid depth never becomes a keyframe (nothing
to map).

Revisits (:func:`covering_keyframe`): a frame whose view an old keyframe already holds adds none. Old: made
at least ``revisit_min_age`` frames ago (the window may hold it: on laps of a room it holds the first lap's last
keyframes while the later laps make none). When only the last-keyframe criteria
fire (covisibility, translation, rotation; not coverage: the map lacks surfaces there), the
``revisit_candidates`` old keyframes nearest in pose (translation over the frame's median depth plus rotation
over ``rotation_deg``) within the translation and rotation bounds are tested; the first whose covisibility
reaches ``covisibility_threshold`` covers the frame, which then is no keyframe. On laps of one room the
keyframes stop growing once it is covered; a camera swaying back and forth over one place (fr1_rpy) keeps
making the keyframes its map needs (docs/tracking.md, "Keyframes").

Window: newest first; the newest ``keep_newest`` always stay, older ones leave when their
overlap with the new keyframe falls below ``min_overlap`` and, beyond ``window_size``, the least
overlapping (then the oldest) leave first (the MonoGS policy, with our covisibility).

The functions above are pure. The stage's steps in the frame loop apply them to the
:class:`~mipslam.state.SLAMState`: :func:`keyframe_decision` and :func:`insert_keyframe`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Mapping, Sequence

import torch

from mipslam.config import KeyframeConfig, section_options
from mipslam.geometry.camera import project, unproject
from mipslam.geometry.se3 import relative_motion, se3_inverse, transform_points

if TYPE_CHECKING:
    from mipslam.datasets import FrameCache
    from mipslam.state import FrameRecord, SLAMState
    from mipslam.types import Frame



@dataclass(frozen=True)
class KeyframeOptions:
    """The keyframe rule and window: the ``keyframes`` config section's keys (defaults there) and the
    stage's constants (defined here). Built from the config by :meth:`from_config`."""

    covisibility_threshold: float = KeyframeConfig.covisibility_threshold
    window_size: int = KeyframeConfig.window_size
    random_past: int = KeyframeConfig.random_past
    min_map_coverage: float = KeyframeConfig.min_map_coverage
    translation_ratio: float = 0.1  # a new keyframe when the translation > ratio * median scene depth ...
    rotation_deg: float = 15.0  # ... or the rotation exceeds this
    # Covisibility: a point is seen by both frames when their depths agree within this fraction, evaluated on
    # every covisibility_pixel_stride-th pixel in u and v.
    covisibility_depth_tolerance: float = 0.1
    covisibility_pixel_stride: int = 4
    window_min_overlap: float = 0.05  # window keyframes seeing less of the new keyframe than this leave
    # Old keyframes nearest in pose tested for covering a frame the last keyframe's rule makes one (0: off), and
    # how many frames old a keyframe must be to count (under 7 s at 30 Hz). fr1_rpy sways over one place: with no
    # age it makes 25 keyframes instead of 43 and tracks at 1.76 cm instead of 1.39-1.59; from 200 frames on it
    # keeps its keyframes (150: 41, 1.55 cm; 200: 44, 1.49; 300: 46, 1.48; docs/tracking.md, "Keyframes").
    revisit_candidates: int = 3
    revisit_min_age: int = 200

    @classmethod
    def from_config(cls, section: KeyframeConfig) -> "KeyframeOptions":
        return section_options(cls, section)


DEFAULT_DEPTH_TOLERANCE = KeyframeOptions.covisibility_depth_tolerance
DEFAULT_PIXEL_STRIDE = KeyframeOptions.covisibility_pixel_stride
DEFAULT_MIN_OVERLAP = KeyframeOptions.window_min_overlap


def covisibility(
    depth: torch.Tensor,  # [H, W] metres of the current frame, 0 = no measurement
    T_wc: torch.Tensor,  # [4, 4] current camera to world
    K: torch.Tensor,  # [3, 3] current intrinsics
    keyframe_depth: torch.Tensor,  # [H2, W2] metres
    keyframe_T_wc: torch.Tensor,  # [4, 4]
    keyframe_K: torch.Tensor | None = None,  # [3, 3]; default: same as K
    *,
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
    pixel_stride: int = DEFAULT_PIXEL_STRIDE,
) -> float:
    """Fraction in [0, 1] of the current frame's valid pixels that the keyframe also sees
    (module docstring); NaN when the current frame has no valid depth on the sampling grid."""
    dtype = torch.float64
    device = depth.device
    sampled = depth[::pixel_stride, ::pixel_stride].to(dtype)  # [h, w]
    valid = torch.isfinite(sampled) & (sampled > 0)
    total = int(valid.sum())
    if total == 0:
        return math.nan
    v, u = torch.nonzero(valid, as_tuple=True)
    uv = torch.stack([u * pixel_stride, v * pixel_stride], -1).to(dtype)  # [M, 2]
    K = K.to(device=device, dtype=dtype)
    K_b = K if keyframe_K is None else keyframe_K.to(device=device, dtype=dtype)
    points_a = unproject(uv, sampled[v, u], K)  # [M, 3]
    T_ba = se3_inverse(keyframe_T_wc.to(device=device, dtype=dtype)) @ T_wc.to(device=device, dtype=dtype)
    points_b = transform_points(T_ba, points_a)  # [M, 3]
    uv_b, z_b = project(points_b, K_b)
    height_b, width_b = keyframe_depth.shape
    col = torch.round(uv_b[:, 0])
    row = torch.round(uv_b[:, 1])
    inside = (z_b > 1e-6) & (col >= 0) & (col <= width_b - 1) & (row >= 0) & (row <= height_b - 1)
    col = col.clamp(0, width_b - 1).long()
    row = row.clamp(0, height_b - 1).long()
    d_b = keyframe_depth.to(dtype)[row, col]  # [M]
    agree = inside & torch.isfinite(d_b) & (d_b > 0) & ((z_b - d_b).abs() <= depth_tolerance * d_b)
    return float(agree.sum()) / total


def median_valid_depth(depth: torch.Tensor) -> float:
    """Median of the valid (finite, > 0) depths in metres; NaN when there are none.  depth [H, W]"""
    values = depth[torch.isfinite(depth) & (depth > 0)]
    return float(values.median()) if values.numel() else math.nan


@dataclass(frozen=True)
class KeyframeDecision:
    """Why a frame is (or is not) a keyframe, with the measured quantities.

    reasons: the criteria that fired, a subset of ("first", "covisibility", "translation",
    "rotation", "coverage"); ("no_valid_depth",) when the frame cannot be a keyframe.
    covered_by: the older keyframe whose view holds the frame's (no keyframe although the last keyframe's
    criteria fired; :func:`covering_keyframe`), -1 otherwise.
    """

    is_keyframe: bool
    reasons: tuple[str, ...]
    covisibility: float
    translation_m: float
    translation_ratio: float  # translation / median scene depth
    rotation_deg: float
    median_depth_m: float
    covered_by: int = -1


def decide_keyframe(
    config: KeyframeOptions,
    depth: torch.Tensor,  # [H, W] metres
    T_wc: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    last_keyframe_depth: torch.Tensor | None,  # [H2, W2] metres; None before the first keyframe
    last_keyframe_T_wc: torch.Tensor | None,  # [4, 4]
    last_keyframe_K: torch.Tensor | None = None,  # [3, 3]; default: same as K
    map_coverage: float = math.nan,  # fraction of the frame's valid-depth pixels the map renders (NaN: unknown)
) -> KeyframeDecision:
    """Apply the keyframe rule of the module docstring (covisibility with ``config``'s tolerance and stride).

    Poses are camera-to-world float64 (OpenCV camera); translations in metres, rotations in degrees."""
    if last_keyframe_T_wc is None or last_keyframe_depth is None:
        median_current = median_valid_depth(depth)
        has_depth = not math.isnan(median_current)
        return KeyframeDecision(has_depth, ("first",) if has_depth else ("no_valid_depth",), math.nan, 0.0, 0.0,
                                0.0, median_current)
    covis = covisibility(depth, T_wc, K, last_keyframe_depth, last_keyframe_T_wc, last_keyframe_K,
                         depth_tolerance=config.covisibility_depth_tolerance,
                         pixel_stride=config.covisibility_pixel_stride)
    translation, rotation = (float(v) for v in relative_motion(last_keyframe_T_wc, T_wc))
    median = median_valid_depth(last_keyframe_depth)
    if math.isnan(median):  # the frame's own, only then: a median is a sort of its valid pixels
        median = median_valid_depth(depth)
    ratio = translation / median if median > 0 else (math.inf if translation > 0 else 0.0)
    if math.isnan(covis):
        return KeyframeDecision(False, ("no_valid_depth",), covis, translation, ratio, rotation, median)
    reasons = []
    if covis < config.covisibility_threshold:
        reasons.append("covisibility")
    if ratio > config.translation_ratio:
        reasons.append("translation")
    if rotation > config.rotation_deg:
        reasons.append("rotation")
    if map_coverage < config.min_map_coverage:  # NaN compares False: unknown coverage never fires
        reasons.append("coverage")
    return KeyframeDecision(bool(reasons), tuple(reasons), covis, translation, ratio, rotation, median)


@dataclass(frozen=True)
class WindowUpdate:
    """The keyframe window after adding a keyframe (ids newest first) and the ids that left."""

    window: tuple[int, ...]
    dropped: tuple[int, ...]


def update_window(
    window: Sequence[int],
    new_keyframe: int,
    overlap_with_new: Mapping[int, float],
    *,
    window_size: int,
    min_overlap: float = DEFAULT_MIN_OVERLAP,
    keep_newest: int = 2,
) -> WindowUpdate:
    """Insert ``new_keyframe`` at the front of ``window`` (ids, newest first) and bound it.

    overlap_with_new: keyframe id -> covisibility of the new keyframe with it (missing = 0).
    The newest ``keep_newest`` (including the new one) always stay; others leave when their
    overlap is below ``min_overlap``; then, while the window is longer than ``window_size``,
    the remaining keyframe with the lowest overlap leaves (ties: the oldest).
    """
    if window_size < 1:
        raise ValueError(f"window_size must be >= 1, got {window_size}")
    ordered = [int(new_keyframe)] + [int(k) for k in window if int(k) != int(new_keyframe)]
    protected = min(max(1, keep_newest), window_size)
    kept = ordered[:protected]
    dropped = []
    candidates = []
    for kf in ordered[protected:]:
        overlap = overlap_with_new.get(kf, 0.0)
        if not overlap >= min_overlap:  # also drops NaN overlaps
            dropped.append(kf)
        else:
            candidates.append(kf)
    while len(kept) + len(candidates) > window_size:
        # lowest overlap first; among equals the oldest (last in newest-first order)
        position = min(range(len(candidates)), key=lambda i: (overlap_with_new.get(candidates[i], 0.0), -i))
        dropped.append(candidates.pop(position))
    return WindowUpdate(window=tuple(kept + candidates), dropped=tuple(dropped))


def update_window_from_config(window: Sequence[int], new_keyframe: int, overlap_with_new: Mapping[int, float],
                              config: KeyframeOptions) -> WindowUpdate:
    """:func:`update_window` with ``window_size`` and ``min_overlap`` from the config."""
    return update_window(window, new_keyframe, overlap_with_new, window_size=config.window_size,
                         min_overlap=config.window_min_overlap)


def select_random_past(
    keyframes: Sequence[int],
    window: Sequence[int],
    count: int,
    generator: torch.Generator,
) -> tuple[int, ...]:
    """Up to ``count`` distinct keyframe ids from ``keyframes`` that are not in ``window``, drawn
    uniformly without replacement with ``generator`` (deterministic for a given generator
    state; a draw is made whenever the pool is non-empty so the generator advances the same way
    on every run). Returned in ascending order."""
    in_window = {int(k) for k in window}
    pool = sorted({int(k) for k in keyframes} - in_window)
    if count <= 0 or not pool:
        return ()
    order = torch.randperm(len(pool), generator=generator, device=generator.device)
    return tuple(sorted(pool[int(i)] for i in order[:count]))


# ----------------------------------------------------------------------------- the steps in the frame loop

def keyframe_decision(config: KeyframeOptions, state: "SLAMState", frames: "FrameCache", frame: "Frame",
                      T_wc: torch.Tensor, map_coverage: float = math.nan) -> KeyframeDecision:
    """Whether ``frame``, tracked at ``T_wc`` [4, 4] (camera-to-world) where the map covers ``map_coverage`` of
    its valid depth, becomes a keyframe: the rule of the module docstring against the last keyframe of
    ``state`` (the first one when there is none)."""
    last = state.last_keyframe_id()
    if last is None:
        return decide_keyframe(config, frame.depth, T_wc, frame.intrinsics.matrix(), None, None, None)
    record = state.keyframe_record(last)
    keyframe = frames[record.index]
    decision = decide_keyframe(config, frame.depth, T_wc, frame.intrinsics.matrix(), keyframe.depth, record.T_wc,
                               keyframe.intrinsics.matrix(), map_coverage)
    if not decision.is_keyframe or not set(decision.reasons) <= REVISIT_REASONS:
        return decision
    covering = covering_keyframe(config, state, frames, frame, T_wc, decision.median_depth_m)
    if covering < 0:
        return decision
    return replace(decision, is_keyframe=False, reasons=(), covered_by=covering)


# The last keyframe's criteria an older keyframe's view can answer (coverage: the map lacks the surfaces)
REVISIT_REASONS = frozenset({"covisibility", "translation", "rotation"})


def nearest_keyframes(keyframe_T_wc: torch.Tensor, T_wc: torch.Tensor, median_depth_m: float,
                      config: KeyframeOptions, count: int) -> list[int]:
    """Up to ``count`` keyframe ids, nearest first, whose pose is within the keyframe rule's translation
    (``translation_ratio * median_depth_m``) and rotation (``rotation_deg``) of ``T_wc`` [4, 4].
    Distance: translation / median depth / translation_ratio + rotation / rotation_deg.
    keyframe_T_wc [K, 4, 4] camera-to-world."""
    if count <= 0 or len(keyframe_T_wc) == 0 or not median_depth_m > 0:
        return []
    translation, rotation = relative_motion(keyframe_T_wc, T_wc)  # [K] each
    translation = translation / (median_depth_m * config.translation_ratio)
    rotation = rotation / config.rotation_deg
    near = (translation <= 1.0) & (rotation <= 1.0)
    distance = torch.where(near, translation + rotation, torch.inf)
    order = torch.argsort(distance)[:count]
    return [int(k) for k in order if bool(near[k])]


def covering_keyframe(config: KeyframeOptions, state: "SLAMState", frames: "FrameCache", frame: "Frame",
                      T_wc: torch.Tensor, median_depth_m: float) -> int:
    """The old keyframe (module docstring) whose view holds ``frame`` at ``T_wc`` [4, 4]: of the
    ``revisit_candidates`` nearest in pose (:func:`nearest_keyframes`), the first whose covisibility reaches
    ``covisibility_threshold``; -1 when none does."""
    if config.revisit_candidates <= 0 or not state.keyframe_frames:
        return -1
    newest = len(state.frames) - config.revisit_min_age
    old = [k for k, position in enumerate(state.keyframe_frames) if position <= newest]
    if not old:
        return -1
    if not median_depth_m > 0:
        median_depth_m = median_valid_depth(frame.depth)
    poses = state.keyframe_poses()[old]
    for nearest in nearest_keyframes(poses, T_wc, median_depth_m, config, config.revisit_candidates):
        kf = old[nearest]
        record = state.keyframe_record(kf)
        keyframe = frames[record.index]
        covis = covisibility(frame.depth, T_wc, frame.intrinsics.matrix(), keyframe.depth, record.T_wc,
                             keyframe.intrinsics.matrix(), depth_tolerance=config.covisibility_depth_tolerance,
                             pixel_stride=config.covisibility_pixel_stride)
        if covis >= config.covisibility_threshold:
            return kf
    return -1


def insert_keyframe(config: KeyframeOptions, state: "SLAMState", frames: "FrameCache",
                    record: "FrameRecord") -> tuple[int, ...]:
    """Make ``record`` (the newest frame of ``state``) keyframe ``record.keyframe_id``: update the window by
    covisibility with the new keyframe and draw ``random_past`` older keyframes with the run's generator.
    Returns the keyframes to map over: the window (newest first), then the past ones (ascending)."""
    state.keyframe_frames.append(len(state.frames) - 1)
    frames.keep(record.index)  # mapping's past views and loop verification read keyframes again
    frame = frames[record.index]
    overlaps = {}
    for kf in state.window:
        other = state.keyframe_record(kf)
        overlaps[kf] = covisibility(frame.depth, record.T_wc, frame.intrinsics.matrix(), frames[other.index].depth,
                                    other.T_wc, depth_tolerance=config.covisibility_depth_tolerance,
                                    pixel_stride=config.covisibility_pixel_stride)
    state.window = list(update_window_from_config(state.window, record.keyframe_id, overlaps, config).window)
    past = select_random_past(range(len(state.keyframe_frames)), state.window, config.random_past, state.generator)
    return (*state.window, *past)
