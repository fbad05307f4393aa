"""How cost grows with the work: renderer time against Gaussian count and against
pixel count, PGO time against keyframe count, each with the fitted log-log exponent.

Renderer (``rasterize``, cpu backend, ``eaa`` with the default options, ``scaling.threads`` torch threads):

* *forward*: one call under ``torch.no_grad()`` (what evaluation and the map checks do);
* *pose-only forward+backward*: ``pose_only=True`` with the view matrix requiring a gradient and the
  tracking-like loss ``mean|color| + mean|depth|`` (what every tracking iteration does).

Scene, "a map of realistic scale": a 6 x 5 x 3 m box room whose six surfaces are covered by N
Gaussians placed uniformly at random (mean spacing d = sqrt(area / N), in-plane standard deviation
0.8 d, 0.1 d along the normal, each scaled by 0.8-1.2, random in-plane rotation, opacity 0.5-1, random colours), so the map's
density grows with N the way a SLAM map's does when it is densified more finely, and a view sees
a few layers of overlapping splats, not a pile. The camera stands inside the room (1.5 m from the
centre, looking at a corner, 70 degrees horizontal field of view), so about a quarter to a third of
the map is in view, as in a SLAM frame. Gaussian counts 1k..200k at 320x240; pixel counts
80x60..1280x720 (same horizontal field of view) at 30k Gaussians.

PGO: :func:`mipslam.loop.solver.optimize_pose_graph` on ``make_synthetic_pose_graph`` graphs
(2 laps of a circle, a loop edge every 5 keyframes, odometry noise 1 cm / 0.3 deg), plain full LM
and SA-PGO with both switches (as the ``pgo`` scenario), each over the whole graph, and SA-PGO
over the newest ``LoopOptions.pgo_window_keyframes`` nodes as the SLAM loop runs it
(:func:`mipslam.loop.solver.optimize_pose_graph_window`); one thread (the solver's default).

Every time is the median of ``scaling.repeats`` runs (>= 5 by default) after one warm-up call; the sizes
are measured interleaved (round r times every size once) so a change of the machine's load hits
every size alike. Wall time and process CPU time are both kept: on a loaded machine CPU time is the
steadier one (with one thread it is the work; with two, threads spinning at barriers count too). The exponent p of ``t = c n^p`` is a least-squares line through (log n, log t)
over all sizes, and over the upper half of the range (where fixed per-call costs no longer dominate).

    mipslam bench --scenario scaling --out bench_out/scaling                            # several minutes on 2 cores
    mipslam bench --scenario scaling --out bench_out/scaling_quick --set scaling.quick=true  # a few sizes, 3 repeats

The synthetic pose graphs are a helper of the test suite: the PGO sweep runs from a source checkout only.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import import_test_helper, parameters
from mipslam.bench.scenarios.render_speed import configure_threads
from mipslam.errors import MipslamError

log = logging.getLogger(__name__)

GAUSSIAN_COUNTS = (1_000, 3_000, 10_000, 30_000, 100_000, 200_000)
RESOLUTIONS = ((80, 60), (160, 120), (320, 240), (640, 480), (1280, 720))
KEYFRAME_COUNTS = (25, 50, 100, 200, 400, 1000, 2000)
ROOM_M = (6.0, 5.0, 3.0)
HFOV_DEG = 70.0


@dataclass(frozen=True)
class Options:
    threads: int = 2  # torch threads for the renderer
    repeats: int = 7  # timed runs per size (median)
    pgo_repeats: int = 5  # graphs (seeds) per keyframe count
    render_size: str = "320x240"  # image size of the Gaussian-count sweep
    pixel_gaussians: int = 30_000  # Gaussian count of the pixel-count sweep
    gaussian_counts: tuple[int, ...] = GAUSSIAN_COUNTS
    resolutions: tuple[str, ...] = tuple(f"{w}x{h}" for w, h in RESOLUTIONS)
    keyframe_counts: tuple[int, ...] = KEYFRAME_COUNTS
    skip_render: bool = False
    skip_pgo: bool = False
    seed: int = 0
    quick: bool = False  # fewer sizes, 3 repeats (not for the docs)


SMOKE = dict(repeats=1, pgo_repeats=1, pixel_gaussians=300, gaussian_counts=(200, 400), resolutions=("40x30", "80x60"),
             keyframe_counts=(10, 20))


# ----------------------------------------------------------------------------- scene

def room_map(torch, count: int, seed: int):
    """N Gaussians covering the surfaces of a box room centred at the origin (metres, world frame).

    -> means [N, 3], quats [N, 4] wxyz, scales [N, 3] std-devs (m), opacities [N], colors [N, 3]
    """
    from mipslam.geometry.se3 import rotmat_to_quat_wxyz

    g = torch.Generator().manual_seed(seed)
    sx, sy, sz = ROOM_M
    # faces: (normal axis, sign, the two in-plane axes, their lengths)
    faces = [(0, s, (1, 2), (sy, sz)) for s in (-1, 1)] + [(1, s, (0, 2), (sx, sz)) for s in (-1, 1)] + \
            [(2, s, (0, 1), (sx, sy)) for s in (-1, 1)]
    half = (sx / 2, sy / 2, sz / 2)
    areas = torch.tensor([a * b for _, _, _, (a, b) in faces], dtype=torch.float64)
    spacing = math.sqrt(float(areas.sum()) / count)
    per_face = torch.floor(areas / areas.sum() * count).long()
    per_face[0] += count - int(per_face.sum())
    means, normals, tangents = [], [], []
    for (axis, sign, (a, b), (la, lb)), n in zip(faces, per_face.tolist()):
        pts = torch.zeros(n, 3)
        pts[:, a] = (torch.rand(n, generator=g) - 0.5) * la
        pts[:, b] = (torch.rand(n, generator=g) - 0.5) * lb
        pts[:, axis] = sign * half[axis]
        means.append(pts)
        normal = torch.zeros(3)
        normal[axis] = 1.0
        tangent = torch.zeros(3)
        tangent[a] = 1.0
        normals.append(normal.expand(n, 3))
        tangents.append(tangent.expand(n, 3))
    means, normals, tangents = torch.cat(means), torch.cat(normals), torch.cat(tangents)
    # in-plane rotation by a random angle about the normal: R = [t', n x t', n] as columns (x, y in plane, z normal)
    angle = torch.rand(count, generator=g) * 2 * math.pi
    bitangent = torch.cross(normals, tangents, dim=1)
    t_rot = torch.cos(angle)[:, None] * tangents + torch.sin(angle)[:, None] * bitangent
    b_rot = torch.cross(normals, t_rot, dim=1)
    R = torch.stack([t_rot, b_rot, normals], dim=2)  # [N, 3, 3]
    quats = rotmat_to_quat_wxyz(R.double())
    scales = torch.stack([torch.full((count,), 0.8 * spacing), torch.full((count,), 0.8 * spacing),
                          torch.full((count,), 0.1 * spacing)], dim=1)
    scales = scales * (0.8 + 0.4 * torch.rand(count, 1, generator=g))
    opacities = 0.5 + 0.5 * torch.rand(count, generator=g)
    colors = torch.rand(count, 3, generator=g)
    return means.float(), quats.float(), scales.float(), opacities.float(), colors.float()


def camera(torch, width: int, height: int):
    """viewmat [4, 4] (T_cw) of a camera 1.5 m from the room centre looking at a corner; K [3, 3]."""
    focal = (width / 2) / math.tan(math.radians(HFOV_DEG) / 2)
    K = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    eye = torch.tensor([-1.0, -1.0, 0.3])
    target = torch.tensor([ROOM_M[0] / 2, ROOM_M[1] / 2, -0.2])
    z = (target - eye) / (target - eye).norm()
    up = torch.tensor([0.0, 0.0, -1.0])  # camera y points down: world -z is "down" in the image
    x = torch.cross(up, z, dim=0)
    x = x / x.norm()
    y = torch.cross(z, x, dim=0)
    R_wc = torch.stack([x, y, z], dim=1)
    T_cw = torch.eye(4)
    T_cw[:3, :3] = R_wc.T
    T_cw[:3, 3] = -R_wc.T @ eye
    return T_cw, K


# ----------------------------------------------------------------------------- timing

def time_forward(torch, rasterize, scene, viewmat, K, width, height) -> tuple[float, float]:
    """(wall s, process CPU s) of one forward call without autograd."""
    with torch.no_grad():
        wall, cpu = time.perf_counter(), time.process_time()
        rasterize(*scene, viewmat, K, width, height, mode="eaa", backend="cpu")
        return time.perf_counter() - wall, time.process_time() - cpu


def time_pose_backward(torch, rasterize, scene, viewmat, K, width, height) -> tuple[float, float]:
    """(wall s, process CPU s) of one pose-only forward+backward."""
    pose = viewmat.clone().requires_grad_()
    wall, cpu = time.perf_counter(), time.process_time()
    out = rasterize(*scene, pose, K, width, height, mode="eaa", backend="cpu", pose_only=True)
    loss = out.color.abs().mean() + out.depth.abs().mean()
    loss.backward()
    return time.perf_counter() - wall, time.process_time() - cpu


def median_ms(samples, which: int = 0) -> float:
    """Median in ms of the wall (which=0) or CPU (which=1) times of (wall, cpu) samples."""
    return 1e3 * statistics.median(sample[which] for sample in samples)


def fit_rows(sizes, times_ms):
    """(exponent over all sizes, exponent over the upper half) of t = c n^p."""
    from mipslam.bench import fit_power_law

    whole = fit_power_law(sizes, times_ms)
    k = max(2, (len(sizes) + 1) // 2)
    upper = fit_power_law(sizes[-k:], times_ms[-k:])
    return whole, upper


def load_average() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def render_sweeps(torch, args) -> dict:
    from mipslam.render import cpu as cpu_backend
    from mipslam.render import rasterize

    if not cpu_backend.is_available():
        raise MipslamError(f"the cpu backend is not available: {cpu_backend.unavailable_reason()}")
    width, height = (int(v) for v in args.render_size.lower().split("x"))
    counts = args.gaussian_counts
    resolutions = [tuple(int(v) for v in size.lower().split("x")) for size in args.resolutions]
    cases = [("gaussians", n, make_case(torch, n, width, height, args.seed)) for n in counts]
    pixel_scene = room_map(torch, args.pixel_gaussians, args.seed)
    cases += [("pixels", w * h, (pixel_scene, *camera(torch, w, h), w, h)) for w, h in resolutions]
    samples = {(kind, size): {"forward": [], "pose": []} for kind, size, _ in cases}
    for kind, size, (scene, viewmat, K, w, h) in cases:  # warm-up, and the visible count
        with torch.no_grad():
            out = rasterize(*scene, viewmat, K, w, h, mode="eaa", backend="cpu")
        samples[(kind, size)]["visible"] = int(out.n_visible)
        samples[(kind, size)]["image"] = f"{w}x{h}"
        samples[(kind, size)]["gaussians"] = int(scene[0].shape[0])
        time_pose_backward(torch, rasterize, scene, viewmat, K, w, h)
    for r in range(args.repeats):
        for kind, size, (scene, viewmat, K, w, h) in cases:
            samples[(kind, size)]["forward"].append(time_forward(torch, rasterize, scene, viewmat, K, w, h))
            samples[(kind, size)]["pose"].append(time_pose_backward(torch, rasterize, scene, viewmat, K, w, h))
        log.info("render round %d/%d (load %s)", r + 1, args.repeats, load_average())
    return {f"{kind}:{size}": {**v, "kind": kind, "size": size} for (kind, size), v in samples.items()}


def make_case(torch, count, width, height, seed):
    return (room_map(torch, count, seed), *camera(torch, width, height), width, height)


def pgo_sweep(args) -> dict:
    from mipslam.loop.closer import LoopOptions
    from mipslam.loop.solver import PGOOptions, optimize_pose_graph_window
    make_synthetic_pose_graph = import_test_helper("synthetic_pose_graphs").make_synthetic_pose_graph

    sa_pgo = PGOOptions(spectral_edge_weighting=True, low_frequency_correction=True)
    window = LoopOptions.pgo_window_keyframes
    # (options, window of free keyframes; 0 = the whole graph)
    methods = {"full LM": (PGOOptions(), 0), "SA-PGO (both)": (sa_pgo, 0),
               f"SA-PGO, newest {window} free (the SLAM default)": (sa_pgo, window)}
    counts = args.keyframe_counts
    graphs = {(n, s): make_synthetic_pose_graph(n, laps=2.0, sigma_translation=0.01, sigma_rotation=0.005, seed=s)
              for n in counts for s in range(args.pgo_repeats)}
    samples = {(m, n): [] for m in methods for n in counts}
    edges = {n: int(graphs[(n, 0)].graph.num_edges) for n in counts}
    for (n, s), syn in graphs.items():  # warm-up once per size (first-call costs)
        if s == 0:
            for options, free in methods.values():
                optimize_pose_graph_window(syn.graph, options, free)
    for s in range(args.pgo_repeats):
        for n in counts:
            for name, (options, free) in methods.items():
                wall, cpu = time.perf_counter(), time.process_time()
                optimize_pose_graph_window(graphs[(n, s)].graph, options, free)
                samples[(name, n)].append((time.perf_counter() - wall, time.process_time() - cpu))
        log.info("pgo round %d/%d (load %s)", s + 1, args.pgo_repeats, load_average())
    return {"edges": edges, "samples": {f"{m}:{n}": v for (m, n), v in samples.items()}, "counts": list(counts),
            "methods": list(methods)}


# ----------------------------------------------------------------------------- report

def render_tables(results: dict) -> list[str]:
    lines = []
    for kind, title, size_label in (("gaussians", "Renderer time against Gaussian count", "Gaussians"),
                                    ("pixels", "Renderer time against pixel count", "pixels")):
        rows = sorted((v for v in results.values() if v["kind"] == kind), key=lambda v: v["size"])
        if not rows:
            continue
        lines += ["", f"### {title}", "",
                  f"| {size_label} | image | Gaussians (visible) | forward ms wall (CPU) | "
                  "pose-only fwd+bwd ms wall (CPU) |", "|---:|---|---:|---:|---:|"]
        for v in rows:
            lines.append(f"| {v['size']:,} | {v['image']} | {v['gaussians']:,} ({v['visible']:,}) | "
                         f"{median_ms(v['forward']):.1f} ({median_ms(v['forward'], 1):.1f}) | "
                         f"{median_ms(v['pose']):.1f} ({median_ms(v['pose'], 1):.1f}) |")
        sizes = [v["size"] for v in rows]
        for which, clock in ((0, "wall"), (1, "CPU")):
            cells = []
            for key in ("forward", "pose"):
                whole, upper = fit_rows(sizes, [median_ms(v[key], which) for v in rows])
                cells.append(f"**{whole.exponent:.2f}** all (r2 {whole.r2:.2f}), **{upper.exponent:.2f}** upper half")
            lines.append(f"| exponent ({clock}) | | | {cells[0]} | {cells[1]} |")
    return lines


def pgo_table(pgo: dict) -> list[str]:
    methods = pgo["methods"]
    lines = ["", "### PGO time against keyframe count", "",
             "| keyframes | edges | " + " | ".join(f"{m} ms wall (CPU)" for m in methods) + " |",
             "|---:|---:|" + "---:|" * len(methods)]
    for n in pgo["counts"]:
        cells = [f"{median_ms(pgo['samples'][f'{m}:{n}']):.1f} ({median_ms(pgo['samples'][f'{m}:{n}'], 1):.1f})"
                 for m in methods]
        lines.append(f"| {n} | {pgo['edges'][n]} | " + " | ".join(cells) + " |")
    for which, clock in ((0, "wall"), (1, "CPU")):
        cells = []
        for m in methods:
            whole, upper = fit_rows(pgo["counts"], [median_ms(pgo["samples"][f"{m}:{n}"], which) for n in pgo["counts"]])
            cells.append(f"**{whole.exponent:.2f}** all (r2 {whole.r2:.2f}), **{upper.exponent:.2f}** upper half")
        lines.append(f"| exponent ({clock}) | | " + " | ".join(cells) + " |")
    return lines


def cpu_model() -> str:
    from mipslam.bench.report import cpu_model as model

    return model()


def run(options: Options, out_dir: Path) -> ScenarioResult:
    if options.quick:
        options = dataclasses.replace(options, repeats=3, pgo_repeats=3, gaussian_counts=(1_000, 10_000, 100_000),
                                      resolutions=("80x60", "320x240", "1280x720"), keyframe_counts=(25, 100, 400))
    torch = configure_threads(options.threads)
    info = {"cpu": cpu_model(), "logical_cpus": os.cpu_count(), "threads": options.threads, "torch": torch.__version__,
            "python": platform.python_version(), "load_before": load_average(), "repeats": options.repeats,
            "pgo_repeats": options.pgo_repeats, "quick": options.quick}
    log.info("%s, %s logical CPUs, renderer %d threads, PGO 1 thread; torch %s; load average %s; medians of %d "
             "(render) / %d (PGO) runs", info["cpu"], info["logical_cpus"], options.threads, info["torch"],
             info["load_before"], options.repeats, options.pgo_repeats)
    started = time.perf_counter()
    out: dict = {"machine": info}
    lines: list[str] = []
    if not options.skip_render:
        out["render"] = render_sweeps(torch, options)
        lines += render_tables(out["render"])
    if not options.skip_pgo:
        out["pgo"] = pgo_sweep(options)
        lines += pgo_table(out["pgo"])
    info["load_after"] = load_average()
    info["seconds"] = time.perf_counter() - started
    lines.append(f"\nload average {info['load_before']} -> {info['load_after']}; {info['seconds']:.0f} s in all")
    from mipslam.bench.record import write_benchmark

    report = "\n".join(lines)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), out, threads=options.threads, markdown=report)
    return ScenarioResult(files, report)
