"""Local bundle adjustment: the keyframe window's poses by their ORB features, before mapping.

Render-based tracking is precise from frame to frame, but each keyframe inherits the small errors of the map it
was tracked against, and those add up over a few keyframes (fr3_teddy: relative error over one frame better
than ORB-SLAM3's, over 30 frames 1.6x its rotation error). Feature SLAM holds those keyframes together by
bundle adjustment over covisible keyframes (ORB-SLAM3's local BA). Here, at each new keyframe:

1. :func:`window_observations`: every ordered pair (a, b) of window keyframes is matched by projection
   (:func:`~mipslam.frontend.guided_matches` at the current poses); a match is keyframe a's 3D point, from its
   depth, seen at a keypoint of keyframe b. Points on a depth edge are left out (:func:`smooth_depth_points`):
   a corner's depth there may be the foreground's or the background's.
2. :func:`adjust_poses`: the poses minimise the Huber-weighted reprojection error of all matches by damped
   Gauss-Newton, with the oldest keyframes fixed (the gauge). The 3D points stay tied to their keyframe's
   depth, so the unknowns are the poses alone (6 per free keyframe).
3. :meth:`LocalBundleAdjuster.adjust_window`: the state takes the new poses; the Gaussians anchored to a moved
   keyframe and the frames tracked after it move with it (:meth:`~mipslam.state.SLAMState.correct_keyframe_poses`),
   so the map and the poses stay consistent and mapping starts from the adjusted window.

Keypoints are weighted by their pyramid level (sigma 1.2^level pixels, as ORB-SLAM). The stage is off unless
``local_ba.enabled``: docs/mapping.md, "Local bundle adjustment", has where it helps and where it does not.

Conventions (docs/design.md): OpenCV camera, ``T_wc`` camera-to-world, metres, pixels with integer centres.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from mipslam.config import LocalBAConfig, section_options
from mipslam.frontend import ORB_SCALE_FACTOR, FeatureOptions, FrameFeatures, extract_features, guided_matches
from mipslam.geometry import project, se3_exp, se3_inverse, se3_log
from mipslam.types import Frame, Intrinsics

if TYPE_CHECKING:
    from mipslam.datasets import FrameCache
    from mipslam.state import SLAMState


@dataclass(frozen=True)
class LocalBAOptions:
    """The ``local_ba`` config section and the adjustment's constants (docs/mapping.md, "Local bundle adjustment")."""

    enabled: bool = LocalBAConfig.enabled
    fixed_keyframes: int = 1  # the oldest window keyframes held fixed (the gauge)
    min_matches: int = 30  # a keyframe pair with fewer matches adds none (too little shared structure)
    # matching by projection within this fraction of the image size: the window's poses are already good to a few
    # pixels, and the front-end's wider radius lets repeated texture match its neighbouring copy
    match_radius: float = 0.02
    # reprojection errors in units of the keypoint's sigma (1 px at full resolution, 1.2^level above)
    huber_sigmas: float = 2.0  # errors above this weigh linearly
    outlier_sigmas: float = 16.0  # matches further off at the current poses are left out
    # The window's poses as tracking and mapping left them are a measurement too: each free pose is held to them
    # with this standard deviation, so directions the features barely constrain stay where the render put them
    prior_translation_m: float = 0.002
    prior_rotation_deg: float = 0.1
    iterations: int = 5  # damped Gauss-Newton steps
    damping: float = 1e-3  # Levenberg-Marquardt: the normal equations' diagonal grows by this fraction
    depth_edge_ratio: float = 0.03  # a point whose 3x3 depth neighbourhood spans more than this of its depth is dropped

    @classmethod
    def from_config(cls, section: LocalBAConfig) -> "LocalBAOptions":
        return section_options(cls, section)


@dataclass(frozen=True)
class KeyframeObservations:
    """Feature matches between window keyframes (positions in the adjusted pose list).

    source: [N] int64 keyframe whose depth gives the point; target: [N] int64 keyframe that sees it
    points: [N, 3] float64 the point in the source keyframe's camera (metres)
    pixels: [N, 2] float64 the matched keypoint in the target keyframe's image (u, v)
    pairs: keyframe pairs that contributed matches
    sigma: [N] float64 the keypoint's position uncertainty in pixels: the scale of the pyramid level it was found
        at (ORB-SLAM's 1.2^level); None: 1 for every match
    """

    source: torch.Tensor
    target: torch.Tensor
    points: torch.Tensor
    pixels: torch.Tensor
    pairs: int
    sigma: torch.Tensor | None = None

    def subset(self, keep: torch.Tensor) -> "KeyframeObservations":
        """The matches where ``keep`` [N] bool is true."""
        return KeyframeObservations(self.source[keep], self.target[keep], self.points[keep], self.pixels[keep],
                                    self.pairs, None if self.sigma is None else self.sigma[keep])

    def __len__(self) -> int:
        return int(self.source.shape[0])


