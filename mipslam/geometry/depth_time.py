"""Depth images taken at another instant than their colour image, moved to the colour image's instant.

A Kinect-type camera streams colour and depth unsynchronised: on TUM RGB-D's freiburg1 sequences a depth
image comes 0-17 ms after the colour image it is paired with. Under fast motion that is a different
viewpoint (2.4 deg/frame at 30 frames/s is 0.6 deg in 8 ms), and a depth image read as if taken with the
colour image pulls tracking and places the map where the camera was not (data_synth with
``--depth-delay 0.25`` on the fr1_rpy motion: ATE 1.0 -> 1.9 cm; docs/tracking.md, "Colour and depth at
different instants").

Motion model: constant body-frame velocity over the frame interval, so the depth camera at
``t + offset`` sits at ``T_cd = exp((offset / interval) * log(T_prev^-1 T_curr))`` in the colour
camera's frame at ``t`` (``T_prev``, ``T_curr``: camera-to-world at the start and end of an interval
of ``interval`` seconds). The depth image is resampled into the colour camera by backward warping
with nearest-pixel reads, so no depth mixes two surfaces.
"""
from __future__ import annotations

import torch

from mipslam.geometry.camera import pixel_grid, project, unproject
from mipslam.geometry.se3 import se3_exp, se3_inverse, se3_log

# A frame further than this from the colour instant (seconds) is not moved: a pairing that far apart is not
# a stream offset (dataset.association_tolerance_s is 0.02 s).
MAX_OFFSET_S = 0.05
WARP_ITERATIONS = 2  # fixed-point steps of the backward warp (sub-pixel after 2 for motions of a few pixels)


def interval_velocity(T_prev_wc: torch.Tensor, T_curr_wc: torch.Tensor, interval_s: float) -> torch.Tensor | None:
    """Constant body-frame velocity over the motion ``T_prev -> T_curr`` (camera-to-world [4, 4]) of ``interval_s``
    seconds: ``log(T_prev^-1 T_curr) / interval_s``, [rho (m/s), phi (rad/s)] in the camera frame.  -> [6]
    float64, or None without a usable interval."""
    if not interval_s > 0:
        return None
    return se3_log(se3_inverse(T_prev_wc.to(torch.float64)) @ T_curr_wc.to(torch.float64)) / interval_s


def depth_camera_pose(velocity: torch.Tensor, offset_s: float) -> torch.Tensor | None:
    """Pose of the depth camera (at ``t + offset_s``) in the colour camera's frame (at ``t``) for a camera moving
    at ``velocity`` [6] (:func:`interval_velocity`): ``exp(velocity * offset_s)``. None when there is nothing to
    move (no offset, or an offset beyond MAX_OFFSET_S).  -> T_cd [4, 4] float64"""
    if offset_s == 0 or abs(offset_s) > MAX_OFFSET_S:
        return None
    return se3_exp(velocity.to(torch.float64) * offset_s)


def depth_camera_motion(T_prev_wc: torch.Tensor, T_curr_wc: torch.Tensor, interval_s: float,
                        offset_s: float) -> torch.Tensor | None:
    """:func:`depth_camera_pose` for the motion ``T_prev -> T_curr`` over ``interval_s`` seconds (module
    docstring); None also without a usable interval.

    T_prev_wc, T_curr_wc: [4, 4] camera-to-world -> T_cd [4, 4] float64
    """
    velocity = interval_velocity(T_prev_wc, T_curr_wc, interval_s)
    return None if velocity is None else depth_camera_pose(velocity, offset_s)


def depth_at_colour_time(depth: torch.Tensor, K: torch.Tensor, T_cd: torch.Tensor) -> torch.Tensor:
    """The depth image as the colour camera would have measured it: each colour pixel ``u`` reads the depth
    pixel its surface point was seen at, ``u_d = pi(T_cd^-1 X)``, ``X = pi^-1(u, z)`` with ``z`` found by
    WARP_ITERATIONS fixed-point steps from the depth at ``u``; the result is that point's z in the colour
    camera. Pixels whose source falls outside the image or on a missing depth read 0 (no measurement).

    depth: metres, 0 = none   # [H, W]
    K: intrinsics             # [3, 3]
    T_cd: depth camera in the colour camera's frame   # [4, 4]
    Returns [H, W] depth, dtype and device of ``depth``.
    """
    H, W = depth.shape
    dev, dtype = depth.device, torch.float64
    K = K.to(dev, dtype)
    T_cd = T_cd.to(dev, dtype)
    T_dc = se3_inverse(T_cd)
    uv = pixel_grid(H, W, dtype=dtype, device=dev)  # [H, W, 2] colour pixels
    source = depth.to(dtype)
    z = source.clone()
    for _ in range(WARP_ITERATIONS):
        X_d = unproject(uv, z, K) @ T_dc[:3, :3].T + T_dc[:3, 3]  # colour-pixel ray point in the depth camera
        uv_d, z_d = project(X_d, K)
        col, row = torch.round(uv_d[..., 0]), torch.round(uv_d[..., 1])
        inside = (col >= 0) & (col <= W - 1) & (row >= 0) & (row <= H - 1) & (z_d > 0)
        read = source[row.clamp(0, H - 1).long(), col.clamp(0, W - 1).long()]
        read = torch.where(inside, read, torch.zeros_like(read))
        # the read depth is the depth camera's; its point seen from the colour camera gives the next z
        X_c = unproject(torch.stack([col, row], -1), read, K) @ T_cd[:3, :3].T + T_cd[:3, 3]
        z = torch.where(read > 0, X_c[..., 2], torch.zeros_like(read))
    return z.clamp_min(0).to(depth.dtype)
