"""A rolling-shutter colour image moved to one instant: every row as the camera saw it at the frame's time.

A rolling-shutter camera (most colour sensors of consumer RGB-D cameras) reads its rows top to bottom over a
read-out time ``readout_s``; row ``v`` of an ``H``-row image is taken at
``t_v = t + ((v + 0.5) / H - 0.5) * readout_s`` (the frame's timestamp ``t`` is the middle row's instant,
pixel centres at integer coordinates). Under fast rotation the rows then disagree about where the camera
was: at 60 deg/s and a 30 ms read-out the top and bottom rows are 1.8 deg apart. Renderers and alignments
assume one pose per image, so the image is resampled into the one a global shutter at ``t`` would have taken.

Motion model: the camera moves at a constant body-frame velocity (``v`` m/s and ``omega`` rad/s, camera
frame) over the read-out, to first order in the row's time ``dt``: at ``t + dt`` it is turned by
``R = exp(omega * dt)`` and moved by ``v * dt``. The point ``X = z K^-1 q`` that the global-shutter pixel ``q``
sees at ``t`` (``z`` its depth) is then seen at ``p = pi(K R^T (X - v dt(p)))``, ``dt(p)`` from ``p``'s own row,
found by fixed-point steps from ``q``'s row. Without depth the translation is left out (the rotation-only
rectification of Forssen and Ringaby, "Rectifying rolling shutter video from hand-held devices", CVPR 2010);
with it, a camera that travels while it turns to keep a point in view (TUM's fr1_xyz: 0.36 m/s and 20 deg/s)
is not over-corrected: there the two motions' shifts of the image partly cancel.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


# Fixed-point steps on the source row: the row moves by under a pixel per step once the first has moved it,
# for rotations of a few degrees over the read-out.
ROW_ITERATIONS = 2
FIELD_MAX_PIXELS = 16384


def row_time(rows: torch.Tensor, height: int, readout_s: float) -> torch.Tensor:
    """Seconds from the frame's instant to the read-out of (fractional) rows ``rows`` of an image ``height``
    rows high (module docstring); shape and dtype of ``rows``."""
    return ((rows + 0.5) / height - 0.5) * readout_s


def row_times(height: int, readout_s: float, dtype: torch.dtype = torch.float64,
              device: torch.device | str = "cpu") -> torch.Tensor:
    """:func:`row_time` of every row.  -> [H]"""
    return row_time(torch.arange(height, dtype=dtype, device=device), height, readout_s)


def colour_at_frame_instant(color: torch.Tensor, K: torch.Tensor, velocity: torch.Tensor, readout_s: float,
                            depth: torch.Tensor | None = None) -> torch.Tensor:
    """The image a global shutter would have taken at the frame's instant (module docstring); bilinear reads,
    the border repeated where a ray leaves the image.

    color: colour in [0, 1]                                     # [H, W, C]
    K: intrinsics of ``color``                                  # [3, 3]
    velocity: the camera's body-frame velocity [v (m/s), omega (rad/s)], camera frame (OpenCV)   # [6]
    readout_s: seconds from the first row's read-out to the last's (0, or a camera at rest: returned as it is)
    depth: metres at ``color``'s pixels, 0 = none (None: the translation is left out); a pixel without depth
        takes the image's median depth                      # [H, W]
    Returns [H, W, C], dtype and device of ``color``.
    """
    dev, dtype = color.device, torch.float32  # a 640 px image's coordinates to 1e-4 px
    velocity = velocity.to(dev, torch.float64).reshape(6)
    vx, vy, vz = velocity[:3].tolist() if depth is not None else (0.0, 0.0, 0.0)
    omega = velocity[3:]
    speed = float(omega.norm())
    if readout_s == 0 or (speed == 0 and vx == vy == vz == 0):
        return color
    H, W = color.shape[:2]
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    # The source field is smooth: computed on every step-th pixel (under FIELD_MAX_PIXELS, where torch runs an
    # elementwise op on one thread instead of paying a parallel region per op) and interpolated.
    step = max(1, math.ceil(math.sqrt(H * W / FIELD_MAX_PIXELS)))
    # the points z (x, y, 1) the global-shutter pixels see: x [1, w], y [h, 1], z [h, w] or 1
    centre = (step - 1) / 2  # of each step x step block, as the interpolation below places its samples
    u = torch.arange(0, W, step, dtype=dtype, device=dev) + centre
    v = torch.arange(0, H, step, dtype=dtype, device=dev) + centre
    x, y = ((u - cx) / fx)[None, :], ((v - cy) / fy)[:, None]
    z = torch.ones((), dtype=dtype, device=dev)
    if depth is not None:
        depth = depth.to(dev, dtype)[(step - 1) // 2::step, (step - 1) // 2::step][:len(v), :len(u)]
        valid = depth > 0
        fill = depth[valid].median() if bool(valid.any()) else z
        z = torch.where(valid, depth, fill)
    kx, ky, kz = (omega / speed).tolist() if speed > 0 else (0.0, 0.0, 1.0)
    row = v[:, None]  # the source row, first guessed as the pixel's own
    for _ in range(ROW_ITERATIONS):
        dt = row_time(row, H, readout_s)  # seconds, at the source pixel's row
        px, py, pz = z * x - vx * dt, z * y - vy * dt, z - vz * dt  # X - v dt
        angle = -speed * dt  # R^T: the turn undone
        c, s = angle.cos(), angle.sin()
        keep = (kx * px + ky * py + kz * pz) * (1 - c)
        # Rodrigues: r c + (k x r) s + k (k . r)(1 - c)
        rx = px * c + (ky * pz - kz * py) * s + kx * keep
        ry = py * c + (kz * px - kx * pz) * s + ky * keep
        rz = (pz * c + (kx * py - ky * px) * s + kz * keep).clamp_min(1e-9)
        u_source, row = fx * rx / rz + cx, fy * ry / rz + cy  # [h, w]
    # grid_sample's normalised coordinates with pixel centres at integers (align_corners=False), interpolated
    # from the blocks' centres to every pixel (exact where the field is linear)
    grid = torch.stack([(2 * u_source + 1) / W - 1, (2 * row + 1) / H - 1])[None]  # [1, 2, h, w]
    if step > 1:
        grid = F.interpolate(grid, size=(H, W), mode="bilinear", align_corners=False)
    image = color.permute(2, 0, 1)[None].to(torch.float32)
    out = F.grid_sample(image, grid.permute(0, 2, 3, 1), mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out[0].permute(1, 2, 0).to(color.dtype).contiguous()
