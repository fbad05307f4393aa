"""Optional sensor realism applied to exact renders (all off by default).

Each effect draws from its own random stream, seeded by ``(seed, effect, frame)``, so switching
one effect on or off never changes what another one does, and a frame's noise does not depend on
which other frames are generated.

- Depth noise: ``z' = z + sigma * z^2 * n``, ``n ~ N(0, 1)``; sigma (``depth_noise``) is the
  standard deviation in metres at 1 m (structured-light sensors grow with z^2, Khoshelham and
  Elberink 2012). Negative results become 0 (no measurement).
- Depth holes: each pixel drops out (depth 0) with probability ``depth_holes``, and every pixel
  beside a depth discontinuity (a 4-neighbour more than ``DISCONTINUITY_RELATIVE`` of its depth
  nearer or farther) drops out as well, as at the shadowed edges of real RGB-D depth maps. The
  discontinuities are found on the exact depth, before noise.
- Radial depth bias: ``z' = z * (1 + b * r^2)``, ``r^2 = ((u - cx) / cx)^2 + ((v - cy) / cy)^2`` with the
  image centre ``(cx, cy) = ((W - 1) / 2, (H - 1) / 2)`` (0 at the centre, 1 at the middle of each edge, 2 at the
  corners); b (``depth_radial_bias``) is the relative error at the edges, as the spatially varying depth
  distortion of structured-light sensors (Herrera, Kannala and Heikkila 2012). Applied before the noise.
- Exposure: per frame a gain ``exp(jitter * n1)`` and a bias ``jitter / 4 * n2``
  (``n1, n2 ~ N(0, 1)``), colour ``clip(gain * c + bias, 0, 1)``; the values go to synth.json.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DISCONTINUITY_RELATIVE = 0.1
_STREAM_DEPTH_NOISE = 1
_STREAM_DEPTH_HOLES = 2
_STREAM_EXPOSURE = 3


@dataclass(frozen=True)
class SensorOptions:
    """Strength of each effect; 0 switches it off."""

    depth_noise: float = 0.0  # metres of standard deviation at 1 m depth (scales with z^2)
    depth_holes: float = 0.0  # probability of a random dropout per pixel (and holes at discontinuities)
    exposure_jitter: float = 0.0  # standard deviation of log gain per frame (bias: a quarter of it)
    depth_radial_bias: float = 0.0  # relative depth error at the middle of the image's edges (twice at the corners)

    def to_dict(self, exposure: np.ndarray | None = None) -> dict:
        return {
            "depth_noise": self.depth_noise,
            "depth_noise_model": "z + depth_noise * z^2 * N(0, 1); depth_noise is the std in metres at 1 m",
            "depth_holes": self.depth_holes,
            "depth_holes_model": (f"random dropouts with probability depth_holes, plus every pixel beside a "
                                  f"depth jump larger than {DISCONTINUITY_RELATIVE} of its depth (when depth_holes > 0)"),
            "depth_radial_bias": self.depth_radial_bias,
            "depth_radial_bias_model": "z * (1 + depth_radial_bias * r^2), r = 1 at the middle of each image edge",
            "exposure_jitter": self.exposure_jitter,
            "exposure_model": "color = clip(gain * color + bias, 0, 1) per frame",
            "exposure": [] if exposure is None else [[float(g), float(b)] for g, b in exposure],
        }


def _rng(seed: int, stream: int, frame: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), stream, int(frame)])


def exposure_parameters(seed: int, frames: int, jitter: float) -> np.ndarray:
    """Per-frame (gain, bias).  -> [frames, 2]; (1, 0) everywhere when jitter is 0."""
    out = np.zeros((frames, 2))
    out[:, 0] = 1.0
    if jitter > 0:
        for i in range(frames):
            n1, n2 = _rng(seed, _STREAM_EXPOSURE, i).standard_normal(2)
            out[i] = (float(np.exp(jitter * n1)), float(jitter / 4 * n2))
    return out


def apply_exposure(color: np.ndarray, gain: float, bias: float) -> np.ndarray:
    """color [H, W, 3] float32 in [0, 1] -> [H, W, 3] float32 in [0, 1]"""
    return np.clip(gain * color + bias, 0.0, 1.0).astype(np.float32)


def depth_discontinuities(depth: np.ndarray, relative: float = DISCONTINUITY_RELATIVE) -> np.ndarray:
    """Pixels beside a depth jump (either side).  depth [H, W] metres -> bool [H, W]"""
    edge = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        a = np.moveaxis(depth, axis, 0)
        jump = np.abs(a[1:] - a[:-1]) > relative * np.minimum(a[1:], a[:-1])
        e = np.moveaxis(edge, axis, 0)
        e[1:] |= jump
        e[:-1] |= jump
    return edge


def apply_depth_effects(depth: np.ndarray, options: SensorOptions, seed: int, frame: int) -> np.ndarray:
    """Radial bias, noise, then holes, on an exact depth map.  depth [H, W] float32 metres -> [H, W] float32"""
    out = depth.astype(np.float64)
    if options.depth_radial_bias != 0:
        H, W = depth.shape
        cy, cx = (H - 1) / 2, (W - 1) / 2
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        out = out * (1 + options.depth_radial_bias * (((u - cx) / max(cx, 0.5)) ** 2 + ((v - cy) / max(cy, 0.5)) ** 2))
    if options.depth_noise > 0:
        noise = _rng(seed, _STREAM_DEPTH_NOISE, frame).standard_normal(depth.shape)
        out = out + options.depth_noise * out * out * noise
        out[(out < 0) | (depth <= 0)] = 0.0
    if options.depth_holes > 0:
        dropout = _rng(seed, _STREAM_DEPTH_HOLES, frame).random(depth.shape) < options.depth_holes
        out[dropout | depth_discontinuities(depth)] = 0.0
    return out.astype(np.float32)
