"""Aliasing, measured: PSNR of point / mip / ewa / eaa against the exact pixel integral.

Scene: many small, textured-like Gaussians (random colour, opacity, anisotropy and orientation) on a
slanted surface in front of the camera, sized so that at the *native* resolution (``aliasing.width`` x
``aliasing.height``) their projected standard deviations are 0.3 .. 1.5 px ("pixel-sized").

For every scale s in 1/8, 1/4, 1/2, 1 of the native resolution (intrinsics scaled with the
pixel-centre convention of :meth:`mipslam.types.Intrinsics.scaled`):
  ground truth = ``exact`` rendered at 8x the resolution of that scale, area-averaged 8x8 down;
  each mode is rendered at the scale itself and scored by PSNR of the colour image (black background).
A second table varies the EAA node cap (1, 2, 4, 8, 16) and reports PSNR and time per scale;
``aliasing.tune=true`` adds a small grid over the EAA constants (gamma, eta, tau, single-node sigma, k).

    mipslam bench --scenario aliasing --out bench_out/aliasing                          # docs/renderer.md 6
    mipslam bench --scenario aliasing --out bench_out/aliasing_tune --set aliasing.tune=true  # constants search

The tables go to OUT/bench.md, the record (machine, parameters; :mod:`mipslam.bench.record`) to OUT/bench.json.
"""
from __future__ import annotations

import logging
import math
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import parameters
from mipslam.errors import MipslamError
from mipslam.render import footprint, project_gaussians, rasterize
from mipslam.types import Intrinsics

log = logging.getLogger(__name__)

SCALES = (0.125, 0.25, 0.5, 1.0)
MODES = ("point", "mip", "ewa", "eaa")
NODE_CAPS = (1, 2, 4, 8, 16)
SUPERSAMPLE = 8


@dataclass(frozen=True)
class Options:
    width: int = 96  # native resolution; multiples of 8 (so that 1/8 of them are integers)
    height: int = 72
    gaussians: int = 3000
    seed: int = 0
    repeats: int = 3  # timing repeats (median)
    backend: str = "torch"  # torch | cpu | auto
    exact_order: int = 12  # Gauss-Legendre order of the ground truth
    tune: bool = False  # also search the EAA constants
    cache: str = ""  # file to keep the ground truth in between runs ("" for none)


SMOKE = dict(width=16, height=16, gaussians=40, repeats=1, exact_order=4)


def make_scene(width: int, height: int, count: int, seed: int, sigma_px=(0.3, 1.5), max_anisotropy=8.0):
    """Gaussians on a slanted, slightly rough surface; sizes given in native pixels.

    Returns (means [N,3], quats [N,4] wxyz, scales [N,3] m, opacities [N], colors [N,3], intrinsics).
    """
    g = torch.Generator().manual_seed(seed)
    focal = 0.9 * width
    intr = Intrinsics(fx=focal, fy=focal, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)
    u = torch.rand(count, generator=g) * (width + 4) - 2.5
    v = torch.rand(count, generator=g) * (height + 4) - 2.5
    depth = 2.0 + 0.8 * u / width + 0.05 * torch.randn(count, generator=g)
    means = torch.stack([(u - intr.cx) * depth / focal, (v - intr.cy) * depth / focal, depth], -1)
    log_lo, log_hi = math.log(sigma_px[0]), math.log(sigma_px[1])
    major_px = torch.exp(log_lo + (log_hi - log_lo) * torch.rand(count, generator=g))
    kappa = torch.exp(math.log(max_anisotropy) * torch.rand(count, generator=g))
    third = torch.rand(count, generator=g) * 0.5 + 0.5
    scales_px = torch.stack([major_px, major_px / kappa, major_px * third / kappa], -1)
    scales = scales_px * depth[:, None] / focal
    quats = torch.randn(count, 4, generator=g)
    opacities = 0.4 + 0.6 * torch.rand(count, generator=g)
    colors = torch.rand(count, 3, generator=g)
    return means, quats, scales, opacities, colors, intr


def render_color(scene, intr: Intrinsics, mode: str, backend: str, **options):
    means, quats, scales, opacities, colors, _ = scene
    K = intr.matrix()
    with torch.no_grad():
        out = rasterize(means, quats, scales, opacities, colors, torch.eye(4), K, intr.width, intr.height,
                        mode=mode, backend=backend, **options)
    return out.color


