"""Named camera trajectories inside the procedural room (camera-to-world, OpenCV camera axes).

All trajectories but ``spin`` keep handheld speeds whatever the number of frames: about 2 cm and at
most about 2 degrees per frame (checked by the tests for few and many frames). Where a trajectory
cannot complete its full motion at that speed in the frames given, its extent shrinks instead
(a smaller circle, a narrower look-around, a shorter dolly). They stay in the camera corridor
that :func:`data_synth.scene.make_scene` keeps free of objects (within 1 m of the room's vertical
axis, and the strip in front of the +x wall), so the camera is never closer than 0.4 m to a
surface (the zoom's nearest point; elsewhere 0.5 m or more).

- ``loop``: laps of a horizontal circle of radius ``r = min(1 m, 2 cm * frames_per_lap / 2 pi)``
  about the room's axis at 1.4 m height, with small height, pitch and roll oscillations. With
  at least 240 frames per lap the camera looks outwards and turns a full 360 degrees per lap (a
  lap around the room); with fewer it looks towards the +x wall and sweeps its heading by
  ``+-A``, ``A = 1.5 deg * frames_per_lap / (2 pi)``. The phase of frame i is
  ``(laps * i mod (frames - 1)) / (frames - 1)``, computed in integers, so the last frame (and the
  end of every lap) has exactly the start pose: the trajectory closes its loop(s).
- ``zoom``: a dolly straight towards the test chart on the +x wall and back: distance
  ``d = d_near * (d_far / d_near) ** ((1 + cos 2 pi s) / 2)``, d_near = 0.4 m, d_far up to 3 m
  (as large as 3 cm per frame allows), so the texture's on-screen frequency changes by d_far / d_near.
- ``line``: constant-velocity translation of 2 cm per frame (at most 2 m) parallel to the +x wall,
  facing it from 1.6 m, fixed orientation.
- ``static``: the camera at rest (the middle of ``line``), every frame identical.
- ``spin``: a fast turn at the start and the end over the +x wall's repeated textures (blinds, checker
  ladder, fine chart), the failure case of a tracker whose map is one keyframe: from the room's centre the
  camera turns ``SPIN_DEG_PER_FRAME`` (9 degrees) a frame for the first and the last ``SPIN_FRAMES``
  frames (a tenth of the sequence, at least 2), sweeping ``yaw`` from ``-S/2`` to ``+S/2`` (S the spin's
  angle), and between the two spins turns back from ``+S/2`` to ``-S/2`` at handheld speed (a cosine
  profile, at most about 2 degrees a frame for 60 frames or more), so the end spin crosses what the
  start spin saw and the map now holds. The position drifts on a 5 cm circle (under 1 cm a frame).

A recorded trajectory replays instead (:func:`replay_poses`): a TUM file (``timestamp tx ty tz qx qy
qz qw``, camera-to-world, e.g. a TUM RGB-D ground truth) sampled at the sequence's frame rate, its
motion unchanged (real speeds, no speed limit) and moved rigidly into the room: the first camera looks
along +x, level, and the path's bounding box is centred on the room's axis at 1.4 m. A path that does
not fit the camera corridor is refused, not squeezed.

Motion blur (:func:`exposure_poses`): a frame's colour can be the mean over poses spread across an
exposure centred on the frame's time, interpolated between neighbouring frames' poses. A depth delay
(:func:`pose_at`) renders the depth image later than the colour, as a camera whose two streams are not
synchronised (a Kinect's colour and depth are up to half a frame apart).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from data_synth.scene import ROOM_MAX, ROOM_MIN
from mipslam.errors import ConfigError, DatasetError

TRAJECTORIES = ("loop", "zoom", "line", "static", "spin")

STEP_M = 0.02  # nominal translation per frame
MAX_STEP_M = 0.03  # never exceeded
LOOP_RADIUS_M = 1.0
LOOP_HEIGHT_M = 1.4
FULL_TURN_MIN_FRAMES = 240  # frames per lap needed to turn 360 degrees at <= 1.5 deg/frame
ZOOM_NEAR_M = 0.4
ZOOM_FAR_MAX_M = 3.0
ZOOM_HEIGHT_M = 1.3  # centre of the test chart on the +x wall
WALL_VIEW_DISTANCE_M = 1.6  # line and static
LINE_MAX_LENGTH_M = 2.0
CORRIDOR_RADIUS_M = 1.0  # a replayed path stays within this horizontal distance of the room's axis ...
CORRIDOR_HEIGHT_M = (0.5, 2.1)  # ... and between these heights (0.5 m from floor and ceiling)
SPIN_DEG_PER_FRAME = 9.0
SPIN_SHARE = 0.1  # of the frames, each of the two spins
SPIN_MIN_FRAMES = 20  # two spins of 2 frames and a way back
SPIN_CIRCLE_M = 0.05
REPLAY_MAX_GAP_S = 0.1  # a sample time between two recorded poses further apart is refused (tracking dropout)
REPLAY_TIME_TOLERANCE_S = 1e-5


def camera_poses(position: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world poses from a position and heading angles (radians, world z up).

    position [N, 3] metres; yaw [N] (0 looks along +x, positive turns towards +y), pitch [N]
    (positive looks up), roll [N] (about the viewing direction) -> T_wc [N, 4, 4] float64 with
    OpenCV camera axes (columns of R: x right, y down, z forward).
    """
    yaw, pitch, roll = (np.asarray(a, dtype=np.float64) for a in (yaw, pitch, roll))
    forward = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], -1)
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], -1)  # forward x up, normalised
    down = np.cross(forward, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    right_r = c * right + s * down
    down_r = -s * right + c * down
    T = np.zeros((len(yaw), 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = right_r, down_r, forward
    T[:, :3, 3] = position
    T[:, 3, 3] = 1.0
    return T


def _loop(frames: int, laps: int) -> np.ndarray:
    if frames == 1:
        phase = np.zeros(1)
    else:
        i = np.arange(frames, dtype=np.int64)
        phase = ((laps * i) % (frames - 1)).astype(np.float64) / (frames - 1)
    theta = 2 * math.pi * phase
    per_lap = (frames - 1) / laps if frames > 1 else 1.0
    radius = min(LOOP_RADIUS_M, STEP_M * per_lap / (2 * math.pi))
    centre = 0.5 * (np.asarray(ROOM_MIN[:2]) + np.asarray(ROOM_MAX[:2]))
    # Oscillation amplitudes bounded so each adds at most a fraction of a degree (mm) per frame.
    pitch_amp = min(math.radians(4.0), math.radians(0.25) * per_lap / (2 * math.pi * 2))
    roll_amp = min(math.radians(2.0), math.radians(0.15) * per_lap / (2 * math.pi * 3))
    height_amp = min(0.08, 0.003 * per_lap / (2 * math.pi * 2))
    if per_lap >= FULL_TURN_MIN_FRAMES:
        yaw = theta.copy()
    else:
        yaw = math.radians(1.5) * per_lap / (2 * math.pi) * np.sin(theta)
    position = np.stack([centre[0] + radius * np.cos(theta), centre[1] + radius * np.sin(theta),
                         LOOP_HEIGHT_M + height_amp * np.sin(2 * theta)], -1)
    pitch = math.radians(-8.0) + pitch_amp * np.sin(2 * theta)
    roll = roll_amp * np.sin(3 * theta)
    return camera_poses(position, yaw, pitch, roll)


def _zoom_distances(frames: int, far: float) -> np.ndarray:
    s = np.arange(frames, dtype=np.float64) / max(frames - 1, 1)
    blend = 0.5 * (1 + np.cos(2 * math.pi * s))
    return ZOOM_NEAR_M * (far / ZOOM_NEAR_M) ** blend


def zoom_far_distance(frames: int) -> float:
    """Largest start distance (<= 3 m) whose dolly keeps every step within 3 cm."""
    if frames < 3:  # no frame in the middle of the dolly: every frame is at the start distance
        return ZOOM_FAR_MAX_M

    def max_step(far: float) -> float:
        return float(np.abs(np.diff(_zoom_distances(frames, far))).max())
    if max_step(ZOOM_FAR_MAX_M) <= MAX_STEP_M:
        return ZOOM_FAR_MAX_M
    lo, hi = ZOOM_NEAR_M, ZOOM_FAR_MAX_M
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if max_step(mid) <= MAX_STEP_M else (lo, mid)
    return lo


def _zoom(frames: int) -> np.ndarray:
    distance = _zoom_distances(frames, zoom_far_distance(frames))
    y_mid = 0.5 * (ROOM_MIN[1] + ROOM_MAX[1])
    position = np.stack([ROOM_MAX[0] - distance, np.full(frames, y_mid), np.full(frames, ZOOM_HEIGHT_M)], -1)
    zeros = np.zeros(frames)
    return camera_poses(position, zeros, zeros, zeros)


def _line(frames: int) -> np.ndarray:
    length = min(LINE_MAX_LENGTH_M, STEP_M * (frames - 1))
    s = np.arange(frames, dtype=np.float64) / max(frames - 1, 1)
    y_mid = 0.5 * (ROOM_MIN[1] + ROOM_MAX[1])
    y = y_mid + length / 2 - length * s  # moving to the camera's right (-y when facing +x)
    position = np.stack([np.full(frames, ROOM_MAX[0] - WALL_VIEW_DISTANCE_M), y, np.full(frames, 1.35)], -1)
    zeros = np.zeros(frames)
    return camera_poses(position, zeros, np.full(frames, math.radians(-5.0)), zeros)


def _static(frames: int) -> np.ndarray:
    return np.repeat(_line(1), frames, axis=0)


def _spin(frames: int) -> np.ndarray:
    spin = max(2, int(round(SPIN_SHARE * frames)))
    back = frames - 1 - 2 * spin  # frame intervals of the way back
    half = math.radians(SPIN_DEG_PER_FRAME) * spin / 2
    i = np.arange(frames, dtype=np.float64)
    s = np.clip((i - spin) / back, 0.0, 1.0)  # 0 .. 1 along the way back
    yaw = np.where(i <= spin, -half + 2 * half * i / spin,
                   np.where(i < frames - 1 - spin, half * np.cos(math.pi * s),
                            -half + 2 * half * (i - (frames - 1 - spin)) / spin))
    angle = 2 * math.pi * i / (frames - 1)
    centre = 0.5 * (np.asarray(ROOM_MIN) + np.asarray(ROOM_MAX))
    position = np.stack([centre[0] + SPIN_CIRCLE_M * np.cos(angle), centre[1] + SPIN_CIRCLE_M * np.sin(angle),
                         np.full(frames, LOOP_HEIGHT_M)], -1)
    pitch = math.radians(-3.0) + math.radians(2.0) * np.sin(angle)
    return camera_poses(position, yaw, pitch, np.zeros(frames))


def trajectory_poses(name: str, frames: int, *, laps: int = 1) -> np.ndarray:
    """Camera-to-world poses of trajectory ``name`` (one of :data:`TRAJECTORIES`).

    frames: number of poses (>= 1). laps: laps around the room (``loop`` only; the last frame and
    the end of every lap return exactly to the start pose).
    Returns T_wc [frames, 4, 4] float64, OpenCV camera axes, world z up, metres.
    """
    if name not in TRAJECTORIES:
        import difflib

        near = difflib.get_close_matches(str(name), TRAJECTORIES, n=1)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise ConfigError(f"unknown trajectory '{name}'{hint}; choose one of: {', '.join(TRAJECTORIES)}")
    if not isinstance(frames, (int, np.integer)) or isinstance(frames, bool) or frames < 1:
        raise ConfigError(f"frames must be an integer >= 1, got {frames!r}")
    if not isinstance(laps, (int, np.integer)) or isinstance(laps, bool) or laps < 1:
        raise ConfigError(f"laps must be an integer >= 1, got {laps!r}")
    if laps != 1 and name != "loop":
        raise ConfigError(f"laps={laps} applies only to the 'loop' trajectory, not '{name}'")
    frames = int(frames)
    if name == "spin" and frames < SPIN_MIN_FRAMES:
        raise ConfigError(f"the spin trajectory needs at least {SPIN_MIN_FRAMES} frames, got {frames}")
    if name == "spin":
        return _spin(frames)
    if name == "loop":
        return _loop(frames, int(laps))
    if name == "zoom":
        return _zoom(frames)
    if name == "line":
        return _line(frames)
    return _static(frames)


def replay_poses(path: str | Path, frames: int, fps: float, start_s: float = 0.0) -> np.ndarray:
    """A recorded camera path moved into the room, sampled at ``fps`` (module docstring).

    path: TUM trajectory file (camera-to-world); frames: number of samples, 0 = as many as the file
    covers; fps: samples per second; start_s: seconds after the file's first pose of the first sample.
    Each sample is interpolated between the two recorded poses around it, as the TUM reader interpolates ground
    truth (:func:`mipslam.datasets.tum.poses_at_times`: linear position, SLERP rotation). Returns T_wc [frames, 4, 4] float64, OpenCV camera axes, world z up, metres.
    Raises DatasetError for an unreadable file, a sample outside the recording or in a gap of more than
    REPLAY_MAX_GAP_S, or a path that leaves the camera corridor.
    """
    from mipslam.datasets.tum import poses_at_times
    from mipslam.io.tum import read_tum_trajectory

    path = Path(path)
    recorded = read_tum_trajectory(path, allow_duplicate_timestamps=True)
    first = np.r_[True, np.diff(recorded.timestamps) > 0]  # of poses with one timestamp, the first is kept
    stamps = recorded.timestamps[first] - recorded.timestamps[0]
    recorded_T_wc = recorded.T_wc[first]
    if not (math.isfinite(start_s) and start_s >= 0):
        raise ConfigError(f"trajectory start must be >= 0 seconds, got {start_s!r}")
    # float64 Unix times resolve ~0.2 us: a sample within REPLAY_TIME_TOLERANCE_S of the last pose is on it
    available = int(math.floor((stamps[-1] - start_s + REPLAY_TIME_TOLERANCE_S) * fps)) + 1
    if available < 1 or len(stamps) < 2:
        raise DatasetError(path, f"the recording lasts {stamps[-1]:.2f} s: no sample at {start_s:g} s and later; "
                                 "choose an earlier start")
    frames = available if frames == 0 else int(frames)
    if frames > available:
        raise DatasetError(path, f"{frames} frames at {fps:g} frames/s from {start_s:g} s need "
                                 f"{start_s + (frames - 1) / fps:.2f} s of recording; it has {stamps[-1]:.2f} s: "
                                 f"ask for at most {available} frames")
    times = np.minimum(start_s + np.arange(frames, dtype=np.float64) / fps, stamps[-1])
    after = np.clip(np.searchsorted(stamps, times, side="left"), 1, len(stamps) - 1)
    gaps = stamps[after] - stamps[after - 1]
    if (gaps > REPLAY_MAX_GAP_S).any():
        k = int(np.argmax(gaps > REPLAY_MAX_GAP_S))
        raise DatasetError(path, f"no pose for {gaps[k]:.2f} s around {times[k]:.2f} s after the start (a gap in the "
                                 "recording): choose a part without gaps with the start and frame count")
    # every sample lies within REPLAY_MAX_GAP_S of a recorded pose on either side: all interpolated, all valid
    sampled, _ = poses_at_times(stamps, torch.from_numpy(recorded_T_wc), times, REPLAY_MAX_GAP_S)
    positions, rotations = sampled[:, :3, 3].numpy(), sampled[:, :3, :3].numpy()

    # Rigid move into the room: the first camera's axes onto a level camera looking along +x.
    level = camera_poses(np.zeros((1, 3)), np.zeros(1), np.zeros(1), np.zeros(1))[0, :3, :3]
    align = level @ rotations[0].T
    positions = (positions - positions[0]) @ align.T
    low, high = positions.min(0), positions.max(0)
    target = np.array([0.5 * (ROOM_MIN[0] + ROOM_MAX[0]), 0.5 * (ROOM_MIN[1] + ROOM_MAX[1]), LOOP_HEIGHT_M])
    positions = positions - 0.5 * (low + high) + target
    T = np.zeros((frames, 4, 4))
    T[:, :3, :3] = align @ rotations
    T[:, :3, 3] = positions
    T[:, 3, 3] = 1.0
    horizontal = np.linalg.norm(positions[:, :2] - target[:2], axis=1).max()
    if horizontal > CORRIDOR_RADIUS_M or not (CORRIDOR_HEIGHT_M[0] <= positions[:, 2].min()
                                              and positions[:, 2].max() <= CORRIDOR_HEIGHT_M[1]):
        extent = high - low
        raise DatasetError(path, f"the path spans {extent[0]:.2f} x {extent[1]:.2f} x {extent[2]:.2f} m; the room's "
                                 f"camera corridor is {2 * CORRIDOR_RADIUS_M:g} m across and "
                                 f"{CORRIDOR_HEIGHT_M[1] - CORRIDOR_HEIGHT_M[0]:.1f} m high: replay a shorter part "
                                 "(fewer frames, another start)")
    return T


def pose_at(poses: np.ndarray, index: int, offset: float) -> np.ndarray:
    """The pose ``offset`` frame intervals (|offset| <= 1) after frame ``index``'s, interpolated between its pose
    and its neighbour's (:func:`mipslam.geometry.interpolate_pose`: linear position, SLERP rotation); the
    first and last frames hold still beyond their ends.

    poses [N, 4, 4] float64 camera-to-world -> [4, 4]
    """
    from mipslam.geometry import interpolate_pose

    other = index + (1 if offset > 0 else -1)
    if offset == 0 or not 0 <= other < len(poses):
        return poses[index].copy()
    return interpolate_pose(torch.from_numpy(poses[index]), torch.from_numpy(poses[other]), abs(offset)).numpy()


def exposure_poses(poses: np.ndarray, index: int, exposure: float, samples: int, centre: float = 0.0) -> np.ndarray:
    """Poses over an exposure of frame ``index``: ``samples`` times evenly spread over ``exposure`` (a fraction of
    the frame interval) centred ``centre`` frame intervals from the frame's time (:func:`pose_at` each, at most
    one interval away).

    poses [N, 4, 4] float64 camera-to-world -> [samples, 4, 4]
    """
    offsets = (np.arange(samples, dtype=np.float64) + 0.5) / samples - 0.5 if samples > 1 else np.zeros(1)
    return np.stack([pose_at(poses, index, float(u)) for u in np.clip(centre + offsets * exposure, -1.0, 1.0)])
