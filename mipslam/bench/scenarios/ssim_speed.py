"""Benchmark: forward + backward of the SSIM loss term, the torch reference against the compiled kernel.

For each image size, ``1 - SSIM(image, target)`` (11x11 Gaussian window, sigma 1.5, "same" zero padding) of a
random float32 image [H, W, C] that needs a gradient, and ``.backward()``, timed three ways, interleaved in one
process (each repetition runs every variant once, in a rotating order, so a change of the machine's load reaches
all of them alike):

* ``torch``: :func:`mipslam.losses.structural.ssim_loss` with ``backend="torch"`` (autograd through the reference
  :func:`~mipslam.losses.structural.ssim`);
* ``compiled``: ``ssim_loss`` through the compiled kernel (``mipslam/render/cpu/ssim_loss.h``), the target's moments
  computed in the call;
* ``compiled, cached``: the same with an :class:`~mipslam.losses.structural.SSIMTargetCache` holding the target's
  moments (mapping's case: the same keyframe images scored again and again).

Medians (and quartiles) of wall time over ``repeats`` repetitions, on ``threads`` torch / OpenMP threads; the
loss and gradient differences between the paths are recorded as a check. Without the compiled library only
``torch`` is timed.

Run: ``mipslam bench --scenario ssim_speed --out bench_out/ssim_speed`` (``--set ssim_speed.sizes=320x240`` for one
size, ``--threads 1``). Documented in docs/renderer_cpu.md, section 3d.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import parameters


@dataclass(frozen=True)
class Options:
    sizes: tuple[str, ...] = ("320x240", "640x480")  # WIDTHxHEIGHT
    channels: int = 3
    threads: int = 2
    repeats: int = 60  # timed repetitions of each variant, per size
    warmup: int = 3
    seed: int = 0


SMOKE = dict(sizes=("24x16",), repeats=2, warmup=1)

VARIANTS = ("torch", "compiled", "compiled, cached")


def _size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height)


def _measure(width: int, height: int, options: Options, compiled: bool) -> dict:
    from mipslam.losses.structural import SSIMTargetCache, ssim_loss

    generator = torch.Generator().manual_seed(options.seed)
    target = torch.rand(height, width, options.channels, generator=generator)
    image = (target + 0.1 * torch.randn(target.shape, generator=generator)).clamp(0, 1).requires_grad_()
    cache = SSIMTargetCache()
    calls = {"torch": lambda: ssim_loss(image, target, backend="torch"),
             "compiled": lambda: ssim_loss(image, target, backend="cpu"),
             "compiled, cached": lambda: ssim_loss(image, target, backend="cpu", cache=cache)}
    variants = VARIANTS if compiled else ("torch",)

    def once(name: str) -> tuple[float, float, torch.Tensor]:
        image.grad = None
        start = time.perf_counter()
        loss = calls[name]()
        loss.backward()
        return time.perf_counter() - start, loss.detach().item(), image.grad

    results = {name: once(name) for name in variants for _ in range(options.warmup)}
    times: dict[str, list[float]] = {name: [] for name in variants}
    for k in range(options.repeats):
        for i in range(len(variants)):
            name = variants[(i + k) % len(variants)]
            times[name].append(once(name)[0])
    row = {"size": f"{width}x{height}x{options.channels}"}
    for name in variants:
        q = statistics.quantiles(times[name], n=4) if len(times[name]) > 1 else times[name] * 3
        row[name] = {"median_ms": 1e3 * statistics.median(times[name]), "q1_ms": 1e3 * q[0], "q3_ms": 1e3 * q[2],
                     "min_ms": 1e3 * min(times[name])}
    if compiled:
        _, reference_loss, reference_grad = results["torch"]
        for name in variants[1:]:
            _, loss, grad = results[name]
            row[name]["speedup"] = row["torch"]["median_ms"] / row[name]["median_ms"]
            row[name]["loss_difference"] = abs(loss - reference_loss)
            row[name]["gradient_difference"] = float((grad - reference_grad).abs().max() / reference_grad.abs().max())
    return row


def _table(rows: list[dict], options: Options) -> str:
    lines = [f"**SSIM loss forward + backward, {options.threads} threads, median [q1, q3] of {options.repeats} "
             "interleaved repetitions**", "",
             "| image | variant | median [ms] | quartiles [ms] | min [ms] | speed-up |", "|---|---|---|---|---|---|"]
    for row in rows:
        for name in VARIANTS:
            if name not in row:
                continue
            r = row[name]
            speedup = f"{r['speedup']:.1f}x" if "speedup" in r else "-"
            lines.append(f"| {row['size']} | {name} | {r['median_ms']:.2f} | {r['q1_ms']:.2f}-{r['q3_ms']:.2f} | "
                         f"{r['min_ms']:.2f} | {speedup} |")
    return "\n".join(lines)


def run(options: Options, out_dir: Path) -> ScenarioResult:
    from mipslam.render import compiled_library

    torch.set_num_threads(options.threads)
    compiled = compiled_library() is not None
    rows = [_measure(*_size(size), options, compiled) for size in options.sizes]
    report = _table(rows, options)
    if not compiled:
        report += "\n\n(the compiled library is not available here: torch only)"
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), rows, threads=options.threads,
                            markdown=report, overwrite=True)
    return ScenarioResult(files, report)
