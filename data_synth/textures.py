"""Analytic colour textures on 2D surface coordinates.

A texture is a pure function ``(s, t) -> rgb`` of surface coordinates in metres (``s`` runs along
the surface to the viewer's right, ``t`` upwards on walls), so it can be evaluated at any sample
position: the renderer integrates it over a pixel footprint by supersampling. Colours are linear
albedo in [0, 1]. All parameters are plain JSON values, so a texture is rebuilt exactly from
``synth.json``.

Kinds (their parameters are listed in :data:`TEXTURE_PARAMS`):

- ``smooth``: a low-frequency sinusoidal blend of two colours (less than one cycle per metre),
  ``c0 + (c1 - c0) * (1/2 + 1/2 sin(2 pi (fs s + ft t) + phase))``.
- ``stripes``: a square wave like window blinds; ``a = s cos(angle) + t sin(angle)``, the phase
  ``f = frac(a / period)``; slats (``f < duty``) in ``c1`` shaded ``0.8 + 0.2 f / duty`` across
  the slat, gaps in ``c0``. ``angle = 90`` degrees gives horizontal slats.
- ``checker``: squares of side ``period`` in coordinates rotated by ``angle``;
  ``parity = (floor(a / period) + floor(b / period)) mod 2`` chooses ``c0`` or ``c1``.
- ``print``: lines of small glyph-like marks, like fine print. Glyph cells of ``cell_w x cell_h``
  metres; each glyph is a 5 x 7 bitmap taken from a hash of (key, line, column), with a spacing
  column and row, word gaps, ragged line ends and blank lines.
"""
from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

TEXTURE_PARAMS: dict[str, tuple[str, ...]] = {
    "smooth": ("c0", "c1", "fs", "ft", "phase"),
    "stripes": ("c0", "c1", "period", "duty", "angle"),
    "checker": ("c0", "c1", "period", "angle"),
    "print": ("paper", "ink", "cell_w", "cell_h", "line_spacing", "line_chars", "key"),
}
TEXTURE_KINDS = tuple(TEXTURE_PARAMS)