def timed(fn, repeats: int):
    """(result, median seconds) of ``repeats`` calls."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return result, statistics.median(times)


def psnr(image: torch.Tensor, reference: torch.Tensor) -> float:
    mse = torch.mean((image.double() - reference.double()) ** 2).item()
    return 10.0 * math.log10(1.0 / max(mse, 1e-20))


def eaa_nodes_per_pair(scene, intr: Intrinsics, eaa_max_nodes=4, eaa_gamma=0.5, eaa_single_node_sigma=1.0,
                       k_sigma=3.0, **_ignored) -> float:
    """Machine-independent EAA cost: mean node count over the (pixel, Gaussian) pairs of the k-sigma boxes.

    A 1-node pair costs one exp (like ``point``); an n-row pair about n exp + 2n + 2 erf.
    """
    means, quats, scales, opacities, colors, _ = scene
    proj = project_gaussians(means, quats, scales, opacities, colors, torch.eye(4), intr.matrix(), intr.width,
                             intr.height, extent_sigma=k_sigma, extent_pad=0.5)
    xx, xy, yy = proj.cov2d[proj.visible].unbind(-1)
    det = proj.cov_det[proj.visible]
    nodes = footprint.eaa_node_counts(xx, xy, yy, det, max_nodes=eaa_max_nodes, gamma=eaa_gamma,
                                      single_node_sigma=eaa_single_node_sigma).double()
    support = (2 * k_sigma * xx.sqrt() + 1) * (2 * k_sigma * yy.sqrt() + 1)
    return float((nodes * support).sum() / support.sum().clamp_min(1e-9))


def ground_truth(scene, scale: float, backend: str, exact_order: int):
    """``exact`` at SUPERSAMPLE x the resolution of ``scale``, area-averaged down.  -> [H, W, 3]"""
    native = scene[-1]
    high = native.scaled(scale * SUPERSAMPLE)
    image = render_color(scene, high, "exact", backend, exact_order=exact_order)
    pooled = F.avg_pool2d(image.permute(2, 0, 1).unsqueeze(0), SUPERSAMPLE)
    return pooled[0].permute(1, 2, 0)


def run(options: Options, out_dir: Path) -> ScenarioResult:
    if options.width % 8 or options.height % 8:
        raise MipslamError(f"aliasing.width {options.width}, aliasing.height {options.height}: must be multiples of 8 "
                           "(so that 1/8 of them are integers)")
    if options.backend not in ("torch", "cpu", "auto"):
        raise MipslamError(f"aliasing.backend {options.backend!r}: choose torch, cpu or auto")
    lines: list[str] = []

    def emit(text: str = "") -> None:
        lines.append(text)
        log.debug("%s", text)

    _tables(options, emit)
    report = "\n".join(lines)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), {"tables_markdown": report},
                            threads=torch.get_num_threads(), markdown=report)
    return ScenarioResult(files, report)


def _tables(args: Options, emit: Callable[..., None]) -> None:

    torch.manual_seed(args.seed)
    scene = make_scene(args.width, args.height, args.gaussians, args.seed)
    native = scene[-1]
    emit(f"# bench_aliasing: {args.gaussians} Gaussians, native {args.width}x{args.height}, "
          f"backend {args.backend}, torch threads {torch.get_num_threads()}")

    start = time.perf_counter()
    key = f"{args.width}x{args.height}-{args.gaussians}-{args.seed}-{args.exact_order}"
    truth = None
    if args.cache and os.path.exists(args.cache):
        stored = torch.load(args.cache, weights_only=True)
        if stored.get("key") == key:
            truth = {float(s): image for s, image in stored["truth"].items()}
    if truth is None:
        truth = {s: ground_truth(scene, s, args.backend, args.exact_order) for s in SCALES}
        if args.cache:
            torch.save({"key": key, "truth": {str(s): image for s, image in truth.items()}}, args.cache)
    emit(f"# ground truth (exact, {SUPERSAMPLE}x, GL order {args.exact_order}): "
          f"{time.perf_counter() - start:.1f} s")

    def scale_name(s):
        return f"1/{round(1 / s)}" if s < 1 else "1"

    header = "| mode | " + " | ".join(f"{scale_name(s)} ({native.scaled(s).width}x{native.scaled(s).height})"
                                       for s in SCALES) + " | time at 1 (ms) |"
    emit("\n## PSNR (dB) against exact-at-8x, per scale\n")
    emit(header)
    emit("|" + "---|" * (len(SCALES) + 2))
    scores = {}
    for mode in MODES:
        row = []
        for s in SCALES:
            intr = native.scaled(s)
            image, seconds = timed(lambda: render_color(scene, intr, mode, args.backend), args.repeats)
            row.append(psnr(image, truth[s]))
            scores[(mode, s)] = row[-1]
        emit(f"| {mode} | " + " | ".join(f"{p:.2f}" for p in row) + f" | {1000 * seconds:.0f} |")
    emit("\nMargins of eaa (dB): " + "; ".join(
        f"{scale_name(s)}: vs point {scores[('eaa', s)] - scores[('point', s)]:+.2f}, "
        f"vs mip {scores[('eaa', s)] - scores[('mip', s)]:+.2f}, vs ewa {scores[('eaa', s)] - scores[('ewa', s)]:+.2f}"
        for s in SCALES))

    emit("\n## EAA node cap: PSNR (dB) per scale, nodes per pair at 1/8 and 1, time\n")
    emit("| eaa_max_nodes | " + " | ".join(scale_name(s) for s in SCALES)
          + " | nodes/pair at 1/8 | nodes/pair at 1 | time at 1 (ms) | time, all scales (ms) |")
    emit("|" + "---|" * (len(SCALES) + 5))
    for cap in NODE_CAPS:
        row, total = [], 0.0
        for s in SCALES:
            intr = native.scaled(s)
            image, seconds = timed(lambda: render_color(scene, intr, "eaa", args.backend, eaa_max_nodes=cap),
                                   args.repeats)
            row.append(psnr(image, truth[s]))
            total += seconds
        nodes = [eaa_nodes_per_pair(scene, native.scaled(s), eaa_max_nodes=cap) for s in (SCALES[0], SCALES[-1])]
        emit(f"| {cap} | " + " | ".join(f"{p:.2f}" for p in row) + f" | {nodes[0]:.2f} | {nodes[1]:.2f} | "
              f"{1000 * seconds:.0f} | {1000 * total:.0f} |")

    if args.tune:
        tune(scene, truth, args, emit)


def tune(scene, truth, args: Options, emit: Callable[..., None]) -> None:
    """Constants search. Accuracy: mean PSNR over the scales; cost: nodes per pair (deterministic)."""
    native = scene[-1]
    defaults = dict(eaa_max_nodes=4, eaa_gamma=0.5, eaa_eta=0.0, eaa_tau=0.25, eaa_single_node_sigma=1.0, k_sigma=3.0)
    grid = [dict(eaa_gamma=g, eaa_max_nodes=m) for m in (4, 8) for g in (0.0, 0.25, 0.5, 1.0, 2.0)]
    grid += [dict(eaa_eta=eta, eaa_tau=tau) for eta, tau in ((0.5, 0.1), (1.0, 0.25), (2.0, 0.25), (2.0, 0.5))]
    grid += [dict(k_sigma=k) for k in (2.5, 3.5, 4.0)]
    grid += [dict(eaa_single_node_sigma=s) for s in (0.5, 0.7, 0.8, 1.5, 1e9)]
    emit("\n## EAA constants on the aliasing scene (others at the defaults "
          + ", ".join(f"{k}={v}" for k, v in defaults.items()) + ")\n")
    emit("| setting | " + " | ".join(f"1/{round(1 / s)}" if s < 1 else "1" for s in SCALES)
          + " | mean PSNR | nodes/pair at 1 | time, all scales (ms) |")
    emit("|" + "---|" * (len(SCALES) + 4))
    for change in [{}] + grid:
        options = {**defaults, **change}
        row, total = [], 0.0
        for s in SCALES:
            intr = native.scaled(s)
            image, seconds = timed(lambda: render_color(scene, intr, "eaa", args.backend, **options), args.repeats)
            row.append(psnr(image, truth[s]))
            total += seconds
        name = ", ".join(f"{k}={v}" for k, v in change.items()) or "defaults"
        emit(f"| {name} | " + " | ".join(f"{p:.2f}" for p in row) + f" | {statistics.mean(row):.3f} | "
              f"{eaa_nodes_per_pair(scene, native, **options):.2f} | {1000 * total:.0f} |")
    tune_single_node_sigma(emit)


def tune_single_node_sigma(emit: Callable[..., None]) -> None:
    """Splats from sub-pixel to large (minor-axis sigma 0.3..6 px, kappa 1..4): the 1-node threshold
    ``eaa_single_node_sigma`` (above it one node moment-matched to the pixel box, below it rows).

    Mean absolute per-pixel opacity error against ``exact`` over each splat's 13x13 neighbourhood, with the
    renderer's k-sigma cut (k = 3) and without one (k = 8: the approximation alone), per band of minor-axis
    sigma; ``mip`` and 4 rows everywhere for comparison.
    """
    g = torch.Generator().manual_seed(7)
    n = 3000
    dtype = torch.float64
    sigma_minor = torch.exp(math.log(0.3) + (math.log(6.0) - math.log(0.3)) * torch.rand(n, generator=g, dtype=dtype))
    kappa = 1.0 + 3.0 * torch.rand(n, generator=g, dtype=dtype)
    theta = math.pi * torch.rand(n, generator=g, dtype=dtype)
    c, s_ = torch.cos(theta), torch.sin(theta)
    s1, s2 = sigma_minor * kappa, sigma_minor
    xx, yy, xy = c * c * s1**2 + s_ * s_ * s2**2, s_ * s_ * s1**2 + c * c * s2**2, c * s_ * (s1**2 - s2**2)
    det = (s1 * s2) ** 2
    mx, my = torch.rand(n, generator=g, dtype=dtype) - 0.5, torch.rand(n, generator=g, dtype=dtype) - 0.5
    o = torch.ones(n, dtype=dtype)
    r = torch.arange(-6, 7, dtype=dtype)
    py, px = (t.reshape(-1, 1) for t in torch.meshgrid(r, r, indexing="ij"))
    exact = footprint.exact_pixel_opacity(px, py, mx, my, xx, xy, yy, det, o)
    bands = [(0.3, 0.6), (0.6, 1.0), (1.0, 1.5), (1.5, 3.0), (3.0, 6.0)]

    def errors(k_sigma, single_node_sigma=None, mode="eaa"):
        if mode == "mip":
            value = footprint.centre_sample_opacity(px, py, mx, my, *footprint.footprint_parameters(
                "mip", xx, xy, yy, det, o), k_sigma=k_sigma)
        else:
            fxx, fxy, fyy, fdet, fo, nodes = footprint.mode_footemit(
                "eaa", xx, xy, yy, det, o, max_nodes=4, gamma=0.5, single_node_sigma=single_node_sigma)
            value = footprint.eaa_pixel_opacity(px, py, mx, my, fxx, fxy, fyy, fdet, fo, nodes, row_capacity=4,
                                                k_sigma=k_sigma, eta=0.0, tau=0.25)
        per_splat = (value - exact).abs().mean(0)
        return [per_splat[(sigma_minor >= lo) & (sigma_minor < hi)].mean().item() for lo, hi in bands]

    emit("\n## eaa_single_node_sigma: mean |a - exact| (1e-4) per band of minor-axis sigma (px), kappa 1..4\n")
    header = " | ".join(f"{lo}-{hi}" for lo, hi in bands)
    emit(f"| setting | k | {header} | share of 1-node splats |")
    emit("|" + "---|" * (len(bands) + 3))
    for k_sigma in (3.0, 8.0):
        mip_errors = errors(k_sigma, mode="mip")
        emit(f"| mip | {k_sigma:g} | " + " | ".join(f"{1e4 * e:.1f}" for e in mip_errors) + " | 1.00 |")
        for threshold in (0.5, 0.7, 0.8, 1.0, 1.5, 3.0, 1e9):
            share = (sigma_minor >= threshold).double().mean().item()
            name = "4 rows everywhere" if threshold > 100 else f"eaa_single_node_sigma={threshold:g}"
            emit(f"| {name} | {k_sigma:g} | " + " | ".join(f"{1e4 * e:.1f}" for e in errors(k_sigma, threshold))
                  + f" | {share:.2f} |")

