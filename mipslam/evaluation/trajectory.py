"""Trajectory accuracy: association, Umeyama alignment, ATE and RPE (the numbers evo computes).

Protocol (the same as ``evo_ape tum GT EST -a --t_max_diff 0.02`` and ``evo_rpe tum GT EST -a
--delta 1 --delta_unit f --t_max_diff 0.02``, evo 1.38):

1. Association. ``timestamp``: evo's ``sync.associate_trajectories`` (nearest time): it walks the
   trajectory with fewer poses (the estimate when both have the same count), finds for each of
   its stamps the nearest stamp of the other one and keeps the pair when ``|dt| <= max_diff``; on
   a tie the earlier stamp wins; one ground-truth pose may serve two estimated ones. ``index``:
   pose i with pose i (Replica, whose ground truth has no timestamps); both must have as many poses.
2. Alignment (Umeyama, IEEE PAMI 1991, closed form; Horn's method for SE(3)): the similarity
   ``p_gt ~ s R p_est + t`` minimising the squared position error over the matched poses, with the
   reflection fix ``S = diag(1, 1, -1)`` when ``det(U) det(V) < 0``; ``s = 1`` for ``se3``; nothing
   for ``none``. The aligned estimate is ``R (s p) + t`` with orientation ``R R_est``.
3. ATE (evo's APE, translation part): ``e_i = |p_gt,i - p_est,i|`` after alignment, metres;
   statistics RMSE, mean, median, std (population), min, max.
4. RPE over consecutive pairs ``(i, i + delta)``, i = 0, delta, 2 delta, ... of the matched
   (and aligned) poses: ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with Q ground truth, P estimate;
   translation ``|t(E)|`` in metres, rotation ``angle(R(E))`` in degrees (Sturm et al., IROS 2012).
   RPE does not change under an SE(3) alignment; Sim(3) rescales the estimate's translations.
5. Path length: ``sum_i |p_i+1 - p_i|`` over the matched poses, of the aligned estimate and of the
   ground truth (evo_traj's ``path length``). Jitter and jumps (a loop correction's step) lengthen the
   estimate's path; ATE barely sees them when they are small.

Poses are camera-to-world ``T_wc`` (docs/design.md). Everything is float64 numpy.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mipslam.errors import EvaluationError
from mipslam.geometry import rotation_angle
from mipslam.io.tum import Trajectory

logger = logging.getLogger(__name__)

ALIGNMENTS = ("se3", "sim3", "none")
ASSOCIATIONS = ("timestamp", "index")
MIN_MATCHED_POSES = 3
DEFAULT_MAX_DIFF_S = 0.02


# ----------------------------------------------------------------------------- association


@dataclass(frozen=True, eq=False)
class Association:
    """Which ground-truth pose goes with which estimated pose.

    gt_indices, est_indices: matched pairs, in the order evo produces them   # [M] int64 each
    method: "timestamp" or "index"; max_diff_s: tolerance in seconds (None for "index")
    """

    gt_indices: np.ndarray
    est_indices: np.ndarray
    method: str
    max_diff_s: float | None

    def __len__(self) -> int:
        return int(self.gt_indices.shape[0])


def _nearest_time_matches(stamps_short: np.ndarray, stamps_long: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """For each stamp of ``stamps_short`` the nearest stamp of ``stamps_long`` within ``max_diff``.

    stamps_short [S], stamps_long [L] seconds -> (short indices [M], long indices [M]), M <= S.
    Reproduces evo's ``sync.matching_time_indices`` decision for decision: for sorted
    ``stamps_long`` a binary search where the later neighbour wins only when strictly closer;
    otherwise a linear search taking the first minimum.
    """
    if stamps_long.size == 0 or stamps_short.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not np.all(np.diff(stamps_long) >= 0):
        logger.warning("timestamps are not sorted; using linear nearest-time matching")
        diffs = np.abs(stamps_long[None, :] - stamps_short[:, None])  # [S, L]
        nearest = np.argmin(diffs, axis=1)  # first minimum, as np.argmin in evo
        keep = diffs[np.arange(stamps_short.size), nearest] <= max_diff
        return np.flatnonzero(keep).astype(np.int64), nearest[keep].astype(np.int64)

    in_range = (stamps_short >= stamps_long[0] - max_diff) & (stamps_short <= stamps_long[-1] + max_diff)
    upper = np.minimum(np.searchsorted(stamps_long, stamps_short, side="right"), stamps_long.size - 1)  # [S]
    diff_upper = stamps_long[upper] - stamps_short  # may be negative when clamped at the end (as in evo)
    diff_lower = np.where(upper > 0, stamps_short - stamps_long[np.maximum(upper - 1, 0)], np.inf)
    take_upper = (diff_upper <= max_diff) & (diff_upper < diff_lower)
    take_lower = ~take_upper & (diff_lower <= max_diff) & (diff_lower <= diff_upper)
    keep = in_range & (take_upper | take_lower)
    long_index = np.where(take_upper, upper, upper - 1)
    return np.flatnonzero(keep).astype(np.int64), long_index[keep].astype(np.int64)


def associate_by_timestamp(
    gt_timestamps: np.ndarray, est_timestamps: np.ndarray, max_diff: float = DEFAULT_MAX_DIFF_S
) -> Association:
    """Nearest-timestamp association exactly as evo's ``associate_trajectories(gt, est, max_diff=...)``.

    gt_timestamps [N] s, est_timestamps [K] s. evo walks the shorter trajectory (the estimate when
    both are equally long), so each estimated pose is used at most once when K <= N.
    """
    if not max_diff >= 0:
        raise EvaluationError(f"association tolerance max_diff must be >= 0 seconds, got {max_diff}")
    gt_timestamps = np.asarray(gt_timestamps, dtype=np.float64).reshape(-1)
    est_timestamps = np.asarray(est_timestamps, dtype=np.float64).reshape(-1)
    est_longer = est_timestamps.size > gt_timestamps.size  # evo: "second_longer"
    if est_longer:
        gt_indices, est_indices = _nearest_time_matches(gt_timestamps, est_timestamps, max_diff)
    else:
        est_indices, gt_indices = _nearest_time_matches(est_timestamps, gt_timestamps, max_diff)
    return Association(gt_indices, est_indices, "timestamp", float(max_diff))


def associate_by_index(num_gt: int, num_est: int) -> Association:
    """Pose i with pose i (Replica: ground truth without timestamps). Both counts must be equal."""
    if num_gt != num_est:
        raise EvaluationError(
            f"association by index needs as many estimated poses as ground-truth poses, got {num_est} estimated "
            f"and {num_gt} ground truth; write the ground truth of exactly the evaluated frames (the run folder's "
            "traj_gt.txt) or associate by timestamp"
        )
    indices = np.arange(num_gt, dtype=np.int64)
    return Association(indices, indices.copy(), "index", None)


# ----------------------------------------------------------------------------- alignment


@dataclass(frozen=True, eq=False)
class Alignment:
    """A similarity ``x -> scale * rotation @ x + translation`` taking estimate coordinates to ground truth.

    rotation [3, 3], translation [3] metres, scale (1 for SE(3)); method "se3" | "sim3" | "none".
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float
    method: str

    @staticmethod
    def identity() -> "Alignment":
        return Alignment(np.eye(3), np.zeros(3), 1.0, "none")

    def matrix(self) -> np.ndarray:
        """The 4x4 similarity ``[[s R, t], [0, 1]]``.  -> [4, 4]"""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def apply(self, T_wc: np.ndarray) -> np.ndarray:
        """Aligned poses: position ``R (s p) + t``, orientation ``R R_wc`` (still rigid).  [N, 4, 4] -> [N, 4, 4]"""
        out = np.array(T_wc, dtype=np.float64, copy=True)
        out[:, :3, 3] = (self.scale * out[:, :3, 3]) @ self.rotation.T + self.translation
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        return out


