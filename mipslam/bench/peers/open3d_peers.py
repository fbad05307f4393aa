"""Open3D peers: dense RGB-D SLAM (``open3d.t.pipelines.slam``) and frame-to-frame RGB-D odometry.

* Dense SLAM (KinectFusion-style, Newcombe et al. 2011): each frame is tracked frame-to-model by
  point-to-plane ICP against the depth/normals raycast from the TSDF at the previous pose, then
  integrated into the TSDF at the tracked pose. The first frame is the world origin.
* Odometry (Steinbruecker et al. 2011 with the hybrid photometric + geometric term of Open3D):
  ``compute_rgbd_odometry`` between consecutive frames from the identity, increments chained. No map,
  no loop closure.

A frame whose registration fails (an exception or ``success=False``) gets no pose (it is lost); the
next frame is registered against the last frame that succeeded (odometry) or the unchanged model
(dense). Lens distortion is not modelled, as in Open3D's examples and in mipslam. Open3D's raycast
needs images of about 160x120 or more (smaller ones leave the model frame empty: every frame is lost).
"""
from __future__ import annotations

import re
import time

import numpy as np

from mipslam.bench.peers.common import PeerRun, peer_frames
from mipslam.bench.peers.options import Open3DDenseOptions, Open3DOdometryOptions

__all__ = ["run_open3d_dense", "run_open3d_odometry"]


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _open3d_message(exc: Exception) -> str:
    """The reason of an Open3D error, without its terminal colours and C++ signature."""
    lines = [line.strip() for line in _ANSI.sub("", str(exc)).splitlines() if line.strip()]
    text = lines[-1] if lines else type(exc).__name__
    return text.rsplit(": ", 1)[-1][:200] if "[Open3D Error]" in text else text[:200]


def _intrinsic_matrix(intrinsics) -> np.ndarray:
    return np.array([[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]])


def run_open3d_dense(sequence, options: Open3DDenseOptions) -> PeerRun:
    """Open3D dense SLAM on ``sequence``: -> :class:`PeerRun` (camera-to-world, first frame = identity)."""
    import open3d as o3d

    start = time.perf_counter()
    intr = sequence.intrinsics
    device = o3d.core.Device(options.device)
    K = o3d.core.Tensor(_intrinsic_matrix(intr), o3d.core.Dtype.Float64)
    T_wc = np.identity(4)
    model = o3d.t.pipelines.slam.Model(options.voxel_size_m, options.block_resolution, options.block_count,
                                       o3d.core.Tensor(T_wc), device)
    input_frame = o3d.t.pipelines.slam.Frame(intr.height, intr.width, K, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(intr.height, intr.width, K, device)
    depth_scale = 1.0  # depth arrives in metres (float32); colour as float32 in [0, 1]
    start_s = time.perf_counter() - start
    stamps, poses, positions, seconds, fitness, failures = [], [], [], [], [], []
    integrated = False
    for frame, _read_s in peer_frames(sequence):
        t0 = time.perf_counter()
        input_frame.set_data_from_image("depth", o3d.t.geometry.Image(frame.depth).to(device))
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(
            np.ascontiguousarray(frame.color, dtype=np.float32) / 255.0).to(device))
        ok = True
        if integrated:
            try:
                result = model.track_frame_to_model(input_frame, raycast_frame, depth_scale, options.depth_max_m,
                                                    options.distance_threshold_m)
                T_wc = T_wc @ result.transformation.cpu().numpy()
                fitness.append(float(result.fitness))
            except RuntimeError as exc:  # too few correspondences: the frame is lost
                ok = False
                failures.append({"position": frame.position, "error": _open3d_message(exc)})
        if ok:
            model.update_frame_pose(frame.position, o3d.core.Tensor(T_wc))
            model.integrate(input_frame, depth_scale, options.depth_max_m, options.trunc_voxel_multiplier)
            model.synthesize_model_frame(raycast_frame, depth_scale, options.depth_min_m, options.depth_max_m,
                                         options.trunc_voxel_multiplier, False)
            integrated = True
            stamps.append(frame.timestamp)
            poses.append(T_wc.copy())
            positions.append(frame.position)
        seconds.append(time.perf_counter() - t0)
    details = {"system": f"Open3D {o3d.__version__} t.pipelines.slam (frame-to-model ICP + TSDF)",
               "icp_fitness_median": float(np.median(fitness)) if fitness else None, "failures": failures}
    return PeerRun(len(seconds), np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
                   np.asarray(positions, dtype=np.int64), np.asarray(seconds, dtype=np.float64), start_s, details)


def run_open3d_odometry(sequence, options: Open3DOdometryOptions) -> PeerRun:
    """Open3D RGB-D odometry chained frame to frame: -> :class:`PeerRun` (first frame = identity)."""
    import open3d as o3d

    start = time.perf_counter()
    intr = sequence.intrinsics
    camera = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    option = o3d.pipelines.odometry.OdometryOption(depth_diff_max=options.depth_diff_max_m,
                                                   depth_max=options.depth_max_m)
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    start_s = time.perf_counter() - start
    T_wc = np.identity(4)
    previous = None
    stamps, poses, positions, seconds = [], [], [], []
    for frame, _read_s in peer_frames(sequence):
        t0 = time.perf_counter()
        current = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(frame.color), o3d.geometry.Image(frame.depth), depth_scale=1.0,
            depth_trunc=options.depth_max_m, convert_rgb_to_intensity=True)
        ok = True
        if previous is not None:
            # source = previous frame, target = current: the result maps previous-camera points into the current camera
            ok, T_cur_prev, _info = o3d.pipelines.odometry.compute_rgbd_odometry(
                previous, current, camera, np.identity(4), jacobian, option)
            if ok:
                T_wc = T_wc @ np.linalg.inv(T_cur_prev)
        if ok:
            previous = current
            stamps.append(frame.timestamp)
            poses.append(T_wc.copy())
            positions.append(frame.position)
        seconds.append(time.perf_counter() - t0)
    details = {"system": f"Open3D {o3d.__version__} pipelines.odometry (hybrid RGB-D term, frame to frame)"}
    return PeerRun(len(seconds), np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
                   np.asarray(positions, dtype=np.int64), np.asarray(seconds, dtype=np.float64), start_s, details)
