"""Reading and downscaling RGB-D images, with validation at the boundary.

Every function here is pure (arrays in, arrays out) except the two readers, which read one file.
A reader either returns a valid image or raises :class:`~mipslam.errors.DatasetError` naming the
file; it never returns a half-decoded image:

* OpenCV's decoder pads a truncated JPEG with grey and only warns ("Premature end of JPEG file"),
  so a JPEG must end its last scan with the end-of-image marker (``FF D9`` after the last
  ``FF DA``); a PNG must contain its ``IEND`` chunk. Other formats rely on the decoder.
* Colour must be 8-bit with 3 channels (BGR in the file, RGB out); depth must be 16-bit with one
  channel (the stored value divided by ``depth_scale`` is metres, 0 = no measurement).

Downscaling by an integer factor ``d`` (crop to multiples of ``d`` at the right and bottom first,
which leaves the principal point unchanged):

* colour: the mean over each ``d x d`` block (area averaging; the box filter of the larger pixels).
* depth: never the mean across a depth edge. Per block, the valid samples (finite, > 0) are sorted
  and split into surface clusters wherever two consecutive sorted values differ by more than
  ``edge_gap`` relative to the smaller one (5 % by default: far above sensor quantisation and
  noise within one block, far below a typical occlusion step). The output is the mean of the
  *nearest* cluster (the surface in front, the one that occludes the rest inside the big pixel).
  A block with fewer than ``min_valid_fraction`` (default 1/2) valid samples is invalid (0).
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch

from mipslam.errors import DatasetError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
DEPTH_EDGE_RELATIVE_GAP = 0.05
DEPTH_MIN_VALID_FRACTION = 0.5


def _read_bytes(path: Path, what: str) -> np.ndarray:
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except FileNotFoundError:
        raise DatasetError(path, f"{what} image file not found") from None
    except (IsADirectoryError, PermissionError, OSError) as exc:
        raise DatasetError(path, f"cannot read {what} image ({exc.strerror or exc})") from None
    if data.size == 0:
        raise DatasetError(path, f"{what} image file is empty; re-copy or regenerate it")
    return data


def _check_complete(data: np.ndarray, path: Path, what: str) -> None:
    """Reject files whose container shows they were cut short (see module docstring)."""
    head = data[:8].tobytes()
    raw = data.tobytes()
    truncated = False
    if head.startswith(PNG_SIGNATURE):
        truncated = raw.rfind(b"IEND") < 0
    elif head.startswith(JPEG_SIGNATURE):
        last_scan = raw.rfind(b"\xff\xda")
        truncated = last_scan < 0 or raw.rfind(b"\xff\xd9") < last_scan
    if truncated:
        raise DatasetError(path, f"{what} image is truncated (the file ends before the image data does); re-copy it")


def _decode(path: Path, what: str) -> np.ndarray:
    data = _read_bytes(path, what)
    _check_complete(data, path, what)
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise DatasetError(path, f"cannot decode {what} image ({str(exc).strip().splitlines()[-1]})") from None
    if image is None:
        raise DatasetError(path, f"unreadable or truncated {what} image (OpenCV cannot decode it); re-copy it")
    return image


def read_color(path: str | Path) -> np.ndarray:
    """Read an 8-bit 3-channel image file as float32 RGB in [0, 1].  -> [H, W, 3]

    Raises DatasetError (naming ``path``) for a missing, empty, truncated or undecodable file and
    for any other bit depth or channel count.
    """
    path = Path(path)
    image = _decode(path, "colour")
    if image.dtype != np.uint8:
        raise DatasetError(path, f"colour image must be 8-bit, got {image.dtype} ({_bits(image)}-bit); convert it to 8-bit RGB")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.ndim != 3 or channels != 3:
        raise DatasetError(path, f"colour image must have 3 channels (RGB), got {channels}; convert it to 8-bit RGB")
    rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return rgb.astype(np.float32) * np.float32(1.0 / 255.0)


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """Read a 16-bit single-channel depth image as float32 metres (``value / depth_scale``).  -> [H, W]

    0 (and anything non-finite) means no measurement. Raises DatasetError (naming ``path``) for a
    missing, empty, truncated or undecodable file and for any other bit depth or channel count.
    """
    path = Path(path)
    if not depth_scale > 0 or not math.isfinite(depth_scale):
        raise DatasetError(path, f"depth scale must be a positive number, got {depth_scale}")
    image = _decode(path, "depth")
    if image.dtype != np.uint16:
        raise DatasetError(
            path, f"depth image must be 16-bit (uint16), got {image.dtype} ({_bits(image)}-bit); store depth * scale as uint16 PNG"
        )
    if image.ndim != 2:
        raise DatasetError(path, f"depth image must have 1 channel, got {image.shape[2]}; store it as single-channel uint16 PNG")
    depth = image.astype(np.float32) / np.float32(depth_scale)
    depth[~np.isfinite(depth)] = 0.0
    return depth


def _bits(image: np.ndarray) -> int:
    return image.dtype.itemsize * 8


def crop_to_multiple(image: np.ndarray, factor: int) -> np.ndarray:
    """Crop the right and bottom so height and width are multiples of ``factor``.  [H, W, ...] -> [H', W', ...]"""
    height, width = image.shape[:2]
    return image[: height - height % factor, : width - width % factor]


def _block_samples(image: np.ndarray, factor: int) -> list[np.ndarray]:
    """The ``factor * factor`` samples of every block, row-major within the block.  [H, W, ...] (multiples of
    factor) -> factor * factor views [H / f, W / f, ...]"""
    return [image[dy::factor, dx::factor] for dy in range(factor) for dx in range(factor)]


def downscale_color(color: np.ndarray, factor: int) -> np.ndarray:
    """Area-average an image by an integer factor.  color [H, W, C] float -> [H // f, W // f, C]

    The block sums are taken in float64 (exact for 8-bit colour), then divided by ``f * f``."""
    if factor == 1:
        return color
    samples = _block_samples(crop_to_multiple(color, factor), factor)
    total = samples[0].astype(np.float64)
    for sample in samples[1:]:
        total += sample
    total /= factor * factor
    return total.astype(color.dtype)


def _sorted_samples(samples: list[np.ndarray]) -> list[np.ndarray]:
    """Element-wise ascending order of equally shaped arrays (a sorting network for 4, else np.sort)."""
    if len(samples) == 4:
        a, b, c, d = samples
        a, b = np.minimum(a, b), np.maximum(a, b)
        c, d = np.minimum(c, d), np.maximum(c, d)
        a, c = np.minimum(a, c), np.maximum(a, c)
        b, d = np.minimum(b, d), np.maximum(b, d)
        b, c = np.minimum(b, c), np.maximum(b, c)
        return [a, b, c, d]
    return list(np.sort(np.stack(samples), axis=0))


def downscale_depth(
    depth: np.ndarray,
    factor: int,
    edge_gap: float = DEPTH_EDGE_RELATIVE_GAP,
    min_valid_fraction: float = DEPTH_MIN_VALID_FRACTION,
) -> np.ndarray:
    """Downscale depth by an integer factor without mixing surfaces.  depth [H, W] metres -> [H // f, W // f]

    Per ``f x f`` block: the mean of the nearest surface cluster (clusters split where sorted
    neighbours differ by more than ``edge_gap`` relative), or 0 where fewer than
    ``ceil(min_valid_fraction * f * f)`` samples are valid. See the module docstring.
    """
    if factor == 1:
        return depth
    cropped = crop_to_multiple(depth, factor).astype(np.float64)
    samples = np.where(np.isfinite(cropped) & (cropped > 0), cropped, np.inf)  # invalid sorts last
    ordered = _sorted_samples(_block_samples(samples, factor))  # f*f of [h, w], ascending
    in_nearest = np.isfinite(ordered[0])
    count = in_nearest.astype(np.int64)  # valid samples of the block
    size = in_nearest.astype(np.int64)  # samples of its nearest cluster
    total = np.where(in_nearest, ordered[0], 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        for previous, sample in zip(ordered[:-1], ordered[1:]):
            finite = np.isfinite(sample)
            count += finite
            # a break (inf / finite too) ends the nearest cluster; inf / inf is nan -> no break, but not finite
            in_nearest &= finite & ~(sample / previous > 1.0 + edge_gap)
            total += np.where(in_nearest, sample, 0.0)
            size += in_nearest
    needed = max(1, math.ceil(min_valid_fraction * factor * factor))
    out = np.where((count >= needed) & (size > 0), total / np.maximum(size, 1), 0.0)
    return out.astype(np.float32)


class LensUndistortion:
    """Removes radial-tangential lens distortion (OpenCV's model) from the images of one camera.

    ``camera`` = (fx, fy, cx, cy) px and ``coefficients`` = (k1, k2, p1, p2[, k3]) of the images on disk,
    ``size`` = (width, height). The undistorted image keeps the same intrinsics and size (a pinhole
    camera with the given fx..cy), so nothing downstream changes. Colour is resampled bilinearly;
    depth (metres, 0 = none) takes the nearest sample, never a mix of two surfaces. Output pixels whose
    source lies outside the image get colour 0 and depth 0 (no measurement).
    """

    def __init__(self, camera: tuple[float, float, float, float], coefficients: tuple[float, ...],
                 size: tuple[int, int]):
        fx, fy, cx, cy = camera
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        D = np.asarray(coefficients, dtype=np.float64)
        # [H, W] float32 each: for every output pixel, where to sample the distorted image
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(K, D, None, K, tuple(size), cv2.CV_32FC1)

    def color(self, color: np.ndarray) -> np.ndarray:
        """color [H, W, 3] float in [0, 1] -> [H, W, 3]"""
        return cv2.remap(color, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """depth [H, W] metres -> [H, W] (nearest sample; 0 outside the source image)"""
        return cv2.remap(depth, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)


class DepthRegistration:
    """Moves depth images taken by a second camera into the colour camera (depth not registered to colour: a raw
    Kinect's, whose depth camera sits a few centimetres beside the colour camera with another focal length).

    ``depth_camera`` = (fx, fy, cx, cy) px of the depth images on disk, ``T_cd`` [4, 4] float64 the depth camera's
    pose in the colour camera's frame (metres), ``color_camera`` = (fx, fy, cx, cy) px and ``size`` = (width,
    height) of the colour images. Each depth pixel's point ``X_c = T_cd K_d^-1 [u, v, 1] z`` is projected into the
    colour image and written, as its colour-frame depth, to every colour pixel whose centre its footprint covers
    (at least the nearest one), the nearest surface winning where several land: so no depth mixes two surfaces,
    and a depth grid finer or coarser than the colour grid leaves no holes inside a surface. Colour pixels that no
    depth point reaches (the part of the view the depth camera does not see, and what it sees behind an occluding
    edge from its other position) get 0, no measurement. Lens distortion of the depth camera is not modelled.
    """

    MAX_FOOTPRINT_PX = 4  # colour pixels per side one depth pixel may fill (a depth camera at most 4x finer)

    def __init__(self, depth_camera: tuple[float, float, float, float], T_cd: np.ndarray,
                 color_camera: tuple[float, float, float, float], size: tuple[int, int]):
        self.depth_camera = tuple(float(v) for v in depth_camera)
        self.color_camera = tuple(float(v) for v in color_camera)
        self.T_cd = np.asarray(T_cd, dtype=np.float64)
        self._rotation = torch.from_numpy(self.T_cd[:3, :3].T.copy()).to(torch.float32)  # for row vectors
        self._translation = torch.from_numpy(self.T_cd[:3, 3].copy()).to(torch.float32)
        self.width, self.height = int(size[0]), int(size[1])
        self._rays: dict[tuple[int, int], torch.Tensor] = {}

    def _depth_rays(self, height: int, width: int) -> torch.Tensor:
        """Rays (x / z, y / z, 1) of the depth camera's pixel centres, [height * width, 3] float32."""
        rays = self._rays.get((height, width))
        if rays is None:
            fx, fy, cx, cy = self.depth_camera
            v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                                  indexing="ij")
            rays = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1).reshape(-1, 3)
            self._rays[(height, width)] = rays
        return rays

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """depth [H_d, W_d] metres in the depth camera (0 = none) -> [height, width] metres in the colour camera"""
        z = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)).reshape(-1)
        valid = torch.isfinite(z) & (z > 0)
        X_d = self._depth_rays(*depth.shape)[valid] * z[valid, None]  # [N, 3] depth camera frame
        X_c = X_d @ self._rotation + self._translation  # [N, 3] colour camera frame
        front = X_c[:, 2] > 1e-6
        X_c, z_d = X_c[front], z[valid][front]
        z_c = X_c[:, 2]
        fx, fy, cx, cy = self.color_camera
        u, v = fx * X_c[:, 0] / z_c + cx, fy * X_c[:, 1] / z_c + cy
        # half the footprint of a depth pixel in colour pixels: it spans z_d / fx_d metres at its depth
        half_u = 0.5 * fx * z_d / (self.depth_camera[0] * z_c)
        half_v = 0.5 * fy * z_d / (self.depth_camera[1] * z_c)
        out = torch.full((self.height * self.width,), math.inf, dtype=torch.float32)
        first_u, last_u = _covered_centres(u, half_u)
        first_v, last_v = _covered_centres(v, half_v)
        span_u = int((last_u - first_u).max()) + 1 if len(u) else 0
        span_v = int((last_v - first_v).max()) + 1 if len(v) else 0
        for dv in range(span_v):
            for du in range(span_u):
                col, row = first_u + du, first_v + dv
                inside = ((col <= last_u) & (row <= last_v) & (col >= 0) & (col < self.width) & (row >= 0)
                          & (row < self.height))
                out.scatter_reduce_(0, row[inside] * self.width + col[inside], z_c[inside], reduce="amin")
        out[torch.isinf(out)] = 0.0
        return out.reshape(self.height, self.width).numpy()


def _covered_centres(x: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last integer pixel centre in ``[x - half, x + half]`` (the nearest one where none is), at most
    ``DepthRegistration.MAX_FOOTPRINT_PX`` of them.  [N] float32 each -> [N] int64 each"""
    first = torch.ceil(x - half)
    last = torch.floor(x + half)
    none = last < first
    nearest = torch.round(x)
    first = torch.where(none, nearest, first)
    last = torch.where(none, nearest, torch.minimum(last, first + DepthRegistration.MAX_FOOTPRINT_PX - 1))
    return first.to(torch.int64), last.to(torch.int64)
