"""Write a procedural sequence as a Replica (NICE-SLAM) or TUM RGB-D folder plus ``synth.json``.

Contract with ``mipslam.datasets`` (the reader):

- Replica: ``results/frame%06d.png`` (8-bit RGB, lossless), ``results/depth%06d.png`` (uint16,
  metres * 6553.5), ``traj.txt`` (16 numbers a line, row-major camera-to-world),
  ``cam_params.json`` = ``{"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}``.
- TUM: ``rgb.txt``, ``depth.txt`` (``timestamp filename`` after ``#`` comments),
  ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world),
  ``rgb/<timestamp>.png``, ``depth/<timestamp>.png`` (uint16, metres * 5000); timestamps
  ``1000.0 + i / 30`` with 6 decimals, the same for rgb, depth and ground truth.
- ``synth.json``: format_version, generator, layout, trajectory, seed, frames, intrinsics,
  depth_scale, fps, scene (everything :func:`data_synth.load_scene` needs), sensor; plus
  ``trajectory_options`` ({"laps"}; a replayed file: {"file", "start_s"}), ``render``
  ({"supersample", "fov_deg", "motion_blur", "blur_samples", "depth_delay", "rolling_shutter"}) and, for a replayed file (``trajectory``
  "file"), ``poses``: every frame's camera-to-world pose, 16 numbers row-major, exact float64.
- Depth is camera-frame z in metres, 0 = no measurement; poses camera-to-world, OpenCV axes.

``synth.json`` is written last: a folder without it is an interrupted generation.
"""
from __future__ import annotations

import difflib
import json
import logging
import math
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from data_synth.render import MAX_SUPERSAMPLE, render_view
from data_synth.scene import Scene, make_scene
from data_synth.sensor import SensorOptions, apply_depth_effects, apply_exposure, exposure_parameters
from data_synth.trajectories import TRAJECTORIES, exposure_poses, pose_at, replay_poses, trajectory_poses
from mipslam.errors import ConfigError, DatasetError
from mipslam.geometry import quat_wxyz_to_xyzw, rotmat_to_quat_wxyz
from mipslam.types import Intrinsics

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
GENERATOR = "data_synth"
LAYOUTS = ("replica", "tum")
DEPTH_SCALE = {"replica": 6553.5, "tum": 5000.0}
FPS = 30.0
TUM_TIME_ORIGIN = 1000.0
DEFAULT_FOV_DEG = 70.0
REPLAYED = "file"  # synth.json's trajectory name for a replayed trajectory file
_WRITTEN_FILES = ("traj.txt", "cam_params.json", "rgb.txt", "depth.txt", "groundtruth.txt", "synth.json")
_WRITTEN_DIRS = ("results", "rgb", "depth")


def default_intrinsics(width: int, height: int, fov_deg: float = DEFAULT_FOV_DEG) -> Intrinsics:
    """Square pixels, horizontal field of view ``fov_deg``, principal point at the image centre
    (``(W - 1) / 2``, ``(H - 1) / 2`` with pixel centres at integers)."""
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Intrinsics(fx=focal, fy=focal, cx=(width - 1) / 2, cy=(height - 1) / 2, width=int(width), height=int(height))


def tum_timestamp(index: float) -> str:
    """Timestamp of frame ``index`` as written: ``1000.0 + i / 30`` with 6 decimals (a depth image taken
    ``depth_delay`` frame intervals later: ``index + depth_delay``)."""
    return f"{TUM_TIME_ORIGIN + index / FPS:.6f}"