def umeyama_alignment(source_points: np.ndarray, target_points: np.ndarray, with_scale: bool) -> Alignment:
    """Least-squares similarity (or rigid) transform taking ``source_points`` onto ``target_points``.

    source_points [N, 3], target_points [N, 3] (metres) -> Alignment minimising
    ``sum_i |target_i - (s R source_i + t)|^2``. Umeyama (1991), eqs. 34-43:
    ``Sigma = 1/N sum (y_i - mu_y)(x_i - mu_x)^T = U D V^T``, ``S = diag(1, 1, det(U) det(V) < 0 ? -1 : 1)``,
    ``R = U S V^T``, ``s = tr(D S) / sigma_x^2``, ``t = mu_y - s R mu_x``.
    Raises EvaluationError when the covariance has rank < 2 (all points equal or on one line),
    where the rotation is not determined.
    """
    x = np.asarray(source_points, dtype=np.float64)
    y = np.asarray(target_points, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise EvaluationError(f"alignment needs two [N, 3] point sets of equal shape, got {x.shape} and {y.shape}")
    mean_x, mean_y = x.mean(0), y.mean(0)
    x_centred, y_centred = x - mean_x, y - mean_y
    variance_x = float((x_centred**2).sum()) / x.shape[0]
    covariance = y_centred.T @ x_centred / x.shape[0]  # [3, 3]
    u, d, vt = np.linalg.svd(covariance)
    if np.count_nonzero(d > np.finfo(np.float64).eps) < 2:
        raise EvaluationError(
            f"cannot align: the {x.shape[0]} matched positions are (nearly) all equal or collinear, so the rotation "
            "is not determined (singular values of the cross-covariance: "
            f"{', '.join(f'{v:.3g}' for v in d)}); evaluate this trajectory with alignment='none'"
        )
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0  # reflection fix: keep a proper rotation
    rotation = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s) / variance_x) if with_scale else 1.0
    translation = mean_y - scale * rotation @ mean_x
    return Alignment(rotation, translation, scale, "sim3" if with_scale else "se3")


