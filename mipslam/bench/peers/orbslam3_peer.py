"""ORB-SLAM3 RGB-D (Campos et al., IEEE T-RO 2021) through the optional package ``pyorbslam3`` (GPL-3.0).

The run follows ORB-SLAM3's ``Examples/RGB-D/rgbd_tum.cc``: one ``track_rgbd`` call per frame, paced
to the recording's timestamps unless ``realtime`` is off, then ``shutdown`` and the final trajectory
(``SaveTrajectoryTUM``: every frame ORB-SLAM3 did not lose, expressed relative to its refined
keyframe, so loop closure and bundle adjustment are in it). A frame absent from that trajectory is
lost. The settings file is written from the sequence's pinhole intrinsics (no lens distortion, the
camera model mipslam and the Open3D peers use); depth goes in as float32 metres
(``RGBD.DepthMapFactor: 1``), colour as 8-bit RGB (``Camera.RGB: 1``).

ORB-SLAM3 runs local mapping and loop closing in threads of its own: its results vary from run to
run, so the bench repeats it (median and spread).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mipslam.optional import import_optional
from mipslam.bench.peers.common import PeerRun, peer_frames
from mipslam.bench.peers.options import ORBSLAM3Options
from mipslam.errors import MipslamError
from mipslam.io.tum import read_tum_trajectory

__all__ = ["frames_of_saved_poses", "orbslam3_settings_text", "run_orbslam3"]

PACKAGE_HINT = ("pip install 'mipslam[peers]' (installs pyorbslam3, GPL-3.0; Linux x86_64, Python 3.8-3.12) or "
                "give --peer-python an interpreter that has it")


def orbslam3_settings_text(intrinsics, options: ORBSLAM3Options) -> str:
    """ORB-SLAM3 settings (YAML 1.0, settings file format 1.0) for a pinhole RGB-D camera in metres."""
    values = {
        "Camera.type": '"PinHole"',
        "Camera1.fx": intrinsics.fx, "Camera1.fy": intrinsics.fy, "Camera1.cx": intrinsics.cx, "Camera1.cy": intrinsics.cy,
        "Camera1.k1": 0.0, "Camera1.k2": 0.0, "Camera1.p1": 0.0, "Camera1.p2": 0.0,
        "Camera.width": int(intrinsics.width), "Camera.height": int(intrinsics.height),
        "Camera.fps": int(options.fps), "Camera.RGB": 1,
        "Stereo.ThDepth": options.close_depth_baselines, "Stereo.b": options.baseline_m,
        "RGBD.DepthMapFactor": 1.0,
        "ORBextractor.nFeatures": int(options.features), "ORBextractor.scaleFactor": options.scale_factor,
        "ORBextractor.nLevels": int(options.levels), "ORBextractor.iniThFAST": int(options.fast_threshold),
        "ORBextractor.minThFAST": int(options.fast_threshold_min),
    }
    # ORB-SLAM3 requires the viewer's keys even when the viewer is off; these values draw nothing here
    values.update({"Viewer.KeyFrameSize": 0.05, "Viewer.KeyFrameLineWidth": 1.0, "Viewer.GraphLineWidth": 0.9,
                   "Viewer.PointSize": 2.0, "Viewer.CameraSize": 0.08, "Viewer.CameraLineWidth": 3.0,
                   "Viewer.ViewpointX": 0.0, "Viewer.ViewpointY": -0.7, "Viewer.ViewpointZ": -1.8,
                   "Viewer.ViewpointF": 500.0})

    def text(value) -> str:
        if isinstance(value, float):
            return repr(value) if "." in repr(value) or "e" in repr(value) else f"{value:.1f}"
        return str(value)

    lines = ["%YAML:1.0", 'File.version: "1.0"', *(f"{k}: {text(v)}" for k, v in values.items())]
    return "\n".join(lines) + "\n"


def frames_of_saved_poses(saved_times: np.ndarray, frame_times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which frame each line of ORB-SLAM3's saved trajectory belongs to. -> (frame positions [M], line numbers [M]).

    ORB-SLAM3 writes the times it was given with 6 decimals, one line per frame; for a frame it lost it
    repeats the previous line's time and pose, so only the first line of a time is that frame's pose and
    a frame whose time is missing (or only repeated) has none. saved_times [L], frame_times [N] seconds.
    """
    if len(saved_times) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    nearest = np.abs(saved_times[:, None] - frame_times[None, :]).argmin(axis=1)
    close = np.abs(frame_times[nearest] - saved_times) < 1e-4
    first_line: dict[int, int] = {}
    for line, frame in enumerate(nearest):
        if close[line]:
            first_line.setdefault(int(frame), line)
    positions = np.asarray(sorted(first_line), dtype=np.int64)
    return positions, np.asarray([first_line[int(p)] for p in positions], dtype=np.int64)