@dataclass(frozen=True)
class LocalBAResult:
    """Outcome of :func:`adjust_poses`.

    T_wc: [K, 4, 4] float64 adjusted camera-to-world poses (the fixed ones unchanged)
    matches: matches used (within ``outlier_sigmas`` at the start); pairs: keyframe pairs with matches
    error_before / error_after: median reprojection error of those matches before and after, in sigmas
    """

    T_wc: torch.Tensor
    matches: int
    pairs: int
    error_before: float
    error_after: float


def smooth_depth_points(features: FrameFeatures, depth: torch.Tensor, max_ratio: float) -> FrameFeatures:
    """``features`` with the 3D points on a depth edge set to NaN: those whose 3x3 neighbourhood in ``depth``
    [H, W] (metres, 0 = none) spans more than ``max_ratio`` of the point's depth, or has a pixel without depth."""
    if max_ratio <= 0 or len(features) == 0:
        return features
    d = depth.detach().to("cpu", torch.float32)[None, None]  # [1, 1, H, W]
    highest = F.max_pool2d(d, 3, 1, 1)[0, 0].numpy()
    lowest = -F.max_pool2d(torch.where(d > 0, -d, torch.full_like(d, -np.inf)), 3, 1, 1)[0, 0].numpy()
    lowest = np.where(F.max_pool2d((d <= 0).float(), 3, 1, 1)[0, 0].numpy() > 0, 0.0, lowest)  # a hole nearby
    col = np.clip(np.rint(features.keypoints[:, 0]).astype(np.int64), 0, highest.shape[1] - 1)
    row = np.clip(np.rint(features.keypoints[:, 1]).astype(np.int64), 0, highest.shape[0] - 1)
    z = np.nan_to_num(features.points_c[:, 2], nan=0.0)
    edge = ~((lowest[row, col] > 0) & (highest[row, col] - lowest[row, col] <= max_ratio * z))
    points = features.points_c.copy()
    points[edge] = np.nan
    return FrameFeatures(features.keypoints, features.descriptors, points, features.octaves)


def window_observations(features: Sequence[FrameFeatures], T_wc: torch.Tensor, intrinsics: Intrinsics,
                        feature_options: FeatureOptions, min_matches: int) -> KeyframeObservations:
    """Matches of every ordered keyframe pair (module docstring, step 1). ``features``: one per keyframe, at the
    resolution of ``intrinsics``; ``T_wc`` [K, 4, 4] their current poses (the matching's prior)."""
    T_wc = T_wc.to(torch.float64)
    source, target, points, pixels, sigma, pairs = [], [], [], [], [], 0
    for a in range(len(features)):
        for b in range(len(features)):
            if a == b:
                continue
            T_ab = se3_inverse(T_wc[a]) @ T_wc[b]  # keyframe b's camera -> a's: guided_matches' T_rc
            matches = guided_matches(features[a], features[b], intrinsics, T_ab, feature_options)  # (b kp, a pt)
            if len(matches):
                matches = matches[np.isfinite(features[a].points_c[matches[:, 1], 0])]
            if len(matches) < min_matches:
                continue
            pairs += 1
            source.append(torch.full((len(matches),), a, dtype=torch.int64))
            target.append(torch.full((len(matches),), b, dtype=torch.int64))
            points.append(torch.from_numpy(features[a].points_c[matches[:, 1]]))
            pixels.append(torch.from_numpy(features[b].keypoints[matches[:, 0]].astype(np.float64)))
            octaves = features[b].octaves
            level = octaves[matches[:, 0]] if octaves is not None else np.zeros(len(matches), np.int64)
            sigma.append(torch.from_numpy(ORB_SCALE_FACTOR ** level.astype(np.float64)))
    if not pairs:
        empty = torch.zeros(0, dtype=torch.int64)
        return KeyframeObservations(empty, empty, torch.zeros(0, 3, dtype=torch.float64),
                                    torch.zeros(0, 2, dtype=torch.float64), 0)
    return KeyframeObservations(torch.cat(source), torch.cat(target), torch.cat(points), torch.cat(pixels), pairs,
                                torch.cat(sigma))


def reprojection_residuals(T_wc: torch.Tensor, observations: KeyframeObservations,
                           intrinsics: Intrinsics) -> torch.Tensor:
    """Each match's source point projected into its target keyframe minus the matched keypoint.
    T_wc [K, 4, 4] float64 -> [N, 2] pixels."""
    T_cw = se3_inverse(T_wc)
    T_ts = T_cw[observations.target] @ T_wc[observations.source]  # [N, 4, 4] source camera -> target camera
    p = (T_ts[:, :3, :3] @ observations.points.unsqueeze(-1)).squeeze(-1) + T_ts[:, :3, 3]  # [N, 3]
    projected, _ = project(p, intrinsics.matrix(torch.float64))
    return projected - observations.pixels