# ----------------------------------------------------------------------------- metrics


@dataclass(frozen=True)
class ErrorStatistics:
    """Summary of per-pose errors (evo's statistics; std is the population standard deviation)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int
    unit: str

    @staticmethod
    def from_errors(errors: np.ndarray, unit: str) -> "ErrorStatistics":
        """errors [M] (M >= 1) -> statistics."""
        errors = np.asarray(errors, dtype=np.float64)
        return ErrorStatistics(
            rmse=math.sqrt(float(np.mean(errors**2))),
            mean=float(np.mean(errors)),
            median=float(np.median(errors)),
            std=float(np.std(errors)),
            min=float(np.min(errors)),
            max=float(np.max(errors)),
            count=int(errors.size),
            unit=unit,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "unit": self.unit, "rmse": self.rmse, "mean": self.mean, "median": self.median, "std": self.std,
            "min": self.min, "max": self.max, "count": self.count,
        }


def absolute_trajectory_errors(gt_T_wc: np.ndarray, est_T_wc_aligned: np.ndarray) -> np.ndarray:
    """Translational ATE per matched pose, metres.  gt_T_wc [M, 4, 4], est_T_wc_aligned [M, 4, 4] -> [M]"""
    return np.linalg.norm(gt_T_wc[:, :3, 3] - est_T_wc_aligned[:, :3, 3], axis=1)


def _inverse_times(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """``T_a^-1 T_b`` for rigid transforms (R^T, no matrix inversion).  [K, 4, 4] x [K, 4, 4] -> [K, 4, 4]"""
    R_a_t = np.swapaxes(T_a[:, :3, :3], 1, 2)
    out = np.tile(np.eye(4), (T_a.shape[0], 1, 1))
    out[:, :3, :3] = R_a_t @ T_b[:, :3, :3]
    out[:, :3, 3] = (R_a_t @ (T_b[:, :3, 3] - T_a[:, :3, 3])[:, :, None])[:, :, 0]
    return out


def path_length(positions: np.ndarray) -> float:
    """Summed distance between consecutive positions [N, 3] (metres)."""
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) if len(positions) > 1 else 0.0


def rpe_pairs(num_poses: int, delta: int) -> tuple[np.ndarray, np.ndarray]:
    """evo's consecutive pairs for ``--delta_unit f``: (0, d), (d, 2d), ...  -> (first [K], second [K])"""
    starts = np.arange(0, num_poses, delta, dtype=np.int64)
    return starts[:-1], starts[1:]


