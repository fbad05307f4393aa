"""What the viewer draws, as plain CPU arrays: one :class:`SceneSnapshot` per update.

A snapshot is built either from a live run (:mod:`mipslam.viewer.live`, from tensors the frame
loop handed over) or from a finished run folder (:func:`snapshot_from_run_dir`). It holds copies,
never references into the run's state, so the run may change its tensors at once. World frame and
poses as everywhere in mipslam: ``T_wc`` camera-to-world, OpenCV camera axes, metres.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mipslam.errors import DatasetError, EvaluationError, MipslamError
from mipslam.types import Intrinsics


@dataclass(frozen=True)
class Splats:
    """The map's Gaussians, activated (what a splat renderer draws).

    means [N, 3] world metres; covariances [N, 3, 3] m^2 (``R diag(s^2) R^T``);
    colors [N, 3] RGB in [0, 1]; opacities [N] in [0, 1]. All float32.
    """

    means: np.ndarray
    covariances: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @classmethod
    def empty(cls) -> "Splats":
        return cls(np.zeros((0, 3), np.float32), np.zeros((0, 3, 3), np.float32), np.zeros((0, 3), np.float32),
                   np.zeros(0, np.float32))

    @classmethod
    def from_activated(cls, means, quats_wxyz, scales, colors, opacities) -> "Splats":
        """From activated parameters (numpy or CPU tensors): quats_wxyz [N, 4] (normalised here),
        scales [N, 3] std-devs in metres, colors [N, 3], opacities [N]."""
        means, quats, scales, colors, opacities = (np.asarray(v, dtype=np.float32) for v in
                                                   (means, quats_wxyz, scales, colors, opacities))
        rotations = quaternion_wxyz_to_matrix(quats)  # [N, 3, 3]
        covariances = (rotations * (scales**2)[:, None, :]) @ rotations.transpose(0, 2, 1)
        return cls(np.ascontiguousarray(means), covariances.astype(np.float32), np.clip(colors, 0.0, 1.0),
                   np.clip(opacities.reshape(-1), 0.0, 1.0))


@dataclass(frozen=True)
class Headline:
    """The numbers the viewer shows above everything else."""

    frame: int  # frames processed so far
    total_frames: int  # frames in the sequence (0 = unknown, e.g. a live camera)
    frames_per_second: float | None  # processing rate of the run (None = unknown)
    gaussians: int
    keyframes: int
    ate_rmse_m: float | None = None  # SE(3)-aligned ATE RMSE where ground truth is known
    finished: bool = False

    def markdown(self) -> str:
        frames = f"{self.frame} / {self.total_frames}" if self.total_frames else f"{self.frame}"
        parts = [f"**frame** {frames}"]
        if self.frames_per_second is not None and math.isfinite(self.frames_per_second):
            parts.append(f"**frames/s** {self.frames_per_second:.2f}")
        parts += [f"**Gaussians** {self.gaussians:,}", f"**keyframes** {self.keyframes}"]
        if self.ate_rmse_m is not None:
            parts.append(f"**ATE** {self.ate_rmse_m * 100:.2f} cm")
        if self.finished:
            parts.append("(finished)")
        return " · ".join(parts)


@dataclass(frozen=True)
class SceneSnapshot:
    """Everything one viewer update draws.

    splats: the map; est_T_wc [F, 4, 4] float64 estimated poses of the processed frames (in order);
    gt_positions [G, 3] ground-truth camera centres where known (None: no ground truth);
    keyframe_T_wc [K, 4, 4] float64; loop_edges [E, 2] int keyframe ids joined by a loop closure;
    current: position in ``est_T_wc`` of the frame shown beside the map (-1 = none);
    frame_image / rendered_image [H, W, 3] uint8: that frame and the map rendered from its estimated pose;
    intrinsics: the camera of the processed frames (None = unknown).
    """

    splats: Splats
    est_T_wc: np.ndarray
    keyframe_T_wc: np.ndarray
    headline: Headline
    gt_positions: np.ndarray | None = None
    loop_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    current: int = -1
    frame_image: np.ndarray | None = None
    rendered_image: np.ndarray | None = None
    intrinsics: Intrinsics | None = None


# ----------------------------------------------------------------------------- small geometry

def quaternion_wxyz_to_matrix(quats_wxyz: np.ndarray) -> np.ndarray:
    """Unit rotation matrices from quaternions (w, x, y, z).  [N, 4] -> [N, 3, 3] (normalised first)."""
    q = np.asarray(quats_wxyz, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of one rotation matrix R [3, 3] (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-12))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def aligned_ate_rmse(est_positions: np.ndarray, gt_positions: np.ndarray) -> float | None:
    """ATE RMSE (metres) after the rigid (SE(3)) Umeyama alignment of est [N, 3] onto gt [N, 3];
    None when fewer than 3 pairs or the positions do not fix a rotation (a line, a point)."""
    from mipslam.evaluation.trajectory import umeyama_alignment

    if len(est_positions) < 3 or len(est_positions) != len(gt_positions):
        return None
    try:
        alignment = umeyama_alignment(est_positions, gt_positions, with_scale=False)
    except EvaluationError:
        return None
    aligned = est_positions @ alignment.rotation.T + alignment.translation
    return float(np.sqrt(np.mean(np.sum((aligned - gt_positions) ** 2, axis=1))))


def to_uint8_image(color) -> np.ndarray:
    """[H, W, 3] float in [0, 1] (numpy or tensor) -> [H, W, 3] uint8."""
    array = np.asarray(color, dtype=np.float32)
    return (np.clip(array, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


# ----------------------------------------------------------------------------- a finished run

@dataclass(frozen=True)
class RecordedRun:
    """A finished run folder, read for the viewer (:func:`snapshot_from_run_dir`).

    est_timestamps [F]; keyframe_positions_in_est [K] index into the estimate of every keyframe;
    config: the run's resolved config (None when config.yaml is missing or unreadable).
    """

    run_dir: Path
    snapshot: SceneSnapshot
    est_timestamps: np.ndarray
    config: object | None
    map_file: Path | None = None  # the map shown: RUN/map.ply, or RUN/refined/map.ply of mipslam refine
    refined: bool = False  # the map (and poses) of mipslam refine

    def describe_map(self) -> str:
        """Which map is shown, in words (the viewer's log line)."""
        if self.refined:
            return (f"the refined map {self.map_file} (mipslam refine) with its poses; --slam-map shows the SLAM "
                    "map instead")
        if (self.run_dir / "refined" / "map.ply").is_file():
            return f"the SLAM map {self.map_file} (--slam-map; without it the refined map is shown)"
        return f"the SLAM map {self.map_file}"


def snapshot_from_run_dir(run_dir: str | Path, *, refined: bool = True) -> RecordedRun:
    """Read a run folder written by ``mipslam run`` (map.ply, traj_est.txt, and where present
    traj_gt.txt, keyframes.txt, loops.json, run.json, metrics.json, frames.json, config.yaml).

    ``refined``: where ``mipslam refine`` wrote ``refined/map.ply``, show that map with its poses and metrics
    (``refined/traj_est.txt``, ``keyframes.txt``, ``metrics.json``) instead of the SLAM map's.
    A missing map or trajectory raises DatasetError naming the file; the optional files are skipped
    when absent.
    """
    import torch

    from mipslam.config import config_from_dict
    from mipslam.io.ply import read_map_ply
    from mipslam.io.tum import read_tum_trajectory

    root = Path(run_dir)
    if not root.is_dir():
        raise DatasetError(root, "no such run folder; give a folder written by 'mipslam run'")
    for name in ("map.ply", "traj_est.txt"):
        if not (root / name).is_file():
            raise DatasetError(root / name, "missing; is this a finished run folder? (a run writes it at its end)")
    shown = root / "refined" if refined and (root / "refined" / "map.ply").is_file() else root

    def source(name: str) -> Path:
        """The shown map's own file where it has one (refined/), else the run's."""
        return shown / name if (shown / name).is_file() else root / name

    gaussian_map = read_map_ply(shown / "map.ply")
    with torch.no_grad():
        activated = gaussian_map.activated()
        splats = Splats.from_activated(activated.means.numpy(), activated.quats.numpy(), activated.scales.numpy(),
                                       activated.colors.numpy(), activated.opacities.numpy())
    est = read_tum_trajectory(source("traj_est.txt"))
    est_T_wc = np.asarray(est.T_wc, dtype=np.float64)
    keyframe_T_wc = np.zeros((0, 4, 4))
    if source("keyframes.txt").is_file():
        keyframe_T_wc = np.asarray(read_tum_trajectory(source("keyframes.txt")).T_wc, dtype=np.float64)
    gt_positions = None
    if (root / "traj_gt.txt").is_file():
        gt_positions = np.asarray(read_tum_trajectory(root / "traj_gt.txt", allow_duplicate_timestamps=True).positions,
                                  dtype=np.float64)
    loop_edges = np.zeros((0, 2), np.int64)
    loops = _read_json(root / "loops.json")
    if loops:
        pairs = [(row["keyframe_i"], row["keyframe_j"]) for row in loops.get("loops", []) if row.get("accepted")]
        if pairs:
            loop_edges = np.asarray(pairs, dtype=np.int64)
    info = _read_json(root / "run.json") or {}
    intrinsics = None
    camera = info.get("dataset", {}).get("intrinsics")
    if camera:
        intrinsics = Intrinsics(fx=camera["fx"], fy=camera["fy"], cx=camera["cx"], cy=camera["cy"],
                                width=int(camera["width"]), height=int(camera["height"]))
    metrics = _read_json(source("metrics.json")) or {}
    ate = (metrics.get("trajectory") or {}).get("ate") or {}
    timings = _read_json(root / "timings.json") or {}
    headline = Headline(frame=len(est), total_frames=int(info.get("dataset", {}).get("frames", len(est))),
                        frames_per_second=_frames_per_second(timings), gaussians=len(splats),
                        keyframes=len(keyframe_T_wc), ate_rmse_m=ate.get("rmse"), finished=True)
    config = None
    if (root / "config.yaml").is_file():
        import yaml

        try:
            config = config_from_dict(yaml.safe_load((root / "config.yaml").read_text(encoding="utf-8")) or {})
        except (MipslamError, yaml.YAMLError, OSError):
            config = None  # the map and trajectory still show; only re-rendering frames needs the config
    snapshot = SceneSnapshot(splats=splats, est_T_wc=est_T_wc, keyframe_T_wc=keyframe_T_wc, headline=headline,
                             gt_positions=gt_positions, loop_edges=loop_edges, current=len(est) - 1,
                             intrinsics=intrinsics)
    return RecordedRun(root, snapshot, np.asarray(est.timestamps, dtype=np.float64), config, shown / "map.ply",
                       shown != root)


def _read_json(path: Path) -> dict | None:
    """A run folder's JSON file, or None when it is absent or unreadable (these files are optional here)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _frames_per_second(timings: dict) -> float | None:
    """Frames per second of the run as timings.json states it (None where it does not)."""
    if not isinstance(timings, dict):
        return None
    for where in (timings, timings.get("summary")):
        fps = where.get("frames_per_second") if isinstance(where, dict) else None
        if isinstance(fps, (int, float)) and math.isfinite(fps):
            return float(fps)
    return None
