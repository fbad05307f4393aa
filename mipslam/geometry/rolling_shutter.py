"""A rolling-shutter colour image moved to one instant: every row as the camera saw it at the frame's time.

A rolling-shutter camera (most colour sensors of consumer RGB-D cameras) reads its rows top to bottom over a
read-out time ``readout_s``; row ``v`` of an ``H``-row image is taken at
``t_v = t + ((v + 0.5) / H - 0.5) * readout_s`` (the frame's timestamp ``t`` is the middle row's instant,
pixel centres at integer coordinates). Under fast rotation the rows then disagree about where the camera
was: at 60 deg/s and a 30 ms read-out the top and bottom rows are 1.8 deg apart. Renderers and alignments
assume one pose per image, so the image is resampled into the one a global shutter at ``t`` would have taken.

Motion model: the camera turns at a constant body-frame angular velocity ``omega`` (rad/s, camera frame)
over the read-out, and its translation within it is neglected (the rotation-only rectification of Forssen
and Ringaby, "Rectifying rolling shutter video from hand-held devices", CVPR 2010: a few millimetres of
travel move a pixel far less than a degree of rotation does). A world direction seen along the ray ``r`` at
``t`` is seen along ``exp(-omega * dt) r`` at ``t + dt``; so the global-shutter pixel ``q`` reads the
rolling-shutter image at ``p = pi(K exp(-omega * dt(p)) K^-1 q)``, ``dt(p)`` from ``p``'s own row, found by
fixed-point steps from ``q``'s row.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


# Fixed-point steps on the source row: the row moves by under a pixel per step once the first has moved it,
# for rotations of a few degrees over the read-out.
ROW_ITERATIONS = 2


def row_times(height: int, readout_s: float, dtype: torch.dtype = torch.float64,
              device: torch.device | str = "cpu") -> torch.Tensor:
    """Seconds from the frame's instant to each row's read-out (module docstring).  -> [H]"""
    rows = torch.arange(height, dtype=dtype, device=device)
    return ((rows + 0.5) / height - 0.5) * readout_s


def colour_at_frame_instant(color: torch.Tensor, K: torch.Tensor, angular_velocity: torch.Tensor,
                            readout_s: float) -> torch.Tensor:
    """The image a global shutter would have taken at the frame's instant (module docstring); bilinear reads,
    the border repeated where a ray leaves the image.

    color: colour in [0, 1]                                     # [H, W, C]
    K: intrinsics of ``color``                                  # [3, 3]
    angular_velocity: the camera's body-frame rotation rate, rad/s, camera frame (OpenCV)   # [3]
    readout_s: seconds from the first row's read-out to the last's (0, or no rotation: returned as it is)
    Returns [H, W, C], dtype and device of ``color``.
    """
    omega = angular_velocity.to(color.device, torch.float32).reshape(3)
    speed = omega.norm()
    if readout_s == 0 or float(speed) == 0:
        return color
    H, W = color.shape[:2]
    dev, dtype = color.device, torch.float32  # a 640 px image's coordinates to 1e-4 px
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    # the rays (x, y, 1) of the global-shutter pixels, separable: x [1, W], y [H, 1]
    x = ((torch.arange(W, dtype=dtype, device=dev) - cx) / fx)[None, :]
    y = ((torch.arange(H, dtype=dtype, device=dev) - cy) / fy)[:, None]
    kx, ky, kz = (omega / speed).tolist()
    along = kx * x + ky * y + kz  # [H, W] the rays' components along the axis, which the rotation keeps
    row = torch.arange(H, dtype=dtype, device=dev)[:, None]  # the source row, first guessed as the pixel's own
    for _ in range(ROW_ITERATIONS):
        angle = -float(speed) * ((row + 0.5) / H - 0.5) * readout_s  # rad, at the source pixel's row
        c, s = angle.cos(), angle.sin()
        keep = along * (1 - c)
        # Rodrigues: r c + (k x r) s + k (k . r)(1 - c), with r = (x, y, 1)
        rx = x * c + (ky - kz * y) * s + kx * keep
        ry = y * c + (kz * x - kx) * s + ky * keep
        rz = c + (kx * y - ky * x) * s + kz * keep
        rz = rz.clamp_min(1e-9)
        u_source, row = fx * rx / rz + cx, fy * ry / rz + cy  # [H, W]
    # grid_sample's normalised coordinates with pixel centres at integers (align_corners=False)
    grid = torch.stack([(2 * u_source + 1) / W - 1, (2 * row + 1) / H - 1], -1)
    image = color.permute(2, 0, 1)[None].to(torch.float32)
    out = F.grid_sample(image, grid[None], mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out[0].permute(1, 2, 0).to(color.dtype).contiguous()
