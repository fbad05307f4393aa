"""Speed and memory of the renderer backends.

Scene: 20k random Gaussians in front of a 320x240 pinhole camera (f = 300 px), depths 2-6 m, projected
standard deviations 0.5-3 px (per axis, random rotations), opacities 0.1-1, random colours. Loss for the
backward: sum(color) + 0.1 sum(depth) + sum(alpha), all inputs (viewmat included) requiring gradients.

Measured in one process, interleaved (so the machine's load hits both backends alike), median of
``render_speed.repeats`` runs (torch: ``render_speed.torch_repeats``), wall time and process CPU time:

1. forward+backward, cpu vs torch, ``point`` and ``eaa`` (default options);
2. forward rasterisation rate in ``point`` mode: Gaussian-pixel evaluations per second per thread,
   counted two ways: the 8-pixel row segments the kernel evaluated x 8 ("lanes", the work done) and
   the (tile, Gaussian) pairs x 256 ("tile pairs", what a 16x16 tile rasterizer resolves), both for the
   whole forward (projection included) and for the C++ stage alone;
3. ``eaa`` at the default node budget against ``point`` on the cpu backend (forward, forward+backward);
4. pose-only backward (``pose_only=True``: the viewmat alone needs a gradient) against the full backward;
5. with ``render_speed.runs=DIR[,DIR2]``: the renderer as the SLAM code calls it, on the map of a mipslam run
   folder (``map.ply``, the pose of its middle frame from ``traj_est.txt``, its intrinsics scaled by each
   of ``render_speed.scales``, its render config: mode, EAA budget, ...): per call the forward, the pose-only
   backward (tracking) and the full backward (mapping), each split into the time inside the C++ kernels
   (every call into the extension, timed by ``mipslam.render.cpu.profile_kernels``) and the rest (Python,
   torch and autograd glue). Two paths, interleaved: ``fused`` (the C++ projection, the cpu backend's
   path) and ``unfused`` (the torch projection with its autograd in front of the same C++ rasterizer,
   the path before the fused projection). The backward is driven by fixed random incoming gradients
   of color, depth and alpha (no loss operations in the timings).

Peak memory of one forward+backward per backend: a fresh child process renders a tiny warm-up image,
resets the kernel's peak-RSS counter (``/proc/self/clear_refs`` <- 5), runs the full-size forward+backward
and reports ``VmHWM`` minus the ``VmRSS`` before the run (Linux; "n/a" elsewhere).

The torch backend is given its best allocator setting: the measurement runs in a child process with
``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` = 4 GiB unless ``render_speed.malloc_tuning=false``
(glibc otherwise maps and unmaps its large temporaries on every call, about 2x slower).

    mipslam bench --scenario render_speed --out bench_out/render_speed     # full run (several minutes)
    mipslam bench --scenario render_speed --out bench_out/render_quick --set render_speed.quick=true
    mipslam bench --scenario render_speed --out bench_out/glue --set render_speed.glue_only=true \
        --set render_speed.runs=RUN_DIR,RUN_DIR2 --set render_speed.scales=1,2
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import REPO, parameters
from mipslam.errors import MipslamError

log = logging.getLogger(__name__)

MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "4294967296", "MALLOC_TRIM_THRESHOLD_": "4294967296"}
MODULE = "mipslam.bench.scenarios.render_speed"  # the child processes run it with -m (as __main__ inside them)


@dataclass(frozen=True)
class Options:
    width: int = 320
    height: int = 240
    gaussians: int = 20000
    threads: int = 2
    repeats: int = 7  # timed runs per cpu-backend measurement
    torch_repeats: int = 3  # timed runs per torch-backend measurement
    seed: int = 0
    skip_torch: bool = False  # cpu backend only (no ratios against torch)
    skip_memory: bool = False
    malloc_tuning: bool = True
    quick: bool = False  # 160x120, 5000 Gaussians, 3/1 repeats
    runs: tuple[str, ...] = ()  # mipslam run folders whose maps are rendered for the kernel/glue split
    scales: tuple[float, ...] = (1.0, 2.0)  # render scales of each run's intrinsics (1 = mapping size)
    glue_only: bool = False  # only the run-folder measurements (section 5)


SMOKE = dict(width=32, height=24, gaussians=200, repeats=1, torch_repeats=1, skip_memory=True, malloc_tuning=False)


def configure_threads(threads: int):
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ["MKL_NUM_THREADS"] = str(threads)
    import torch

    torch.set_num_threads(threads)
    return torch


def make_scene(torch, width: int, height: int, count: int, seed: int):
    """(params [means, quats, scales, opacities, colors, viewmat], K) of the benchmark scene."""
    g = torch.Generator().manual_seed(seed)
    focal = 300.0 * width / 320.0
    cx, cy = (width - 1) / 2, (height - 1) / 2
    z = 2.0 + 4.0 * torch.rand(count, generator=g)
    u = torch.rand(count, generator=g) * width - 0.5
    v = torch.rand(count, generator=g) * height - 0.5
    means = torch.stack([(u - cx) * z / focal, (v - cy) * z / focal, z], -1)
    sigma_px = 0.5 + 2.5 * torch.rand(count, generator=g)
    # per-axis factors 0.7-1.3: the projected sigmas stay within about 0.5-3 px
    scales = (sigma_px * z / focal)[:, None] * (0.7 + 0.6 * torch.rand(count, 3, generator=g))
    quats = torch.randn(count, 4, generator=g)
    opacities = 0.1 + 0.9 * torch.rand(count, generator=g)
    colors = torch.rand(count, 3, generator=g)
    K = torch.tensor([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    return [means, quats, scales, opacities, colors, torch.eye(4)], K


class Timer:
    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu


def forward_backward(torch, rasterize, params, K, width, height, backend, mode, pose_only=False):
    """One forward+backward: returns (forward Timer, backward Timer)."""
    inputs = [t.clone().requires_grad_() for t in params]
    with Timer() as fwd:
        out = rasterize(*inputs[:5], inputs[5], K, width, height, mode=mode, backend=backend, pose_only=pose_only)
        loss = out.color.sum() + 0.1 * out.depth.sum() + out.alpha.sum()
    with Timer() as bwd:
        loss.backward()
    return fwd, bwd


def median(values):
    return statistics.median(values) if values else float("nan")


def run_memory_child(args: Options, backend: str) -> None:
    """Peak RSS increase (MiB) of one full-size forward+backward in this (fresh) process, printed as JSON for the
    parent (:func:`measure_memory`)."""
    torch = configure_threads(args.threads)
    from mipslam.render import rasterize

    params, K = make_scene(torch, args.width, args.height, args.gaussians, args.seed)
    small, Ks = make_scene(torch, 32, 24, 50, args.seed)
    forward_backward(torch, rasterize, small, Ks, 32, 24, backend, "point")  # load libraries, pools
    status = Path("/proc/self/status")
    try:
        Path("/proc/self/clear_refs").write_text("5")
        before = _status_kib(status, "VmRSS")
    except OSError:
        print(json.dumps({"peak_mib": None}))
        return
    forward_backward(torch, rasterize, params, K, args.width, args.height, backend, "point")
    peak = _status_kib(status, "VmHWM")
    print(json.dumps({"peak_mib": (peak - before) / 1024.0}))


def _status_kib(status: Path, key: str) -> int:
    for line in status.read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise OSError(f"{key} not in {status}")


def measure_memory(args, backend):
    cmd = [sys.executable, "-m", MODULE, "--memory-child", backend, json.dumps(dataclasses.asdict(args))]
    result = subprocess.run(cmd, capture_output=True, text=True, env=_child_environment(os.environ), timeout=3600,
                            check=False)
    if result.returncode != 0:
        return None, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])["peak_mib"], None


def cpu_model() -> str:
    from mipslam.bench.report import cpu_model as model

    return model()


def load_average() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def load_run_scene(torch, run_dir: Path):
    """(params [means, quats, scales, opacities, colors, viewmat], intrinsics, mode, options) of a run folder:
    its map, the pose of the middle frame of its estimated trajectory, its dataset's intrinsics, its render
    config."""
    from mipslam.datasets import make_sequence
    from mipslam.evaluation.run_files import read_run_config
    from mipslam.geometry.se3 import se3_inverse
    from mipslam.io.ply import read_map_ply
    from mipslam.io.run_folder import RunFolder
    from mipslam.io.tum import read_tum_trajectory
    from mipslam.rendering import render_options

    config = read_run_config(RunFolder(run_dir))
    intrinsics = make_sequence(config.dataset).intrinsics
    gaussians = read_map_ply(run_dir / "map.ply").activated()
    trajectory = read_tum_trajectory(run_dir / "traj_est.txt")
    T_wc = torch.tensor(trajectory.T_wc[len(trajectory.T_wc) // 2], dtype=torch.float64)
    viewmat = se3_inverse(T_wc).float()
    params = [t.detach().contiguous() for t in (gaussians.means, gaussians.quats, gaussians.scales,
                                                 gaussians.opacities, gaussians.colors)] + [viewmat]
    return params, intrinsics, config.render.mode, render_options(config.render)


def glue_iteration(torch, cpu_backend, render_call, params, K, width, height, pose_only, grads):
    """One forward and backward: (forward wall, forward kernels, backward wall, backward kernels, iteration
    process CPU time, kernels' process CPU time) in seconds."""
    viewmat = params[5].clone().requires_grad_()
    if pose_only:
        gaussians = params[:5]
    else:
        gaussians = [t.clone().requires_grad_() for t in params[:5]]
    cpu_start = time.process_time()
    with cpu_backend.profile_kernels() as kernels_fwd:
        with Timer() as fwd:
            out = render_call(*gaussians, viewmat, K, width, height, pose_only)
    with cpu_backend.profile_kernels() as kernels_bwd:
        with Timer() as bwd:
            torch.autograd.backward([out.color, out.depth, out.alpha], grads)
    return (fwd.wall, kernels_fwd.total, bwd.wall, kernels_bwd.total, time.process_time() - cpu_start,
            kernels_fwd.total_cpu + kernels_bwd.total_cpu)


def measure_glue(args, torch, info):
    """Section 5: kernel/glue split per call on the maps of --run folders. Returns (rows, markdown lines)."""
    from mipslam.render import RenderOptions, rasterize
    from mipslam.render import cpu as cpu_backend

    scales = list(args.scales)
    rows = []
    for run_dir in map(Path, args.runs):
        params, intrinsics, mode, options = load_run_scene(torch, run_dir)
        opts = RenderOptions(**options)
        paths = {
            "fused": lambda *a, pose_only, **_: rasterize(*a, mode=mode, backend="cpu", pose_only=pose_only,
                                                          **options),
            "unfused": lambda *a, pose_only, **_: cpu_backend.rasterize_unfused(
                *a, mode=mode, options=RenderOptions(**{**options, "pose_only": pose_only})),
        }
        for scale in scales:
            cam = intrinsics.scaled(scale) if scale != 1.0 else intrinsics
            W, H = cam.width, cam.height
            K = cam.matrix(dtype=torch.float32, device="cpu")
            g = torch.Generator().manual_seed(args.seed)
            grads = [torch.rand(H, W, params[4].shape[1], generator=g), torch.randn(H, W, generator=g),
                     torch.randn(H, W, generator=g)]
            samples = {}
            for r in range(args.repeats + 1):  # the first round warms up
                for path, call in paths.items():
                    for pose_only in (True, False):
                        result = glue_iteration(torch, cpu_backend, lambda *a: call(*a[:-1], pose_only=a[-1]),
                                                params, K, W, H, pose_only, grads)
                        if r > 0:
                            samples.setdefault((path, pose_only), []).append(result)
            with torch.no_grad():
                n_visible = rasterize(*params, K, W, H, mode=mode, backend="cpu", **options).n_visible
            for (path, pose_only), runs in samples.items():
                med = [1e3 * median([x[i] for x in runs]) for i in range(6)]
                iteration = 1e3 * median([x[0] + x[2] for x in runs])
                kernels = 1e3 * median([x[1] + x[3] for x in runs])
                rows.append({"run": str(run_dir), "size": f"{W}x{H}", "gaussians": int(params[0].shape[0]),
                             "visible": n_visible, "mode": mode, "eaa_max_nodes": int(opts.eaa_max_nodes),
                             "path": path, "pose_only": pose_only, "forward_ms": med[0], "forward_kernels_ms": med[1],
                             "backward_ms": med[2], "backward_kernels_ms": med[3], "iteration_cpu_ms": med[4],
                             "iteration_kernels_cpu_ms": med[5],
                             "iteration_ms": iteration, "iteration_kernels_ms": kernels})
            log.info("%s at %dx%d done (load %s)", run_dir, W, H, load_average())
    lines = ["", f"Per call on run maps ({info['threads']} threads; medians of {args.repeats}; kernels = time inside "
             "the C++ extension; glue = the rest of the call):", "",
             "| map (Gaussians, visible) | size | path | call | forward (kernels) | backward (kernels) | "
             "iteration | kernels | glue | glue share | glue share of CPU time |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        glue = row["iteration_ms"] - row["iteration_kernels_ms"]
        lines.append(
            f"| {Path(row['run']).name} ({row['gaussians']}, {row['visible']}) | {row['size']} | {row['path']} | "
            f"{'pose-only' if row['pose_only'] else 'full'} | {row['forward_ms']:.2f} ({row['forward_kernels_ms']:.2f}) | "
            f"{row['backward_ms']:.2f} ({row['backward_kernels_ms']:.2f}) | {row['iteration_ms']:.2f} ms | "
            f"{row['iteration_kernels_ms']:.2f} ms | {glue:.2f} ms | **{100 * glue / row['iteration_ms']:.1f} %** | "
            f"{100 * (1 - row['iteration_kernels_cpu_ms'] / row['iteration_cpu_ms']):.1f} % |")
    return rows, lines


def _options_from_json(text: str) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(text).items()}


def _child_environment(base) -> dict[str, str]:
    env = dict(base)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH", "")]))
    return env


def run(options: Options, out_dir: Path) -> ScenarioResult:
    if options.quick:
        options = dataclasses.replace(options, width=160, height=120, gaussians=5000, repeats=3, torch_repeats=1)
    if options.glue_only and not options.runs:
        raise MipslamError("render_speed.glue_only needs at least one run folder in render_speed.runs")
    if options.malloc_tuning and any(os.environ.get(k) != v for k, v in MALLOC_ENV.items()):
        # the whole measurement in a child process started with the allocator setting
        env = _child_environment({**os.environ, **MALLOC_ENV})
        child = subprocess.run([sys.executable, "-m", MODULE, "--measure", str(out_dir),
                                json.dumps(dataclasses.asdict(options)), json.dumps(sys.argv)], env=env, check=False)
        if child.returncode != 0:
            raise MipslamError(f"render_speed: the measuring process failed (exit {child.returncode}; its messages "
                               "are above)")
        from mipslam.bench.record import BenchmarkFiles

        files = BenchmarkFiles(out_dir / f"{RECORD_NAME}.json", out_dir / f"{RECORD_NAME}.md")
        return ScenarioResult(files, files.markdown.read_text(encoding="utf-8"))
    return _measure(options, out_dir)


def _measure(args: Options, out_dir: Path) -> ScenarioResult:
    torch = configure_threads(args.threads)
    from mipslam.render import cpu as cpu_backend
    from mipslam.render import project_gaussians, rasterize
    from mipslam.bench.record import write_benchmark
    from mipslam.render.rasterize_torch import FootprintSettings
    from mipslam.render import RenderOptions

    if not cpu_backend.is_available():
        raise MipslamError(f"the cpu backend is not available: {cpu_backend.unavailable_reason()}")
    W, H = args.width, args.height
    params, K = make_scene(torch, W, H, args.gaussians, args.seed)
    info = {"cpu": cpu_model(), "threads": args.threads, "torch": torch.__version__,
            "build": cpu_backend.load_extension().build_info(), "scene": f"{W}x{H}, {args.gaussians} Gaussians",
            "load_before": load_average(),
            "malloc_tuning": all(os.environ.get(k) == v for k, v in MALLOC_ENV.items())}
    log.info("%s, %d threads, %s, torch %s, extension [%s], load average %s", info["scene"], args.threads, info["cpu"],
             info["torch"], info["build"], info["load_before"])

    if args.glue_only:
        rows, lines = measure_glue(args, torch, info)
        info["load_after"] = load_average()
        lines.insert(0, f"load average {info['load_before']} -> {info['load_after']}")
        files = write_benchmark(out_dir, RECORD_NAME, parameters(args), {"info": info, "glue": rows},
                                threads=args.threads, markdown="\n".join(lines))
        return ScenarioResult(files, "\n".join(lines))

    results = {}

    def record(key, timers):
        results[key] = {"wall_ms": 1e3 * median([t.wall for t in timers]), "cpu_ms": 1e3 * median([t.cpu for t in timers])}

    # warm-up (builds/loads the extension, allocator pools)
    for backend in ("cpu",) + (() if args.skip_torch else ("torch",)):
        forward_backward(torch, rasterize, params, K, W, H, backend, "point")

    # 1, 3, 4: forward+backward per (backend, mode, pose_only), interleaved
    samples = {}
    backends = ("cpu",) if args.skip_torch else ("cpu", "torch")
    for r in range(max(args.repeats, args.torch_repeats)):
        for backend in backends:
            if backend == "torch" and r >= args.torch_repeats:
                continue
            if backend == "cpu" and r >= args.repeats:
                continue
            for mode in ("point", "eaa"):
                for pose_only in (False, True):
                    fwd, bwd = forward_backward(torch, rasterize, params, K, W, H, backend, mode, pose_only)
                    samples.setdefault((backend, mode, pose_only), []).append((fwd, bwd))
        log.info("round %d done (load %s)", r + 1, load_average())
    for (backend, mode, pose_only), runs in samples.items():
        tag = f"{backend}/{mode}/{'pose' if pose_only else 'full'}"
        record(tag + "/fwd", [f for f, _ in runs])
        record(tag + "/bwd", [b for _, b in runs])
        total = []
        for f, b in runs:
            t = Timer()
            t.wall, t.cpu = f.wall + b.wall, f.cpu + b.cpu
            total.append(t)
        record(tag + "/fwd+bwd", total)

    # 2: forward rate, point mode (no autograd), whole call and the C++ rasterizer alone (its time inside the
    # whole call, timed by profile_kernels); the lane and pair counts come from one rasterize_projected call
    opts = RenderOptions()
    fwd_timers, stage_timers = [], []
    with torch.no_grad():
        proj = project_gaussians(*params[:5], params[5], K, W, H, near_plane=opts.near_plane,
                                 extent_sigma=opts.k_sigma)
        settings = FootprintSettings(mode="point", k_sigma=opts.k_sigma, max_nodes=int(opts.eaa_max_nodes),
                                     gamma=opts.eaa_gamma, eta=opts.eaa_eta, tau=opts.eaa_tau,
                                     single_node_sigma=opts.eaa_single_node_sigma, exact_order=opts.exact_order)
        image = cpu_backend.rasterize_projected(proj, W, H, settings)
        for _ in range(args.repeats):
            with cpu_backend.profile_kernels() as kernels:
                with Timer() as t:
                    rasterize(*params[:5], params[5], K, W, H, mode="point", backend="cpu")
            fwd_timers.append(t)
            stage = Timer()
            stage.wall, stage.cpu = kernels.seconds["rasterize_forward"], kernels.cpu_seconds["rasterize_forward"]
            stage_timers.append(stage)
    record("cpu/point/forward_nograd", fwd_timers)
    record("cpu/point/raster_stage", stage_timers)
    lanes, pairs = image.lanes_evaluated, image.pairs
    results["lanes_evaluated"], results["tile_pairs"] = lanes, pairs

    glue_rows, glue_lines = measure_glue(args, torch, info) if args.runs else ([], [])

    # memory
    memory = {}
    if not args.skip_memory:
        for backend in backends:
            memory[backend], error = measure_memory(args, backend)
            if error:
                log.warning("memory child for %s failed: %s", backend, error)
    info["load_after"] = load_average()

    # report
    def ms(key, kind="wall_ms"):
        return results[key][kind]

    lines = [f"CPU: {info['cpu']}; {args.threads} threads; torch {info['torch']}; extension built with "
             f"[{info['build']}]; load average {info['load_before']} -> {info['load_after']}; wall-clock medians "
             f"(process CPU time in brackets); cpu backend {args.repeats} runs, torch {args.torch_repeats}.", "",
             "| measurement | cpu backend | torch backend | ratio | target |", "|---|---|---|---|---|"]
    for mode in ("point", "eaa"):
        key_c = f"cpu/{mode}/full/fwd+bwd"
        if args.skip_torch:
            lines.append(f"| fwd+bwd {mode} | {ms(key_c):.1f} ms ({ms(key_c, 'cpu_ms'):.0f}) | - | - | |")
        else:
            key_t = f"torch/{mode}/full/fwd+bwd"
            lines.append(f"| fwd+bwd {mode} | {ms(key_c):.1f} ms ({ms(key_c, 'cpu_ms'):.0f}) | {ms(key_t):.0f} ms "
                         f"({ms(key_t, 'cpu_ms'):.0f}) | **{ms(key_t) / ms(key_c):.1f}x** faster | >= 8x |")
    if memory:
        mem_c, mem_t = memory.get("cpu"), memory.get("torch")
        fmt = (lambda m: "n/a" if m is None else f"{m:.1f} MiB")
        ratio = f"**{mem_c / mem_t:.3f}**" if mem_c is not None and mem_t else "n/a"
        lines.append(f"| peak RSS increase, fwd+bwd point | {fmt(mem_c)} | {fmt(mem_t)} | {ratio} | <= 0.25 |")
    threads = args.threads
    for key, label in (("cpu/point/forward_nograd", "whole forward"), ("cpu/point/raster_stage", "C++ rasterizer")):
        t, t_cpu = ms(key) / 1e3, ms(key, "cpu_ms") / 1e3
        lines.append(f"| point forward rate, {label} ({ms(key):.1f} ms) | {lanes / t / threads:.3g} lanes/s/thread; "
                     f"{pairs * 256 / t / threads:.3g} tile-pair px/s/thread (per CPU second: {lanes / t_cpu:.3g}; "
                     f"{pairs * 256 / t_cpu:.3g}) | | | >= 1e9 /s/core |")
    for what in ("fwd", "fwd+bwd"):
        e, p = ms(f"cpu/eaa/full/{what}"), ms(f"cpu/point/full/{what}")
        lines.append(f"| eaa / point, {what} (cpu) | {e:.1f} / {p:.1f} ms | | **{e / p:.2f}x** | <= 1.5x |")
    for mode in ("point", "eaa"):
        f, p = ms(f"cpu/{mode}/full/bwd"), ms(f"cpu/{mode}/pose/bwd")
        lines.append(f"| backward full / pose-only, {mode} (cpu) | {f:.1f} / {p:.1f} ms | | **{f / p:.2f}x** | >= 1.5x |")
        if not args.skip_torch:
            f, p = ms(f"torch/{mode}/full/bwd"), ms(f"torch/{mode}/pose/bwd")
            lines.append(f"| backward full / pose-only, {mode} (torch) | | {f:.0f} / {p:.0f} ms | {f / p:.2f}x | |")
    lines.append("")
    lines.append(f"Counts: {lanes} lanes evaluated, {pairs} (tile, Gaussian) pairs = {pairs * 256} tile pixel pairs.")
    detail = ["", "| timing (median) | wall ms | cpu ms |", "|---|---|---|"]
    detail += [f"| {k} | {v['wall_ms']:.1f} | {v['cpu_ms']:.1f} |" for k, v in sorted(results.items())
               if isinstance(v, dict)]
    report = "\n".join(lines + glue_lines + detail)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(args),
                            {"info": info, "results": results, "memory_mib": memory, "glue": glue_rows},
                            threads=args.threads, markdown=report)
    return ScenarioResult(files, report)


if __name__ == "__main__":  # the child processes: python -m mipslam.bench.scenarios.render_speed --measure|--memory-child
    if sys.argv[1] == "--memory-child":
        run_memory_child(Options(**_options_from_json(sys.argv[3])), sys.argv[2])
    else:  # --measure OUT OPTIONS ARGV: the record names the command the user typed (ARGV)
        out, options, sys.argv = Path(sys.argv[2]), Options(**_options_from_json(sys.argv[3])), json.loads(sys.argv[4])
        logging.basicConfig(level=logging.INFO, format="mipslam: %(message)s")
        _measure(options, out)