def reprojection_jacobians(T_wc: torch.Tensor, observations: KeyframeObservations,
                           intrinsics: Intrinsics) -> torch.Tensor:
    """d residual / d xi_source of each match, for the left perturbation ``exp(xi) T`` of the source pose
    (the target's is its negative: moving both cameras alike moves nothing). T_wc [K, 4, 4] float64 -> [N, 2, 6].

    With the world point P = T_s p and p' = R_t^T (P - t_t) in the target camera: dP/dxi = [I | -[P]x], so
    dp'/dxi_s = R_t^T [I | -[P]x] and the pinhole projection's d(u, v)/dp' = [[fx/z, 0, -fx x/z^2],
    [0, fy/z, -fy y/z^2]]."""
    T_s, T_t = T_wc[observations.source], T_wc[observations.target]  # [N, 4, 4]
    P = (T_s[:, :3, :3] @ observations.points.unsqueeze(-1)).squeeze(-1) + T_s[:, :3, 3]  # [N, 3] world
    p = (T_t[:, :3, :3].transpose(1, 2) @ (P - T_t[:, :3, 3]).unsqueeze(-1)).squeeze(-1)  # [N, 3] target camera
    z = p[:, 2].clamp_min(1e-6)
    zero = torch.zeros_like(z)
    d_projection = torch.stack([torch.stack([intrinsics.fx / z, zero, -intrinsics.fx * p[:, 0] / z**2], 1),
                                torch.stack([zero, intrinsics.fy / z, -intrinsics.fy * p[:, 1] / z**2], 1)], 1)
    skew = torch.zeros(len(P), 3, 3, dtype=P.dtype)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -P[:, 2], P[:, 1], -P[:, 0]
    skew = skew - skew.transpose(1, 2)  # [P]x
    d_world = torch.cat([torch.eye(3, dtype=P.dtype).expand(len(P), 3, 3), -skew], 2)  # [N, 3, 6]
    return d_projection @ T_t[:, :3, :3].transpose(1, 2) @ d_world


def huber_cost(error: torch.Tensor, huber_sigmas: float) -> float:
    """Sum of the Huber costs of reprojection errors ``error`` [N] (pixels)."""
    return float(torch.where(error <= huber_sigmas, 0.5 * error**2, huber_sigmas * (error - 0.5 * huber_sigmas)).sum())


