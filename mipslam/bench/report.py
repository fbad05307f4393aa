"""The bench's outputs: ``bench.json`` (machine, execution, every job row, per-setting summaries),
``bench.md`` (tables) and ``bench.png`` (frames/s against ATE and against PSNR, Pareto front marked).

Matplotlib draws on its Agg canvas (no pyplot, no global backend change); files are written atomically.
"""
from __future__ import annotations

import io
import logging
import os
import platform
import subprocess
from pathlib import Path
from typing import Any, Sequence

from mipslam import __version__
from mipslam.bench.execute import JobResult
from mipslam.bench.summary import SettingSummary, Spread, ordered_stages
from mipslam.io.run_folder import write_bytes_atomic, write_json_atomic, write_text_atomic

__all__ = ["BenchFiles", "bench_json", "bench_markdown", "machine_info", "plot_bench", "write_outputs"]

log = logging.getLogger(__name__)

BENCH_JSON, BENCH_MD, BENCH_PNG, SWEEP_PNG = "bench.json", "bench.md", "bench.png", "bench_sweep.png"
REPO_ROOT = Path(__file__).resolve().parents[2]


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name") and ":" in line:
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_commit(folder: Path = REPO_ROOT) -> dict[str, Any] | None:
    """HEAD commit of the checkout mipslam runs from, and whether it has uncommitted changes; None without git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=folder, capture_output=True, text=True, timeout=10,
                              check=False)
        if head.returncode != 0:
            return None
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=folder,
                                capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return {"commit": head.stdout.strip(), "uncommitted_changes": bool(status.stdout.strip())}


def machine_info(threads: int | list[int]) -> dict[str, Any]:
    """The machine the bench ran on: CPU, cores, load, Python/torch versions, render backends, git commit."""
    import torch

    try:
        from mipslam.render import available_backends

        backends = list(available_backends())
    except ImportError as exc:
        backends = [f"unknown ({exc})"]
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    try:
        load = [round(v, 2) for v in os.getloadavg()]
    except (AttributeError, OSError):
        load = None
    return {
        "cpu_model": cpu_model(), "logical_cores": os.cpu_count(), "usable_cores": usable,
        "load_average_1_5_15_min_at_start": load, "threads_per_job": threads, "platform": platform.platform(),
        "host": platform.node(), "python": platform.python_version(), "torch": torch.__version__,
        "mipslam": __version__, "render_backends_available": backends, "cuda_available": torch.cuda.is_available(),
        "git": git_commit(),
        "environment": {k: os.environ[k] for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "MALLOC_MMAP_THRESHOLD_",
                                                   "MALLOC_TRIM_THRESHOLD_") if k in os.environ},
    }


def bench_json(machine: dict, execution: dict, request: dict, rows: Sequence[JobResult],
               summaries: Sequence[SettingSummary]) -> dict[str, Any]:
    backends = sorted({f"{r.device} / render {r.render_backend}" for r in rows
                       if r.device is not None and r.system == "mipslam"})
    return {
        "format": "mipslam bench 1",
        "machine": {**machine, "backend_used": backends},
        "execution": execution,
        "request": request,
        "protocol": {
            "fps": "frames / seconds of the SLAM stages (timings.json: start-up and writing outputs excluded)",
            "stage_ms_per_frame": "stage total seconds / frames * 1000 (the stages sum to 1000 / fps)",
            "ate_rmse_cm": "ATE RMSE of all frames after the run's alignment (eval.alignment, se3 by default)",
            "rpe": "RPE RMSE over consecutive matched frames (translation cm, rotation degrees)",
            "lost_frames": "peers: frames without a pose (not in the ATE); mipslam: frames flagged as tracking "
                           "failures (they keep a motion-model pose and are in the ATE); summarised over every "
                           "job that reported it, also those whose evaluation failed",
            "peers": "peer systems read the same frames through mipslam's readers (same association and frame "
                     "selection) at the resolution on disk, and are evaluated with the same code and protocol; "
                     "their frames/s counts the peer's own per-frame processing",
            "psnr_db": "novel-view PSNR: MonoGS's frames (every 5th frames.json position that is not a keyframe) "
                       "rendered at the native resolution in the run's footprint mode; estimated poses, no exposure "
                       "compensation",
            "psnr_train_db": "training-view PSNR: the keyframes, otherwise as psnr_db",
            "wall_s": "wall time of the 'mipslam run' process",
            "summary": "median over the repeats without an error; spread as min/max and interquartile range",
            "pareto_front": "a setting is on the front when no other has >= frames/s and <= ATE (resp. >= PSNR) "
                            "with one of them strict; settings without values are not on it",
        },
        "jobs": [r.to_dict() for r in rows],
        "settings": [s.to_dict() for s in summaries],
    }


# ----------------------------------------------------------------------------- markdown

def _fmt(value: float | None, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _cell(s: Spread | None, digits: int) -> str:
    """``median [min–max]`` (just the median when there is one value)."""
    if s is None:
        return "–"
    if s.n == 1 or s.min == s.max:
        return _fmt(s.median, digits)
    return f"{s.median:.{digits}f} [{s.min:.{digits}f}–{s.max:.{digits}f}]"


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def bench_markdown(data: dict[str, Any], summaries: Sequence[SettingSummary], rows: Sequence[JobResult]) -> str:
    m, ex = data["machine"], data["execution"]
    git = m.get("git") or {}
    commit = git.get("commit", "unknown")[:12] + (" (with uncommitted changes)" if git.get("uncommitted_changes") else "")
    lines = [
        f"# mipslam bench: {data['request']['target']}",
        "",
        f"Machine: {m['cpu_model']}, {m['usable_cores']} usable of {m['logical_cores']} logical cores, load average "
        f"{m['load_average_1_5_15_min_at_start']} at the start; {m['threads_per_job']} threads per job; torch "
        f"{m['torch']}, backend {', '.join(m['backend_used']) or 'unknown'}; mipslam {m['mipslam']} at {commit}.",
        f"Execution: {ex['executor']} ({ex.get('note', '')}). Repeats: {data['request']['repeat']}, seed "
        f"{data['request']['seed']}.",
        "",
        "Values are medians over the repeats without an error, with [min–max] where they differ. frames/s counts the "
        "SLAM stages only; stage columns are milliseconds per frame. PSNR at the native resolution: novel views "
        "(every 5th frame that is not a keyframe, as MonoGS) and train (the keyframes). "
        "Front: on the Pareto front of frames/s against ATE (A) and against novel-view PSNR (P).",
        "",
    ]
    stages = ordered_stages(s for summary in summaries for s in summary.stage_ms_per_frame)
    header = ["setting", "system", "ok", "frames/s", "ATE cm", "RPE cm", "RPE deg", "lost", "PSNR novel dB",
              "PSNR train dB",
              *(f"{s} ms" for s in stages), "Gaussians", "keyframes", "wall s", "front"]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for s in summaries:
        front = "".join(flag for flag, on in (("A", s.on_front_ate), ("P", s.on_front_psnr)) if on) or ""
        cells = [f"`{_escape(s.setting)}`", s.system, f"{s.jobs - s.failed}/{s.jobs}", _cell(s.fps, 2),
                 _cell(s.ate_rmse_cm, 3), _cell(s.rpe_trans_cm, 3), _cell(s.rpe_rot_deg, 3), _cell(s.lost_frames, 0),
                 _cell(s.psnr_db, 2), _cell(s.psnr_train_db, 2),
                 *(_cell(s.stage_ms_per_frame.get(st), 1) for st in stages),
                 _cell(s.gaussians, 0), _cell(s.keyframes, 0), _cell(s.wall_s, 1), front]
        lines.append("| " + " | ".join(cells) + " |")
    sweeps = data["request"].get("sweeps") or {}
    for key in sweeps:
        lines += ["", *sweep_table(summaries, key, list(sweeps[key]))]
    failed = [r for r in rows if not r.ok]
    lines += ["", f"## Jobs ({len(rows)}, {len(failed)} failed)", ""]
    lines += ["| setting | repeat | frames/s | ATE cm | lost | PSNR novel dB | PSNR train dB | Gaussians | keyframes "
              "| wall s | host | error |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| `{_escape(r.setting)}` | {r.repeat} | {_fmt(r.fps, 2)} | {_fmt(r.ate_rmse_cm, 3)} | "
                     f"{r.lost_frames if r.lost_frames is not None else '–'} | "
                     f"{_fmt(r.psnr_db, 2)} | {_fmt(r.psnr_train_db, 2)} | "
                     f"{r.gaussians if r.gaussians is not None else '–'} | "
                     f"{r.keyframes if r.keyframes is not None else '–'} | {_fmt(r.wall_s, 1)} | {r.host} | "
                     f"{_escape(r.error) if r.error else ''} |")
    return "\n".join(lines) + "\n"


def sweep_series(summaries: Sequence[SettingSummary], key: str, values: list[str]
                 ) -> dict[str, dict[str, SettingSummary]]:
    """The settings of a sweep over ``key`` as series: series label (the setting without ``key=...``) ->
    value text -> summary. Settings that do not take ``key`` (e.g. a peer under a non-dataset sweep) are left out."""
    series: dict[str, dict[str, SettingSummary]] = {}
    prefix = f"{key}="
    for s in summaries:
        value = next((a[len(prefix):] for a in s.assignments if a.startswith(prefix)), None)
        if value is None or value not in values:
            continue
        rest = " ".join([s.setting.split(" ")[0], *(a for a in s.assignments if not a.startswith(prefix))])
        series.setdefault(rest, {})[value] = s
    return series


def sweep_table(summaries: Sequence[SettingSummary], key: str, values: list[str]) -> list[str]:
    """Markdown lines: one row per series, one column per value of ``key``: ATE cm (lost frames)."""
    series = sweep_series(summaries, key, values)
    lines = [f"## Sweep of `{key}`: ATE RMSE cm (lost frames), medians over repeats", "",
             "| system | " + " | ".join(f"{key}={v}" for v in values) + " |", "|---|" + "---|" * len(values)]
    for name, by_value in series.items():
        cells = []
        for v in values:
            s = by_value.get(v)
            if s is None or s.ate_rmse_cm is None:
                lost = "" if s is None or s.lost_frames is None else f" (lost {s.lost_frames.median:.0f})"
                cells.append("–" if s is None else f"failed{lost}")
            else:
                lost = "" if s.lost_frames is None else f" ({s.lost_frames.median:.0f})"
                cells.append(f"{_cell(s.ate_rmse_cm, 3)}{lost}")
        lines.append(f"| `{_escape(name)}` | " + " | ".join(cells) + " |")
    return lines


# ----------------------------------------------------------------------------- plot

def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def plot_bench(summaries: Sequence[SettingSummary]) -> bytes:
    """PNG bytes: two panels, frames/s (x) against ATE RMSE and against PSNR (y), medians with min–max bars,
    the Pareto front drawn as a line through its settings."""
    figure = _figure(11.0, 4.6)
    panels = (("ate_rmse_cm", "ATE RMSE (cm), lower is better", "on_front_ate", False),
              ("psnr_db", "novel-view PSNR (dB), higher is better", "on_front_psnr", True))
    for k, (metric, ylabel, front_attr, higher) in enumerate(panels):
        ax = figure.add_subplot(1, 2, k + 1)
        shown = [s for s in summaries if s.fps is not None and getattr(s, metric) is not None]
        if not shown:
            text = "no PSNR: peers render no images" if metric == "psnr_db" and any(
                x.fps is not None and x.system != "mipslam" for x in summaries) else "no successful runs"
            ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
        for s in shown:
            fps, y = s.fps, getattr(s, metric)
            on = getattr(s, front_attr)
            peer = s.system != "mipslam"
            ax.errorbar([fps.median], [y.median], xerr=[[fps.median - fps.min], [fps.max - fps.median]],
                        yerr=[[y.median - y.min], [y.max - y.median]], fmt="*" if on else "s" if peer else "o",
                        color="#d62728" if on else "#2ca02c" if peer else "#1f77b4", ms=11 if on else 6,
                        capsize=2, lw=0.8)
            ax.annotate(s.setting, (fps.median, y.median), textcoords="offset points", xytext=(5, 4), fontsize=7)
        front = sorted((s.fps.median, getattr(s, metric).median) for s in shown if getattr(s, front_attr))
        if len(front) > 1:
            ax.plot(*zip(*front), "-", color="#d62728", lw=1.0, alpha=0.6, label="Pareto front")
            ax.legend(fontsize=8, loc="best")
        ax.set_xlabel("frames per second (SLAM stages)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    failed = sum(1 for s in summaries if s.fps is None)
    title = "mipslam bench: medians over repeats, bars min–max, stars on the Pareto front, squares peers"
    figure.suptitle(title + (f" ({failed} setting(s) without a successful run not shown)" if failed else ""), fontsize=9)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def plot_sweep(summaries: Sequence[SettingSummary], key: str, values: list[str]) -> bytes:
    """PNG bytes: ATE RMSE and lost frames (y) against the values of ``key`` (x, in the order given), a line per
    series (mipslam preset or peer), medians with min–max bars; a failed setting leaves a gap."""
    figure = _figure(11.0, 4.4)
    series = sweep_series(summaries, key, values)
    x = list(range(len(values)))
    for k, (metric, ylabel) in enumerate((("ate_rmse_cm", "ATE RMSE (cm)"), ("lost_frames", "lost frames"))):
        ax = figure.add_subplot(1, 2, k + 1)
        for name, by_value in series.items():
            points = [(i, getattr(by_value[v], metric)) for i, v in enumerate(values)
                      if v in by_value and getattr(by_value[v], metric) is not None]
            if not points:
                continue
            xs = [p[0] for p in points]
            med = [p[1].median for p in points]
            err = [[p[1].median - p[1].min for p in points], [p[1].max - p[1].median for p in points]]
            ax.errorbar(xs, med, yerr=err, fmt="-o", ms=4, capsize=2, lw=1.0, label=name)
        ax.set_xticks(x, [str(v) for v in values])
        ax.set_xlabel(key)
        ax.set_ylabel(ylabel)
        if metric == "ate_rmse_cm":
            ax.set_yscale("log")
        else:  # counts: whole numbers from 0
            ax.set_ylim(-0.3, max(1.0, ax.get_ylim()[1]))  # points at 0 stay visible
            ax.yaxis.get_major_locator().set_params(integer=True)
        ax.grid(alpha=0.3)
        if series:
            ax.legend(fontsize=7, loc="best")
    figure.suptitle(f"mipslam bench: sweep of {key} (medians over repeats, bars min–max)", fontsize=9)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


# ----------------------------------------------------------------------------- files

class BenchFiles:
    """Paths of the outputs in ``out_dir``."""

    def __init__(self, out_dir: Path):
        self.out_dir = Path(out_dir)
        self.json = self.out_dir / BENCH_JSON
        self.markdown = self.out_dir / BENCH_MD
        self.plot = self.out_dir / BENCH_PNG
        self.sweep_plots: list[Path] = []


def write_outputs(out_dir: Path, machine: dict, execution: dict, request: dict, rows: Sequence[JobResult],
                  summaries: Sequence[SettingSummary]) -> BenchFiles:
    """Write bench.json, bench.md and bench.png into ``out_dir`` (created if needed)."""
    files = BenchFiles(out_dir)
    files.out_dir.mkdir(parents=True, exist_ok=True)
    data = bench_json(machine, execution, request, rows, summaries)
    write_json_atomic(files.json, data)
    write_text_atomic(files.markdown, bench_markdown(data, summaries, rows))
    write_bytes_atomic(files.plot, plot_bench(summaries))
    sweeps = request.get("sweeps") or {}
    for key, values in sweeps.items():
        path = files.out_dir / (SWEEP_PNG if len(sweeps) == 1 else f"bench_sweep_{key}.png")
        write_bytes_atomic(path, plot_sweep(summaries, key, list(values)))
        files.sweep_plots.append(path)
    return files