def _import_pyorbslam3():
    return import_optional("pyorbslam3", needed_by="peer orbslam3", install=PACKAGE_HINT)


def run_orbslam3(sequence, options: ORBSLAM3Options, work_dir: Path) -> PeerRun:
    """ORB-SLAM3 RGB-D on ``sequence``; its settings and trajectory files go to ``work_dir``."""
    if not options.vocabulary:
        raise MipslamError("peer orbslam3 needs a DBoW2 vocabulary: give --vocab FILE (train one with "
                           "'mipslam bench --train-vocab FILE --vocab-images DIR')")
    vocabulary = Path(options.vocabulary).expanduser()
    if not vocabulary.is_file():
        raise MipslamError(f"{vocabulary}: ORB vocabulary not found; train one with 'mipslam bench --train-vocab'")
    pos = _import_pyorbslam3()
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    settings = work_dir / "orbslam3_settings.yaml"
    settings.write_text(orbslam3_settings_text(sequence.intrinsics, options), encoding="utf-8")
    start = time.perf_counter()
    slam = pos.Slam(vocab_file=str(vocabulary), settings_file=str(settings), sensor=pos.Sensor.RGBD, use_viewer=False)
    start_s = time.perf_counter() - start
    paced = options.realtime and sequence.timestamp_kind == "time"
    timestamps = np.asarray(sequence.timestamps, dtype=np.float64)
    seconds, states = [], []
    try:
        for frame, _read_s in peer_frames(sequence):
            t0 = time.perf_counter()
            result = slam.track_rgbd(frame.color, frame.depth, frame.timestamp)
            busy = time.perf_counter() - t0
            seconds.append(busy)
            states.append(str(result.state).split(".")[-1])
            if paced and frame.position + 1 < len(timestamps):
                gap = float(timestamps[frame.position + 1] - timestamps[frame.position])
                if busy < gap:
                    time.sleep(gap - busy)
    finally:
        slam.shutdown()
    trajectory_path = work_dir / "orbslam3_trajectory.txt"
    initialised = any(state in ("OK", "OK_KLT", "RECENTLY_LOST", "LOST") for state in states)
    if initialised:  # ORB-SLAM3 crashes saving the trajectory of a map it never started
        slam.save_trajectory_tum(str(trajectory_path))
    if not initialised or not trajectory_path.is_file() or trajectory_path.stat().st_size == 0:
        stamps, poses, positions = np.zeros(0), np.zeros((0, 4, 4)), np.zeros(0, dtype=np.int64)
    else:
        saved = read_tum_trajectory(trajectory_path, allow_duplicate_timestamps=True)
        positions, lines = frames_of_saved_poses(saved.timestamps, timestamps)
        stamps, poses = timestamps[positions], saved.T_wc[lines].reshape(-1, 4, 4)
    counts = {s: states.count(s) for s in sorted(set(states))}
    details = {"system": "ORB-SLAM3 RGB-D (pyorbslam3)", "vocabulary": str(vocabulary), "paced_to_timestamps": paced,
               "tracking_states": counts, "initialised": initialised}
    return PeerRun(len(seconds), stamps, poses, positions, np.asarray(seconds, dtype=np.float64), start_s, details)