def adjust_poses(T_wc: torch.Tensor, observations: KeyframeObservations, intrinsics: Intrinsics,
                 options: LocalBAOptions) -> LocalBAResult:
    """Poses ``T_wc`` [K, 4, 4] (camera-to-world, oldest first) that minimise the Huber-weighted reprojection
    error of ``observations`` with the first ``options.fixed_keyframes`` held (module docstring, step 2): damped
    Gauss-Newton with iteratively reweighted Huber weights, each free pose moving by a left perturbation
    ``exp(xi) T``, xi = (rho, phi) [6] (:func:`reprojection_jacobians`). Kept as they were when the Huber
    cost does not fall."""
    T0 = T_wc.to(torch.float64)
    K = T0.shape[0]
    fixed = min(options.fixed_keyframes, K)
    sigma = observations.sigma if observations.sigma is not None else torch.ones(len(observations), dtype=torch.float64)
    # errors in units of each keypoint's sigma (ORB-SLAM's information 1 / sigma^2 per pyramid level)
    start = (reprojection_residuals(T0, observations, intrinsics).norm(dim=1) / sigma if len(observations)
             else torch.zeros(0, dtype=torch.float64))
    used = start < options.outlier_sigmas  # [N]
    error_before = float(start[used].median()) if bool(used.any()) else float("nan")
    if fixed == K or int(used.sum()) < options.min_matches:
        return LocalBAResult(T0, int(used.sum()), observations.pairs, error_before, error_before)
    kept = observations.subset(used)
    sigma = sigma[used]
    prior_sigma = torch.tensor([options.prior_translation_m] * 3 + [math.radians(options.prior_rotation_deg)] * 3,
                               dtype=torch.float64)  # [6] (rho, phi)
    T = T0.clone()
    for _ in range(options.iterations):
        r = reprojection_residuals(T, kept, intrinsics) / sigma[:, None]  # [N, 2] whitened
        J = reprojection_jacobians(T, kept, intrinsics) / sigma[:, None, None]  # [N, 2, 6]
        error = r.norm(dim=1)
        weight = torch.where(error <= options.huber_sigmas, torch.ones_like(error),
                             options.huber_sigmas / error.clamp_min(1e-12))  # IRLS Huber weights [N]
        block = J.transpose(1, 2) @ (J * weight[:, None, None])  # [N, 6, 6]
        gradient = (J.transpose(1, 2) @ (weight[:, None] * r).unsqueeze(-1)).squeeze(-1)  # [N, 6]
        H = torch.zeros(K, K, 6, 6, dtype=torch.float64)
        s, t = kept.source, kept.target
        for rows, cols, sign in ((s, s, 1.0), (t, t, 1.0), (s, t, -1.0), (t, s, -1.0)):
            H.index_put_((rows, cols), sign * block, accumulate=True)
        g = torch.zeros(K, 6, dtype=torch.float64)
        g.index_add_(0, s, gradient)
        g.index_add_(0, t, -gradient)
        H = H[fixed:, fixed:].permute(0, 2, 1, 3).reshape((K - fixed) * 6, (K - fixed) * 6)
        prior = se3_log(T[fixed:] @ se3_inverse(T0[fixed:])) / prior_sigma  # [F, 6] whitened; d/dxi ~ I / sigma
        H = H + torch.diag((1.0 / prior_sigma**2).repeat(K - fixed))
        g = g[fixed:].reshape(-1) + (prior / prior_sigma).reshape(-1)
        H = H + options.damping * torch.diag(H.diagonal()) + 1e-9 * torch.eye(len(g), dtype=torch.float64)
        xi = -torch.linalg.solve(H, g)
        T = torch.cat([T[:fixed], se3_exp(xi.view(K - fixed, 6)) @ T[fixed:]])
    after = reprojection_residuals(T, kept, intrinsics).norm(dim=1) / sigma
    prior_cost = 0.5 * float(((se3_log(T[fixed:] @ se3_inverse(T0[fixed:])) / prior_sigma) ** 2).sum())
    worse = huber_cost(after, options.huber_sigmas) + prior_cost > huber_cost(start[used], options.huber_sigmas)
    if not bool(torch.isfinite(T).all()) or worse:
        return LocalBAResult(T0, len(kept), kept.pairs, error_before, error_before)
    return LocalBAResult(T, len(kept), kept.pairs, error_before, float(after.median()))


class LocalBundleAdjuster:
    """The stage: the options and the features of the window's keyframes (module docstring, step 3).

    Features come from each keyframe's image as the frame cache holds it after tracking: re-timed to the colour
    instant on a rolling-shutter camera (:mod:`mipslam.sensor_sync`), where the front-end's, taken before
    tracking, still carry the shutter's skew (fr1_rpy: keyframes moved by up to 6 cm to fit it). They are
    cached by frame index for the keyframe's time in the window; a miss recomputes the same values.
    """

    def __init__(self, options: LocalBAOptions, feature_options: FeatureOptions = FeatureOptions(),
                 cache_frames: int = 32):
        self.options = options
        self.feature_options = feature_options
        self.cache_frames = cache_frames
        self._features: OrderedDict[int, FrameFeatures] = OrderedDict()

    def features(self, frame: Frame) -> FrameFeatures:
        """``frame``'s features with the points on depth edges dropped (:func:`smooth_depth_points`)."""
        cached = self._features.get(frame.index)
        if cached is None:
            cached = smooth_depth_points(extract_features(frame.color, frame.depth, frame.intrinsics,
                                                          self.feature_options),
                                         frame.depth, self.options.depth_edge_ratio)
            self._features[frame.index] = cached
            while len(self._features) > self.cache_frames:
                self._features.popitem(last=False)
        self._features.move_to_end(frame.index)
        return cached

    def adjust_window(self, state: "SLAMState", frames: "FrameCache") -> LocalBAResult | None:
        """The step in the frame loop, after a keyframe joined the window and before mapping: adjust the window's
        poses and move the state and the map with them. None: fewer than two keyframes in the window."""
        ids = sorted(state.window)  # oldest first: the fixed ones lead
        if len(ids) < 2:
            return None
        records = [state.keyframe_record(k) for k in ids]
        images = [frames[record.index] for record in records]
        T_wc = torch.stack([record.T_wc.to(torch.float64) for record in records])
        matching = replace(self.feature_options, guided_radius=self.options.match_radius)
        observations = window_observations([self.features(image) for image in images], T_wc, images[0].intrinsics,
                                           matching, self.options.min_matches)
        result = adjust_poses(T_wc, observations, images[0].intrinsics, self.options)
        if not torch.equal(result.T_wc, T_wc):
            poses = state.keyframe_poses().clone()
            poses[ids] = result.T_wc
            state.correct_keyframe_poses(poses, move_map=True)
        return result