def _require_int(name: str, value: Any, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
        raise ConfigError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    return int(value)


def _require_float(name: str, value: Any, low: float, high: float, *, high_open: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    upper_ok = number < high if high_open else number <= high
    if not (math.isfinite(number) and number >= low and upper_ok):
        bracket = ")" if high_open else "]"
        raise ConfigError(f"{name} must be in [{low}, {high}{bracket}, got {value!r}")
    return number


def _choice(name: str, value: Any, choices: Sequence[str]) -> str:
    if value not in choices:
        near = difflib.get_close_matches(str(value), choices, n=1)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise ConfigError(f"unknown {name} '{value}'{hint}; choose one of: {', '.join(choices)}")
    return str(value)


def _prepare_folder(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output path {out} exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()):
        if not (overwrite and ((out / "synth.json").is_file() or _looks_generated(out))):
            raise ConfigError(f"output folder {out} is not empty; choose a new --out or delete the folder"
                              + ("" if overwrite else " (overwrite=True replaces an earlier data_synth folder)"))
        for name in _WRITTEN_DIRS:
            if (out / name).is_dir():
                shutil.rmtree(out / name)
        for name in _WRITTEN_FILES:
            (out / name).unlink(missing_ok=True)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DatasetError(out, f"cannot create the output folder: {error}") from error


def _looks_generated(out: Path) -> bool:
    """An interrupted data_synth folder: only the files and folders this writer makes."""
    return all(p.name in _WRITTEN_FILES or p.name in _WRITTEN_DIRS for p in out.iterdir())


def _write_png(path: Path, image: np.ndarray) -> None:
    try:
        ok = cv2.imwrite(str(path), image)
    except cv2.error as error:
        raise DatasetError(path, f"cannot write the image: {error}") from error
    if not ok:
        raise DatasetError(path, "cannot write the image (is the folder writable and the disk not full?)")


def _write_text(path: Path, text: str) -> None:
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as error:
        raise DatasetError(path, f"cannot write: {error}") from error


def color_to_uint8_bgr(color: np.ndarray) -> np.ndarray:
    """color [H, W, 3] float in [0, 1], RGB -> [H, W, 3] uint8 BGR (OpenCV's order), rounded."""
    return np.round(np.clip(color, 0.0, 1.0) * 255.0).astype(np.uint8)[..., ::-1]


def depth_to_uint16(depth: np.ndarray, scale: float) -> np.ndarray:
    """depth [H, W] metres -> [H, W] uint16 ``round(z * scale)``; 0 (no measurement) where z <= 0
    or beyond the uint16 range."""
    q = np.round(depth.astype(np.float64) * scale)
    q[(depth <= 0) | (q > 65535)] = 0
    return q.astype(np.uint16)


def _quaternions_xyzw(poses: np.ndarray) -> np.ndarray:
    """Rotation blocks as unit quaternions in TUM order.  poses [N, 4, 4] -> [N, 4] (qx qy qz qw), qw >= 0"""
    q_wxyz = rotmat_to_quat_wxyz(torch.from_numpy(np.ascontiguousarray(poses[:, :3, :3])))
    return quat_wxyz_to_xyzw(q_wxyz).numpy()


ROLLING_SHUTTER_BANDS = 16


def _moving_camera_color(scene: Scene, poses: np.ndarray, index: int, intrinsics: Intrinsics, supersample: int,
                         motion_blur: float, blur_samples: int, rolling_shutter: float) -> np.ndarray:
    """Frame ``index``'s colour [H, W, 3] seen by a moving camera: each band of rows (one band for a global
    shutter) at its read-out time, ``(band centre / H - 0.5) * rolling_shutter`` frame intervals from the frame's,
    averaged over the exposure's poses around that time (motion blur)."""
    H = intrinsics.height
    bands = ROLLING_SHUTTER_BANDS if rolling_shutter > 0 else 1
    samples = blur_samples if motion_blur > 0 else 1
    color = np.zeros((H, intrinsics.width, 3), dtype=np.float32)
    for b in range(bands):
        r0, r1 = b * H // bands, (b + 1) * H // bands
        if r1 <= r0:
            continue
        band = Intrinsics(fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy - r0,
                          width=intrinsics.width, height=r1 - r0)
        readout = (0.5 * (r0 + r1) / H - 0.5) * rolling_shutter
        color[r0:r1] = np.mean([render_view(scene, T, band, supersample=supersample)[0]
                                for T in exposure_poses(poses, index, motion_blur, samples, centre=readout)], axis=0)
    return color


def generate(out_dir: str | Path, *, layout: str = "replica", trajectory: str = "loop", width: int = 320,
             height: int = 240, frames: int = 100, seed: int = 0, supersample: int = 4, depth_noise: float = 0.0,
             depth_holes: float = 0.0, exposure_jitter: float = 0.0, laps: int = 1,
             fov_deg: float = DEFAULT_FOV_DEG, trajectory_start_s: float = 0.0, motion_blur: float = 0.0,
             blur_samples: int = 8, depth_delay: float = 0.0, rolling_shutter: float = 0.0,
             depth_radial_bias: float = 0.0, depth_baseline: float = 0.0, depth_focal_ratio: float = 1.0,
             overwrite: bool = False) -> Path:
    """Render a procedural RGB-D sequence with exact ground truth into ``out_dir``.

    layout: "replica" | "tum" (the CLI's ``--format``); trajectory: one of :data:`TRAJECTORIES`, or the
    path of a TUM trajectory file to replay (:func:`data_synth.trajectories.replay_poses`, from
    ``trajectory_start_s`` seconds into it; frames 0 = as many as it covers);
    width, height: pixels; frames: number of frames; seed: scene, textures and sensor noise;
    supersample: S, colour is the S x S stratified footprint average; depth_noise (m at 1 m,
    grows with z^2), depth_holes (dropout probability, also holes at depth edges),
    exposure_jitter (log-gain std per frame): sensor realism, 0 = off; laps: laps of ``loop``;
    fov_deg: horizontal field of view; motion_blur: the exposure as a fraction of the frame interval,
    centred on the frame's time (0 = a still camera per frame, up to 1), colour averaged over
    ``blur_samples`` poses across it (each rendered with the S x S footprint; depth stays the frame's pose's);
    depth_delay: the depth image is taken this many frame intervals after the colour (0 to 0.5; the ground
    truth is the colour's pose, the TUM layout's depth.txt has the depth images' own timestamps), as by a
    camera whose colour and depth streams are not synchronised; rolling_shutter: the colour image's rows are
    read out top to bottom over this fraction of the frame interval, centred on the frame's time (0 = a
    global shutter; up to 1), in ROLLING_SHUTTER_BANDS bands of rows, each with its own pose;
    depth_radial_bias: relative depth error at the middle of the image's edges, growing as r^2 from 0 at the
    centre (:mod:`data_synth.sensor`; -0.1 to 0.1);
    depth_baseline, depth_focal_ratio: the depth image is a second camera's, ``depth_baseline`` metres along the
    colour camera's x axis, with ``depth_focal_ratio`` times its focal length (same size and principal point),
    written pixel for pixel as if registered to the colour image, as by a Kinect whose depth is not registered
    (0 and 1 = registered);
    overwrite: replace an earlier data_synth folder.
    Same arguments give byte-identical folders. Returns the folder's path.
    Raises ConfigError for invalid arguments, DatasetError when a file cannot be written.
    """
    layout = _choice("layout (--format)", layout, LAYOUTS)
    replay_file = None
    if str(trajectory) not in TRAJECTORIES and Path(str(trajectory)).is_file():
        replay_file = Path(str(trajectory))
    else:
        trajectory = _choice("trajectory (a name, or a TUM trajectory file to replay)", trajectory, TRAJECTORIES)
    width = _require_int("width", width, 8, 8192)
    height = _require_int("height", height, 8, 8192)
    frames = _require_int("frames", frames, 0 if replay_file else 1, 1_000_000)
    seed = _require_int("seed", seed, 0, 2**63 - 1)
    supersample = _require_int("supersample", supersample, 1, MAX_SUPERSAMPLE)
    laps = _require_int("laps", laps, 1, 1000)
    sensor = SensorOptions(
        depth_noise=_require_float("depth_noise", depth_noise, 0.0, 0.1),
        depth_holes=_require_float("depth_holes", depth_holes, 0.0, 1.0, high_open=True),
        exposure_jitter=_require_float("exposure_jitter", exposure_jitter, 0.0, 0.5),
        depth_radial_bias=_require_float("depth_radial_bias", depth_radial_bias, -0.1, 0.1),
    )
    fov_deg = _require_float("fov_deg", fov_deg, 10.0, 150.0)
    motion_blur = _require_float("motion_blur", motion_blur, 0.0, 1.0)
    blur_samples = _require_int("blur_samples", blur_samples, 1, 64)
    # below half an interval: a reader pairs each colour image with the nearest depth image
    depth_delay = _require_float("depth_delay", depth_delay, 0.0, 0.5, high_open=True)
    rolling_shutter = _require_float("rolling_shutter", rolling_shutter, 0.0, 1.0)
    depth_baseline = _require_float("depth_baseline", depth_baseline, -0.2, 0.2)
    depth_focal_ratio = _require_float("depth_focal_ratio", depth_focal_ratio, 0.5, 2.0)
    if replay_file is not None:
        if laps != 1:
            raise ConfigError(f"laps={laps} applies only to the 'loop' trajectory, not a replayed file")
        trajectory_start_s = _require_float("trajectory_start_s", trajectory_start_s, 0.0, 1e9)
        poses = replay_poses(replay_file, frames, FPS, trajectory_start_s)
        frames, trajectory = len(poses), REPLAYED
        trajectory_options: dict[str, Any] = {"file": replay_file.name, "start_s": trajectory_start_s}
    else:
        poses = trajectory_poses(trajectory, frames, laps=laps)  # validates laps against the trajectory
        trajectory_options = {"laps": laps}
    out = Path(out_dir)
    _prepare_folder(out, overwrite)

    # The scene goes through its JSON form, so a reader rebuilding it from synth.json renders
    # exactly what was written.
    scene_dict = json.loads(json.dumps(make_scene(seed).to_dict()))
    scene = Scene.from_dict(scene_dict)
    intrinsics = default_intrinsics(width, height, fov_deg)
    registered = depth_baseline == 0 and depth_focal_ratio == 1
    depth_intrinsics = replace(intrinsics, fx=intrinsics.fx * depth_focal_ratio, fy=intrinsics.fy * depth_focal_ratio)
    T_cd = np.eye(4)
    T_cd[0, 3] = depth_baseline  # the depth camera in the colour camera's frame
    depth_scale = DEPTH_SCALE[layout]
    exposure = exposure_parameters(seed, frames, sensor.exposure_jitter)
    logger.info("data_synth: %d %s frames of %dx%d (seed %d, %dx%d supersampling) into %s",
                frames, trajectory, width, height, seed, supersample, supersample, out)

    color_dir = out / ("results" if layout == "replica" else "rgb")
    depth_dir = out / ("results" if layout == "replica" else "depth")
    color_dir.mkdir(exist_ok=True)
    depth_dir.mkdir(exist_ok=True)
    color_names, depth_names = [], []
    moving = (motion_blur > 0 and blur_samples > 1) or rolling_shutter > 0
    for i, T_wc in enumerate(poses):
        depth = None
        if moving:
            color = _moving_camera_color(scene, poses, i, intrinsics, supersample, motion_blur, blur_samples,
                                         rolling_shutter)
        else:
            color, depth = render_view(scene, T_wc, intrinsics, supersample=supersample)
        if depth is None or depth_delay > 0 or not registered:  # pixel-centre rays alone: the same at any supersampling
            depth_pose = np.asarray(pose_at(poses, i, depth_delay), dtype=np.float64) @ T_cd
            depth = render_view(scene, depth_pose, depth_intrinsics, supersample=1)[1]
        if sensor.exposure_jitter > 0:
            color = apply_exposure(color, *exposure[i])
        depth = apply_depth_effects(depth, sensor, seed, i)
        if layout == "replica":
            color_name, depth_name = f"results/frame{i:06d}.png", f"results/depth{i:06d}.png"
        else:
            color_name, depth_name = f"rgb/{tum_timestamp(i)}.png", f"depth/{tum_timestamp(i + depth_delay)}.png"
        _write_png(out / color_name, color_to_uint8_bgr(color))
        _write_png(out / depth_name, depth_to_uint16(depth, depth_scale))
        color_names.append(color_name)
        depth_names.append(depth_name)
        if (i + 1) % max(1, math.ceil(frames / 10)) == 0 or i + 1 == frames:
            logger.info("data_synth: rendered %d/%d frames", i + 1, frames)

    if layout == "replica":
        lines = [" ".join(f"{v:.18e}" for v in T.reshape(-1)) for T in poses]
        _write_text(out / "traj.txt", "\n".join(lines) + "\n")
        camera = {"w": width, "h": height, "fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx,
                  "cy": intrinsics.cy, "scale": depth_scale}
        _write_text(out / "cam_params.json", json.dumps({"camera": camera}, indent=2) + "\n")
    else:
        stamps = [tum_timestamp(i) for i in range(frames)]
        depth_stamps = [tum_timestamp(i + depth_delay) for i in range(frames)]
        header = "# data_synth: {kind} (seed {seed}, trajectory {traj})\n# timestamp filename\n"
        _write_text(out / "rgb.txt", header.format(kind="color images", seed=seed, traj=trajectory)
                    + "".join(f"{s} {n}\n" for s, n in zip(stamps, color_names)))
        _write_text(out / "depth.txt", header.format(kind="depth images", seed=seed, traj=trajectory)
                    + "".join(f"{s} {n}\n" for s, n in zip(depth_stamps, depth_names)))
        quats = _quaternions_xyzw(poses)
        rows = [f"{s} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)) for s, T, q in zip(stamps, poses, quats)]
        _write_text(out / "groundtruth.txt", f"# data_synth ground truth (camera-to-world, seed {seed})\n"
                    "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")

    info = {
        "format_version": FORMAT_VERSION,
        "generator": GENERATOR,
        "layout": layout,
        "trajectory": trajectory,
        "seed": seed,
        "frames": frames,
        "intrinsics": {"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
                       "width": width, "height": height},
        "depth_scale": depth_scale,
        "fps": FPS,
        "scene": scene_dict,
        "sensor": sensor.to_dict(exposure if sensor.exposure_jitter > 0 else None),
        "trajectory_options": trajectory_options,
        "render": {"supersample": supersample, "fov_deg": fov_deg, "motion_blur": motion_blur,
                   "blur_samples": blur_samples, "depth_delay": depth_delay, "rolling_shutter": rolling_shutter,
                   "depth_baseline": depth_baseline, "depth_focal_ratio": depth_focal_ratio,
                   "color": "mean of S x S stratified rays over each pixel's unit square, 8-bit rounded",
                   "depth": "camera-frame z of the pixel-centre ray's hit"},
    }
    if replay_file is not None:
        info["poses"] = [[float(v) for v in T.reshape(-1)] for T in poses]  # repr round-trips float64 exactly
    _write_text(out / "synth.json", json.dumps(info, indent=1) + "\n")
    return out