def relative_pose_errors(gt_T_wc: np.ndarray, est_T_wc: np.ndarray, delta: int) -> tuple[np.ndarray, np.ndarray]:
    """RPE per consecutive pair of matched poses.

    gt_T_wc [M, 4, 4], est_T_wc [M, 4, 4] (matched, in order) -> (translation errors [K] metres,
    rotation errors [K] degrees), ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` over :func:`rpe_pairs`.
    """
    first, second = rpe_pairs(gt_T_wc.shape[0], delta)
    gt_relative = _inverse_times(gt_T_wc[first], gt_T_wc[second])  # [K, 4, 4]
    est_relative = _inverse_times(est_T_wc[first], est_T_wc[second])  # [K, 4, 4]
    return pose_errors(gt_relative, est_relative)


def pose_errors(T_true: np.ndarray, T_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (metres) and rotation angle (degrees) of ``E = T_true^-1 T_est`` per pair of rigid transforms.
    T_true [K, 4, 4], T_est [K, 4, 4] -> ([K], [K])"""
    error = _inverse_times(T_true, T_est)  # [K, 4, 4]
    translation_errors = np.linalg.norm(error[:, :3, 3], axis=1)
    angles_rad = rotation_angle(torch.tensor(error[:, :3, :3])).numpy()
    return translation_errors, np.degrees(angles_rad)


def poses_at_stamps(trajectory: Trajectory, stamps: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """The poses of ``trajectory`` nearest in time to ``stamps`` [S] (seconds), within ``max_diff``, matched as
    :func:`associate_by_timestamp` matches. -> (found [S] bool, T_wc [S, 4, 4], identity where not found)"""
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    matched, index = _nearest_time_matches(stamps, trajectory.timestamps, max_diff)
    found = np.zeros(stamps.shape[0], dtype=bool)
    found[matched] = True
    T_wc = np.tile(np.eye(4), (stamps.shape[0], 1, 1))
    T_wc[matched] = trajectory.T_wc[index]
    return found, T_wc


@dataclass(frozen=True, eq=False)
class TrajectoryMetrics:
    """ATE and RPE of an estimated trajectory against ground truth, with the protocol that produced them.

    ate: translational absolute error after alignment (metres)
    rpe_translation (metres), rpe_rotation (degrees): over ``rpe_delta`` matched frames
    ate_errors: per matched pose, metres                     # [M]
    matched_est_timestamps, matched_gt_timestamps: seconds    # [M] each
    path_length_est_m, path_length_gt_m: summed distance between consecutive matched positions, the estimate
        after alignment (evo_traj's path length); an estimate much longer than the ground truth jitters or jumps
    """

    ate: ErrorStatistics
    rpe_translation: ErrorStatistics
    rpe_rotation: ErrorStatistics
    alignment: Alignment
    association: Association
    rpe_delta: int
    num_est_poses: int
    num_gt_poses: int
    est_time_range_s: tuple[float, float]
    gt_time_range_s: tuple[float, float]
    ate_errors: np.ndarray
    matched_est_timestamps: np.ndarray
    matched_gt_timestamps: np.ndarray
    path_length_est_m: float = 0.0
    path_length_gt_m: float = 0.0

    @property
    def num_matched(self) -> int:
        return len(self.association)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary for metrics.json that states the protocol (plain floats, ints, lists)."""
        if self.association.method == "timestamp":
            association_rule = (
                "nearest timestamp within max_diff_s, as evo's sync.associate_trajectories (nearest_time): "
                "walks the trajectory with fewer poses; on a tie the earlier stamp wins"
            )
        else:
            association_rule = "pose i of the estimate with pose i of the ground truth"
        alignment_text = {
            "se3": "Umeyama/Horn closed form on matched positions, rotation and translation (evo_ape -a)",
            "sim3": "Umeyama closed form on matched positions, rotation, translation and scale (evo_ape -as)",
            "none": "no alignment: estimate compared in its own world frame",
        }[self.alignment.method]
        evo_flags = {"se3": " -a", "sim3": " -as", "none": ""}[self.alignment.method]
        evo_sync = f" --t_max_diff {self.association.max_diff_s}" if self.association.method == "timestamp" else ""
        return {
            "protocol": {
                "poses": "T_wc camera-to-world; positions in metres; files in TUM order (timestamp tx ty tz qx qy qz qw)",
                "association": {
                    "method": self.association.method,
                    "max_diff_s": self.association.max_diff_s,
                    "rule": association_rule,
                },
                "alignment": {
                    "method": self.alignment.method,
                    "description": alignment_text,
                    "maps": "estimate to ground truth: p_gt ~ scale * rotation @ p_est + translation",
                    "rotation": self.alignment.rotation.tolist(),
                    "translation_m": self.alignment.translation.tolist(),
                    "scale": self.alignment.scale,
                },
                "num_est_poses": self.num_est_poses,
                "num_gt_poses": self.num_gt_poses,
                "num_matched": self.num_matched,
                "frames": {
                    "est_time_range_s": list(self.est_time_range_s),
                    "gt_time_range_s": list(self.gt_time_range_s),
                    "matched_est_indices": self.association.est_indices.tolist(),
                    "matched_gt_indices": self.association.gt_indices.tolist(),
                },
                "rpe": {
                    "delta": self.rpe_delta,
                    "delta_unit": "frames (matched poses)",
                    "pairs": "consecutive: (0, delta), (delta, 2 delta), ...",
                    "error": "E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) on the aligned estimate; |t(E)| m, angle(R(E)) deg",
                },
                "equivalent_evo": (
                    f"evo_ape tum GT EST{evo_flags}{evo_sync}; "
                    f"evo_rpe tum GT EST{evo_flags}{evo_sync} --delta {self.rpe_delta} --delta_unit f "
                    "(and --pose_relation angle_deg)"
                ),
            },
            "ate": self.ate.to_dict(),
            "rpe_translation": self.rpe_translation.to_dict(),
            "rpe_rotation": self.rpe_rotation.to_dict(),
            "path_length": {
                "unit": "m",
                "estimate": self.path_length_est_m,
                "ground_truth": self.path_length_gt_m,
                "ratio": (self.path_length_est_m / self.path_length_gt_m) if self.path_length_gt_m > 0 else None,
                "meaning": "summed distance between consecutive matched positions, the estimate after alignment "
                           "(evo_traj's path length); a ratio well above 1: the estimate jitters or jumps",
            },
        }


def _format_range(trajectory: Trajectory) -> str:
    first, last = trajectory.time_range
    return f"[{first:.6f}, {last:.6f}] s ({len(trajectory)} poses)"


def _check_finite(trajectory: Trajectory, role: str) -> None:
    bad = np.flatnonzero(~np.isfinite(trajectory.T_wc).reshape(len(trajectory), -1).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise EvaluationError(
            f"{role} pose {i} (t={trajectory.timestamps[i]:.6f} s) is not finite ({bad.size} such poses); "
            "the estimate diverged or the file is corrupt"
        )


def evaluate_trajectory(
    gt: Trajectory,
    est: Trajectory,
    *,
    alignment: str = "se3",
    association: str = "timestamp",
    max_diff: float = DEFAULT_MAX_DIFF_S,
    rpe_delta: int = 1,
) -> TrajectoryMetrics:
    """ATE and RPE of ``est`` against ``gt`` (see the module docstring for the exact protocol).

    alignment: "se3" (default, ``evo_ape -a``), "sim3" (``-as``, monocular) or "none".
    association: "timestamp" (nearest within ``max_diff`` seconds) or "index" (Replica).
    rpe_delta: frame distance of the RPE pairs, counted in matched poses.
    Raises EvaluationError when fewer than 3 poses match (the message gives both time ranges so a
    clock offset shows), when the positions cannot be aligned, or for non-finite poses.
    """
    if alignment not in ALIGNMENTS:
        raise EvaluationError(f"unknown alignment '{alignment}'; choose one of {', '.join(ALIGNMENTS)}")
    if association not in ASSOCIATIONS:
        raise EvaluationError(f"unknown association '{association}'; choose one of {', '.join(ASSOCIATIONS)}")
    if isinstance(rpe_delta, bool) or int(rpe_delta) != rpe_delta or rpe_delta < 1:
        raise EvaluationError(f"rpe_delta must be a positive whole number of frames, got {rpe_delta}")
    rpe_delta = int(rpe_delta)
    _check_finite(gt, "ground-truth")
    _check_finite(est, "estimated")

    if association == "timestamp":
        matches = associate_by_timestamp(gt.timestamps, est.timestamps, max_diff)
    else:
        matches = associate_by_index(len(gt), len(est))
    if len(matches) < MIN_MATCHED_POSES:
        how = f"by timestamp within {max_diff} s" if association == "timestamp" else "by index"
        raise EvaluationError(
            f"only {len(matches)} pose(s) matched {how}; at least {MIN_MATCHED_POSES} are needed. "
            f"Estimate: {_format_range(est)}; ground truth: {_format_range(gt)}. If the ranges are shifted by a "
            "constant the clocks differ; if the estimate's timestamps are frame numbers use association by index"
        )

    gt_matched = gt.T_wc[matches.gt_indices]  # [M, 4, 4]
    est_matched = est.T_wc[matches.est_indices]  # [M, 4, 4]
    if alignment == "none":
        fitted = Alignment.identity()
    else:
        fitted = umeyama_alignment(est_matched[:, :3, 3], gt_matched[:, :3, 3], with_scale=alignment == "sim3")
    est_aligned = fitted.apply(est_matched)

    ate_errors = absolute_trajectory_errors(gt_matched, est_aligned)
    if rpe_delta >= len(matches):
        raise EvaluationError(
            f"rpe_delta={rpe_delta} frames leaves no pose pair among the {len(matches)} matched poses; "
            "choose a smaller delta"
        )
    rpe_translation, rpe_rotation_deg = relative_pose_errors(gt_matched, est_aligned, rpe_delta)
    metrics = TrajectoryMetrics(
        ate=ErrorStatistics.from_errors(ate_errors, "m"),
        rpe_translation=ErrorStatistics.from_errors(rpe_translation, "m"),
        rpe_rotation=ErrorStatistics.from_errors(rpe_rotation_deg, "deg"),
        alignment=fitted,
        association=matches,
        rpe_delta=rpe_delta,
        num_est_poses=len(est),
        num_gt_poses=len(gt),
        est_time_range_s=est.time_range,
        gt_time_range_s=gt.time_range,
        ate_errors=ate_errors,
        matched_est_timestamps=est.timestamps[matches.est_indices],
        matched_gt_timestamps=gt.timestamps[matches.gt_indices],
        path_length_est_m=path_length(est_aligned[:, :3, 3]),
        path_length_gt_m=path_length(gt_matched[:, :3, 3]),
    )
    logger.debug(
        "ATE RMSE %.6f m over %d matched poses (%s alignment, %s association); RPE %.6f m / %.4f deg",
        metrics.ate.rmse, metrics.num_matched, alignment, association,
        metrics.rpe_translation.rmse, metrics.rpe_rotation.rmse,
    )
    return metrics
