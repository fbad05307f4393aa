"""Odometry-only comparison of tracking front-end candidates (docs/tracking.md, "Front-end candidates").

Each candidate estimates the motion between consecutive frames (frame-to-frame, no map) and the poses are
chained from the first frame's ground truth. Reported per candidate: ATE RMSE of the chained trajectory
(SE(3) alignment), the median and 95th-percentile error of the relative pose against ground truth
(what a refinement must still correct, cm / deg), frames where the candidate reported failure (the chain
then repeats the last motion) and milliseconds per frame.

    mipslam bench --scenario frontend --set dataset.path=../shared/data/tum_fr1_rpy_300 \
        --set frontend.methods=orb_pnp,cv_rgbd,o3d_rgbd

``frontend.config`` is the sequence's config, a YAML file or a built-in's name (default: the built-in config of
the ``dataset.path`` folder's kind, as ``mipslam bench SEQUENCE`` picks it, else ``tum``), config keys
(``--set dataset.path=...``) override it; ``frontend.synth_frames=N`` runs on a data_synth sequence of N frames
generated into OUT instead.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import CONFIGS, parameters, sequence_config, synth_sequence
from mipslam.config import load_config
from mipslam.datasets import make_sequence
from mipslam.errors import MipslamError
from mipslam.evaluation.trajectory import absolute_trajectory_errors, umeyama_alignment
from mipslam.frontend import FeatureOptions, estimate_relative_pose, extract_features
from mipslam.geometry.se3 import rotation_angle

log = logging.getLogger(__name__)

METHODS = ("orb_pnp", "cv_rgbd", "cv_depth", "cv_rgb", "o3d_rgbd", "orb_o3d", "const_velocity")


@dataclass(frozen=True)
class Options:
    config: str = ""  # the sequence's config (its dataset section); "" = the built-in <kind> of dataset.path
    methods: tuple[str, ...] = ("orb_pnp", "cv_rgbd", "cv_depth", "o3d_rgbd", "orb_o3d")  # from METHODS
    synth_frames: int = 0  # > 0: a data_synth loop of this many frames (OUT/sequence) instead of the config's
    synth_size: str = "160x120"  # WIDTHxHEIGHT of that sequence
    synth_trajectory: str = "loop"  # its data_synth trajectory
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE, e.g. dataset.path=...


SMOKE = dict(config=str(CONFIGS / "synthetic.yaml"), methods=("orb_pnp", "cv_rgbd", "o3d_rgbd", "const_velocity"),
             synth_frames=8, synth_size="96x72")


def _relative_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(T_gt) @ T_est
    angle = math.degrees(float(rotation_angle(torch.from_numpy(E[:3, :3]))))
    return float(np.linalg.norm(E[:3, 3])), angle


class OrbPnP:
    def __init__(self, options: FeatureOptions):
        self.options = options

    def __call__(self, prev, cur):
        a = extract_features(prev.color, prev.depth, prev.intrinsics, self.options)
        b = extract_features(cur.color, cur.depth, cur.intrinsics, self.options)
        result = estimate_relative_pose(a, b, cur.intrinsics, self.options)
        return result.T_rc.numpy(), result.ok


class CvOdometry:
    """OpenCV 5 ``cv2.Odometry`` (the 3d module's RGB-D / ICP odometry)."""

    def __init__(self, kind: str):
        self.kind = {"rgb": cv2.OdometryType_RGB, "depth": cv2.OdometryType_DEPTH,
                     "rgbd": cv2.OdometryType_RGB_DEPTH}[kind]
        self.odometry = None

    def __call__(self, prev, cur):
        if self.odometry is None:
            settings = cv2.OdometrySettings()
            i = cur.intrinsics
            settings.setCameraMatrix(np.array([[i.fx, 0, i.cx], [0, i.fy, i.cy], [0, 0, 1]], np.float32))
            self.odometry = cv2.Odometry(self.kind, settings, cv2.OdometryAlgoType_COMMON)
        grey = [np.clip(f.color.numpy() @ np.array([0.299, 0.587, 0.114], np.float32) * 255, 0, 255).astype(np.uint8)
                for f in (prev, cur)]
        depth = [f.depth.numpy().astype(np.float32) for f in (prev, cur)]
        Rt = np.eye(4)
        if self.kind == cv2.OdometryType_DEPTH:
            ok, Rt = self.odometry.compute(depth[0], depth[1], Rt)
        else:
            ok, Rt = self.odometry.compute(depth[0], grey[0], depth[1], grey[1], Rt)
        # Rt * src = dst: maps previous-camera points into the current camera (T_cur_prev)
        return np.linalg.inv(Rt), bool(ok)


class O3dOdometry:
    def __init__(self, init: OrbPnP | None = None):
        from mipslam.loop.registration import RegistrationOptions
        self.options = RegistrationOptions(method="rgbd_odometry", pixel_stride=1, min_points=100,
                                           max_correction_m=1.0, max_correction_deg=45.0)
        self.init = init

    def __call__(self, prev, cur):
        from mipslam.loop.registration import register_rgbd_odometry
        guess = torch.eye(4, dtype=torch.float64)
        if self.init is not None:
            T, ok = self.init(prev, cur)
            if ok:
                guess = torch.from_numpy(T)
        result = register_rgbd_odometry(prev.color, prev.depth, cur.color, cur.depth, cur.intrinsics, guess,
                                        self.options)
        return result.T_ij.numpy(), bool(result.accepted)


class ConstantVelocity:
    """The motion model's best case: the previous frame pair's ground-truth motion repeated."""

    def __init__(self, gt: np.ndarray):
        self.gt = gt

    def __call__(self, prev, cur):
        k = prev.index
        if k == 0:
            return np.eye(4), True
        return np.linalg.inv(self.gt[k - 1]) @ self.gt[k], True


def run(options: Options, out_dir: Path) -> ScenarioResult:
    unknown = [m for m in options.methods if m not in METHODS]
    if unknown:
        raise MipslamError(f"frontend.methods: unknown {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    overrides = list(options.config_overrides)
    if options.synth_frames > 0:
        sequence_dir = synth_sequence(out_dir, options.synth_size, options.synth_frames,
                                      trajectory=options.synth_trajectory)
        overrides.insert(0, f"dataset.path={sequence_dir}")
    config = load_config(sequence_config(options.config, overrides), overrides=overrides)
    sequence = make_sequence(config.dataset)
    frames = [sequence[i] for i in range(len(sequence))]
    gt = sequence.gt_T_wc.numpy()
    orb = OrbPnP(FeatureOptions())
    methods = {"orb_pnp": orb, "cv_rgbd": CvOdometry("rgbd"), "cv_depth": CvOdometry("depth"),
               "cv_rgb": CvOdometry("rgb"), "o3d_rgbd": O3dOdometry(), "orb_o3d": O3dOdometry(orb),
               "const_velocity": ConstantVelocity(gt)}
    rows = {}
    for name in options.methods:
        method = methods[name]
        poses = [gt[0]]
        motion = np.eye(4)
        failed, seconds, cpu_seconds, trans_err, rot_err = 0, 0.0, 0.0, [], []
        for k in range(1, len(frames)):
            start, cpu_start = time.perf_counter(), time.process_time()
            T_pc, ok = method(frames[k - 1], frames[k])
            seconds += time.perf_counter() - start
            cpu_seconds += time.process_time() - cpu_start
            if not ok or not np.isfinite(T_pc).all():
                failed += 1
                T_pc = motion
            motion = T_pc
            poses.append(poses[-1] @ T_pc)
            t_err, r_err = _relative_error(T_pc, np.linalg.inv(gt[k - 1]) @ gt[k])
            trans_err.append(t_err * 100)
            rot_err.append(r_err)
        est = np.stack(poses)
        fit = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
        ate = float(np.sqrt(np.mean(absolute_trajectory_errors(gt, fit.apply(est)) ** 2)))
        rows[name] = {"ate_cm": ate * 100, "failed": failed, "ms_per_frame": 1000 * seconds / (len(frames) - 1),
                      "cpu_ms_per_frame": 1000 * cpu_seconds / (len(frames) - 1),
                      "rel_t_cm_median": float(np.median(trans_err)), "rel_t_cm_p95": float(np.percentile(trans_err, 95)),
                      "rel_r_deg_median": float(np.median(rot_err)), "rel_r_deg_p95": float(np.percentile(rot_err, 95))}
        log.info("%s done: %s", name, rows[name])
    lines = [f"**{config.dataset.path}**, {len(frames)} frames, frame-to-frame", "",
             "| method | ATE [cm] | failed | ms/frame (CPU) | rel. t median / p95 [cm] | rel. r median / p95 [deg] |",
             "|---|---:|---:|---:|---:|---:|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['ate_cm']:.2f} | {r['failed']} | {r['ms_per_frame']:.1f} "
                     f"({r['cpu_ms_per_frame']:.1f}) | {r['rel_t_cm_median']:.2f} / {r['rel_t_cm_p95']:.2f} | "
                     f"{r['rel_r_deg_median']:.2f} / {r['rel_r_deg_p95']:.2f} |")
    report = "\n".join(lines)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), rows, threads=torch.get_num_threads(),
                            markdown=report)
    return ScenarioResult(files, report)
