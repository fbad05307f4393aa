"""Statistics of bench rows (pure): medians and spread per setting, the Pareto front, power-law fits.

* :func:`spread` of repeated measurements: median, min, max and the interquartile range (linear
  interpolation between order statistics, numpy's default);
* :func:`summarize` groups rows by setting; medians are over the rows without an error, and a
  setting with no such row has no values (it is never on the front);
* :func:`pareto_front` marks the points no other point dominates: ``j`` dominates ``i`` when it is
  at least as good in every objective and strictly better in one (frames/s higher, ATE lower,
  PSNR higher);
* :func:`fit_power_law` fits ``y = c x^p`` by least squares on ``log y = log c + p log x``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from mipslam.bench.execute import JobResult
from mipslam.errors import MipslamError

__all__ = ["PowerLaw", "SettingSummary", "Spread", "fit_power_law", "pareto_front", "spread", "summarize"]

STAGE_ORDER = ("tracking", "keyframe", "mapping", "loop", "pgo", "refine")


@dataclass(frozen=True)
class Spread:
    """Median and spread of ``n`` repeated values (all finite)."""

    n: int
    median: float
    min: float
    max: float
    q1: float
    q3: float

    def to_dict(self) -> dict[str, float | int]:
        return {"n": self.n, "median": self.median, "min": self.min, "max": self.max, "q1": self.q1, "q3": self.q3}


def spread(values: Sequence[float | None]) -> Spread | None:
    """Spread of the finite values (None and NaN/inf skipped); None when there is none."""
    finite = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if finite.size == 0:
        return None
    q1, median, q3 = np.percentile(finite, [25, 50, 75])
    return Spread(int(finite.size), float(median), float(finite.min()), float(finite.max()), float(q1), float(q3))


@dataclass(frozen=True)
class SettingSummary:
    """One setting over its repeats. ``on_front_ate`` / ``on_front_psnr``: on the Pareto front of
    (frames/s up, ATE down) / (frames/s up, PSNR up) among the settings of the bench."""

    setting_index: int
    setting: str
    preset: str | None
    assignments: tuple[str, ...]
    jobs: int
    failed: int
    errors: tuple[str, ...]
    fps: Spread | None
    ate_rmse_cm: Spread | None
    psnr_db: Spread | None
    wall_s: Spread | None
    gaussians: Spread | None
    keyframes: Spread | None
    stage_ms_per_frame: dict[str, Spread] = field(default_factory=dict)
    on_front_ate: bool = False
    on_front_psnr: bool = False
    system: str = "mipslam"
    rpe_trans_cm: Spread | None = None
    rpe_rot_deg: Spread | None = None
    lost_frames: Spread | None = None
    psnr_train_db: Spread | None = None  # training views (keyframes); psnr_db is of the novel views

    def to_dict(self) -> dict[str, Any]:
        def d(value):
            return None if value is None else value.to_dict()

        return {
            "setting_index": self.setting_index, "setting": self.setting, "preset": self.preset,
            "assignments": list(self.assignments), "jobs": self.jobs, "failed": self.failed,
            "errors": list(self.errors), "fps": d(self.fps), "ate_rmse_cm": d(self.ate_rmse_cm),
            "psnr_db": d(self.psnr_db), "psnr_train_db": d(self.psnr_train_db), "wall_s": d(self.wall_s),
            "gaussians": d(self.gaussians),
            "keyframes": d(self.keyframes), "system": self.system, "rpe_trans_cm": d(self.rpe_trans_cm),
            "rpe_rot_deg": d(self.rpe_rot_deg), "lost_frames": d(self.lost_frames),
            "stage_ms_per_frame": {k: v.to_dict() for k, v in self.stage_ms_per_frame.items()},
            "pareto_front": {"fps_vs_ate": self.on_front_ate, "fps_vs_psnr": self.on_front_psnr},
        }


def ordered_stages(names) -> list[str]:
    """Stage names in pipeline order (known ones first), the rest alphabetically."""
    names = set(names)
    return [s for s in STAGE_ORDER if s in names] + sorted(names - set(STAGE_ORDER))


def pareto_front(points: Sequence[Sequence[float | None]], maximize: Sequence[bool]) -> list[bool]:
    """For each point (one value per objective), whether no other point dominates it.

    A point with a missing or non-finite value is never on the front and dominates nothing. ``maximize[k]``
    says whether objective k is better higher (frames/s, PSNR) or lower (ATE).
    """
    signs = np.array([1.0 if m else -1.0 for m in maximize])
    valid = [all(v is not None and math.isfinite(v) for v in p) and len(p) == len(maximize) for p in points]
    scored = [signs * np.asarray(p, dtype=np.float64) if ok else None for p, ok in zip(points, valid)]
    front = []
    for i, a in enumerate(scored):
        if a is None:
            front.append(False)
            continue
        dominated = any(b is not None and j != i and bool(np.all(b >= a)) and bool(np.any(b > a))
                        for j, b in enumerate(scored))
        front.append(not dominated)
    return front


def summarize(rows: Sequence[JobResult]) -> list[SettingSummary]:
    """Per setting (in setting order): counts, errors, median/spread of every measurement, Pareto marks."""
    groups: dict[int, list[JobResult]] = {}
    for row in rows:
        groups.setdefault(row.setting_index, []).append(row)
    partial = []
    for index in sorted(groups):
        group = groups[index]
        good = [r for r in group if r.ok]
        stages = ordered_stages(s for r in good for s in r.stage_ms_per_frame)
        stage_spreads = {s: spread([r.stage_ms_per_frame.get(s) for r in good]) for s in stages}
        partial.append(dict(
            setting_index=index, setting=group[0].setting, preset=group[0].preset,
            assignments=tuple(group[0].assignments), jobs=len(group), failed=len(group) - len(good),
            errors=tuple(f"repeat {r.repeat}: {r.error}" for r in group if not r.ok),
            fps=spread([r.fps for r in good]), ate_rmse_cm=spread([r.ate_rmse_cm for r in good]),
            psnr_db=spread([r.psnr_db for r in good]), psnr_train_db=spread([r.psnr_train_db for r in good]),
            wall_s=spread([r.wall_s for r in good]),
            gaussians=spread([r.gaussians for r in good]), keyframes=spread([r.keyframes for r in good]),
            stage_ms_per_frame={k: v for k, v in stage_spreads.items() if v is not None},
            system=group[0].system, rpe_trans_cm=spread([r.rpe_trans_cm for r in good]),
            rpe_rot_deg=spread([r.rpe_rot_deg for r in good]),
            lost_frames=spread([r.lost_frames for r in group]),  # also of rows whose evaluation failed
        ))

    def median(s: Spread | None) -> float | None:
        return None if s is None else s.median

    front_ate = pareto_front([(median(p["fps"]), median(p["ate_rmse_cm"])) for p in partial], (True, False))
    front_psnr = pareto_front([(median(p["fps"]), median(p["psnr_db"])) for p in partial], (True, True))
    return [SettingSummary(**p, on_front_ate=a, on_front_psnr=b) for p, a, b in zip(partial, front_ate, front_psnr)]


@dataclass(frozen=True)
class PowerLaw:
    """``y = coefficient * x ** exponent`` fitted in log-log space; r2 of that linear fit."""

    exponent: float
    coefficient: float
    r2: float

    def __call__(self, x: float) -> float:
        return self.coefficient * x ** self.exponent


def fit_power_law(x: Sequence[float], y: Sequence[float]) -> PowerLaw:
    """Least-squares line through (log x, log y): slope = exponent. Needs >= 2 distinct positive x and y > 0."""
    xs, ys = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if xs.size != ys.size or xs.size < 2 or not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ys))
                                                  and np.all(xs > 0) and np.all(ys > 0)):
        raise MipslamError("fit_power_law: needs at least two pairs of positive, finite values")
    lx, ly = np.log(xs), np.log(ys)
    if np.ptp(lx) == 0:
        raise MipslamError("fit_power_law: all x are equal; the exponent is undetermined")
    slope, intercept = np.polyfit(lx, ly, 1)
    residual = ly - (slope * lx + intercept)
    total = float(np.sum((ly - ly.mean()) ** 2))
    r2 = 1.0 - float(np.sum(residual ** 2)) / total if total > 0 else 1.0
    return PowerLaw(float(slope), float(math.exp(intercept)), r2)