_MASK64 = (1 << 64) - 1
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser: a bijective avalanche on uint64 (wrapping arithmetic).  [...] -> [...]"""
    x = x ^ (x >> np.uint64(30))
    x = x * _MIX1
    x = x ^ (x >> np.uint64(27))
    x = x * _MIX2
    return x ^ (x >> np.uint64(31))


def hash_cells(key: int, *cells: np.ndarray) -> np.ndarray:
    """Deterministic 64-bit hash of integer cell indices.  cells: int64 arrays [...] -> uint64 [...]

    Platform independent (pure wrapping uint64 arithmetic); used for glyph bitmaps and line lengths.
    """
    with np.errstate(over="ignore"):
        shape = np.broadcast_shapes(*(c.shape for c in cells)) if cells else ()
        h = np.full(shape, np.uint64(int(key) & _MASK64), dtype=np.uint64)
        h = _mix64(h + _GOLDEN)
        for cell in cells:
            h = _mix64(h ^ (np.ascontiguousarray(cell, dtype=np.int64).view(np.uint64) + _GOLDEN))
    return h


@dataclass(frozen=True)
class Texture:
    """One analytic texture: ``kind`` (see :data:`TEXTURE_KINDS`) and its JSON parameters."""

    kind: str
    params: Mapping[str, Any]

    def to_dict(self) -> dict:
        return {"kind": self.kind, **{k: self.params[k] for k in TEXTURE_PARAMS[self.kind]}}

    @staticmethod
    def from_dict(data: Mapping[str, Any]) -> "Texture":
        """Rebuild from :meth:`to_dict` output; raises ValueError naming a bad kind or missing key."""
        kind = data.get("kind")
        if kind not in TEXTURE_PARAMS:
            raise ValueError(f"unknown texture kind {kind!r} (known: {', '.join(TEXTURE_KINDS)})")
        missing = [k for k in TEXTURE_PARAMS[kind] if k not in data]
        if missing:
            raise ValueError(f"texture of kind {kind!r} lacks {', '.join(missing)}")
        return Texture(kind, {k: data[k] for k in TEXTURE_PARAMS[kind]})


def _rgb(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float64).reshape(3)


def _rotated(s: np.ndarray, t: np.ndarray, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    quarter_turns = angle_deg / 90.0
    if quarter_turns == round(quarter_turns):  # exact for axis-aligned patterns
        ca, sa = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))[int(round(quarter_turns)) % 4]
    else:
        a = math.radians(angle_deg)
        ca, sa = math.cos(a), math.sin(a)
    return s * ca + t * sa, -s * sa + t * ca


def _frac(x: np.ndarray) -> np.ndarray:
    return x - np.floor(x)


def evaluate_texture(texture: Texture, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Albedo of ``texture`` at surface coordinates.  s [N], t [N] metres -> rgb [N, 3] float64 in [0, 1]"""
    p = texture.params
    s = np.asarray(s, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    kind = texture.kind
    if kind == "smooth":
        w = 0.5 + 0.5 * np.sin(2 * math.pi * (p["fs"] * s + p["ft"] * t) + p["phase"])
        c0, c1 = _rgb(p["c0"]), _rgb(p["c1"])
        return c0 + (c1 - c0) * w[:, None]
    if kind == "stripes":
        a, _ = _rotated(s, t, p["angle"])
        f = _frac(a / p["period"])
        slat = f < p["duty"]
        shade = 0.8 + 0.2 * f / p["duty"]
        return np.where(slat[:, None], _rgb(p["c1"]) * shade[:, None], _rgb(p["c0"]))
    if kind == "checker":
        a, b = _rotated(s, t, p["angle"])
        parity = (np.floor(a / p["period"]) + np.floor(b / p["period"])).astype(np.int64) & 1
        return np.where(parity[:, None] == 1, _rgb(p["c1"]), _rgb(p["c0"]))
    if kind == "print":
        return _evaluate_print(p, s, t)
    raise ValueError(f"unknown texture kind {kind!r} (known: {', '.join(TEXTURE_KINDS)})")


def _evaluate_print(p: Mapping[str, Any], s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Fine print: 5 x 7 glyph bitmaps in 6 x 8 sub-cells (one spacing column and row per cell)."""
    key = int(p["key"])
    line_pos = -t / (p["cell_h"] * p["line_spacing"])  # lines run downwards
    line = np.floor(line_pos).astype(np.int64)
    fy = _frac(line_pos) * p["line_spacing"]  # [0, line_spacing): glyph band where < 1
    col_pos = s / p["cell_w"]
    col = np.floor(col_pos).astype(np.int64)
    fx = _frac(col_pos)
    gx = np.floor(fx * 6).astype(np.int64)  # 0..4 ink columns, 5 spacing
    gy = np.floor(np.minimum(fy, 1.0) * 8).astype(np.int64)  # 0..6 ink rows, 7 spacing / gap
    glyph = hash_cells(key, line, col)
    line_hash = hash_cells(key ^ 0x5EED, line)
    chars = int(p["line_chars"])
    line_len = (chars // 2 + (line_hash % np.uint64(chars // 2 + 1))).astype(np.int64)
    blank_line = (line_hash >> np.uint64(40)) % np.uint64(7) == 0
    word_gap = (glyph >> np.uint64(40)) % np.uint64(6) == 0
    inside = (gx < 5) & (gy < 7) & (np.mod(col, chars) < line_len) & ~blank_line & ~word_gap
    bit_index = np.clip(gy * 5 + gx, 0, 34).astype(np.uint64)
    bit = ((glyph >> bit_index) & np.uint64(1)) == 1
    ink = inside & bit
    paper, ink_rgb = _rgb(p["paper"]), _rgb(p["ink"])
    return np.where(ink[:, None], ink_rgb, paper)


# ----------------------------------------------------------------------------- random textures
def random_colour_pair(rng: np.random.Generator, contrast: str = "high") -> tuple[list[float], list[float]]:
    """Two colours of one random hue: a dark one and a light one (or close ones for ``low``)."""
    hue = float(rng.uniform(0, 1))
    sat0, sat1 = float(rng.uniform(0.15, 0.7)), float(rng.uniform(0.1, 0.6))
    hue1 = (hue + float(rng.uniform(-0.15, 0.15))) % 1.0
    if contrast == "high":
        v0, v1 = float(rng.uniform(0.12, 0.35)), float(rng.uniform(0.7, 0.92))
    else:
        v0 = float(rng.uniform(0.45, 0.6))
        v1 = v0 + float(rng.uniform(0.1, 0.2))
    c0 = [round(c, 6) for c in colorsys.hsv_to_rgb(hue, sat0, v0)]
    c1 = [round(c, 6) for c in colorsys.hsv_to_rgb(hue1, sat1, v1)]
    return c0, c1


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return round(float(math.exp(rng.uniform(math.log(low), math.log(high)))), 6)


def random_texture(rng: np.random.Generator, kind: str, *, fine: bool = False) -> Texture:
    """A random texture of ``kind``; ``fine`` picks the high-frequency end of each parameter range."""
    if kind == "smooth":
        c0, c1 = random_colour_pair(rng, "low")
        return Texture("smooth", {
            "c0": c0, "c1": c1,
            "fs": round(float(rng.uniform(-0.8, 0.8)), 6), "ft": round(float(rng.uniform(-0.8, 0.8)), 6),
            "phase": round(float(rng.uniform(0, 2 * math.pi)), 6),
        })
    if kind == "stripes":
        c0, c1 = random_colour_pair(rng)
        period = _log_uniform(rng, 0.006, 0.015) if fine else _log_uniform(rng, 0.012, 0.04)
        angle = 90.0 if rng.uniform() < 0.6 else round(float(rng.choice([0.0, 45.0, 75.0, 120.0])), 6)
        return Texture("stripes", {"c0": c0, "c1": c1, "period": period,
                                   "duty": round(float(rng.uniform(0.55, 0.75)), 6), "angle": angle})
    if kind == "checker":
        c0, c1 = random_colour_pair(rng)
        period = _log_uniform(rng, 0.004, 0.012) if fine else _log_uniform(rng, 0.012, 0.12)
        angle = 0.0 if rng.uniform() < 0.5 else round(float(rng.uniform(10, 40)), 6)
        return Texture("checker", {"c0": c0, "c1": c1, "period": period, "angle": angle})
    if kind == "print":
        paper_v = float(rng.uniform(0.8, 0.95))
        paper = [round(c, 6) for c in colorsys.hsv_to_rgb(float(rng.uniform(0, 1)), float(rng.uniform(0, 0.15)), paper_v)]
        ink = [round(c, 6) for c in colorsys.hsv_to_rgb(float(rng.uniform(0, 1)), float(rng.uniform(0.2, 0.8)),
                                                        float(rng.uniform(0.05, 0.3)))]
        cell_w = _log_uniform(rng, 0.003, 0.005) if fine else _log_uniform(rng, 0.004, 0.009)
        return Texture("print", {
            "paper": paper, "ink": ink, "cell_w": cell_w, "cell_h": round(cell_w * float(rng.uniform(1.3, 1.6)), 6),
            "line_spacing": round(float(rng.uniform(1.3, 1.8)), 6), "line_chars": int(rng.integers(30, 80)),
            "key": int(rng.integers(0, 2**31 - 1)),
        })
    raise ValueError(f"unknown texture kind {kind!r} (known: {', '.join(TEXTURE_KINDS)})")
