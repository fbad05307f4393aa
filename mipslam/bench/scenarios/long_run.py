"""Benchmark: a long run on a data_synth loop sequence that revisits the same room (docs/robustness.md, "Long runs").

The sequence is data_synth's ``loop`` trajectory at 80x60 by default (``long_run.width``, ``long_run.height``),
``long_run.laps`` laps (by default at least 2 and as many as keep at least 240 frames per lap, where the camera
looks outwards and turns a full 360 degrees: 2 laps for 500 frames, 8 for 2000). The first lap covers the room
and every later lap revisits it. (With fewer than 240 frames per lap, e.g. 100 frames, each lap sweeps the +x
wall.) ``mipslam`` runs it with the built-in ``synthetic`` config and ``--preset fast`` (``run.threads`` 1 by
default, checkpoints every 50 frames, 2 kept) in this process, and a per-frame probe (the run's observer,
:class:`mipslam.observer.Observer`, sampling at the end of each frame's tracking) records, for every frame:

* wall time and this process's CPU time since the previous frame's probe (tracking, keyframe
  decision, mapping, loop closure, checkpoint writes: everything the frame loop does), seconds;
* resident memory (RSS) of the process, MiB (psutil where installed, else ``/proc/self/status``);
* Gaussians in the map (after the previous frame);
* keyframes in the map (before the frame's keyframe decision);
* checkpoint files on disk.

Checks (printed with PASS/FAIL; the exit code is 1 if one fails):

* RSS flat after the room is covered: RSS at the end minus RSS when the room is covered (end of
  the first lap; the middle of the run for a single lap) is at most ``max(10 %, 64 MiB)``;
* no growth of per-frame time, over the revisits (from the frame the room is covered, when loop
  closure starts to run and the map stops growing): the median CPU time per frame of their last
  quarter <= 1.5 x that of their first quarter, and the same for the mean, for keyframes and for the
  other frames apart (CPU rather than wall time, which other processes on shared cores inflate; the
  mean catches work done on some frames only, such as pose-graph optimisation).
  Keyframes cost about twice what other frames do and make up about half of the frames at 80x60, so
  one median over both flips between the two costs as the share of keyframes in a quarter moves; and
  a revisited keyframe costs about twice a first-lap one (loop detection and verification), so the
  first lap is not compared with the last. With 2 laps the quarters lie in different parts of the
  room, whose costs differ; the check is fair from about 4 laps (1000 frames) on;
* median frame time, last 1000 frames vs frames 1000-2000: the median wall time per frame of the last
  1000 frames <= 1.2 x that of frames 1000-1999 (the long-run target; wall time, so load from other
  processes on shared cores counts). Runs under 3000 frames, where the two windows would overlap, compare
  the last tenth of the frames with the second tenth (frames N/10 .. 2N/10); the text names the windows and
  the share of keyframes in each. The last frame is left out: its period runs to the end of the run
  (final refinement, outputs);
* Gaussian count plateaus: the last quarter of the run adds at most 5 % to the count;
* keyframes stop growing on revisits: the keyframes in the map at the end minus those when the room is
  covered are at most ``max(2, 5 % of the latter)`` (a revisit may fill a gap the first lap left; one that
  replaces an older keyframe adds none); the text gives both counts, the difference and the peak;
* bounded checkpoint files: never more than ``KEEP_CHECKPOINTS + 1`` (+1: the moment between
  writing a new checkpoint and deleting the oldest).

Plot: ``OUT/bench_curves.png``, three panels over the frame index: wall time per frame (ms; points, and
their rolling median of 100 frames; the y-axis ends at the 99th percentile, the legend counts the frames
above), keyframes in the map, and RSS (MiB); a dashed line at the frame the room is covered.

Run: ``mipslam bench --scenario long_run --out bench_out/long500 --set long_run.frames=500``
(``long_run.frames=100`` for a quick look, ``2000`` for the full run; ``long_run.keep=true`` keeps the sequence
and run folder in OUT/work; ``long_run.progress=true`` appends one JSON line per frame to OUT/progress.jsonl
while the run goes on, and ``long_run.summarise=PROGRESS`` tabulates such a file, of a run still going on or cut
short, and checks and plots it so far). The curves are tabulated at ``long_run.rows`` frames in OUT/bench.md, which
names the plot; OUT/bench.json holds them per frame with the checks and the plot's name. The target the checks
follow: 10,000 frames at 320x240 (``--set long_run.frames=10000 --set long_run.width=320 --set long_run.height=240``).
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import io  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

import data_synth  # noqa: E402
from mipslam.bench.record import write_benchmark  # noqa: E402
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult  # noqa: E402
from mipslam.bench.scenarios.checkout import CONFIGS, REPO, parameters  # noqa: E402
from mipslam.checkpoint import list_checkpoints  # noqa: E402
from mipslam.config import load_config  # noqa: E402
from mipslam.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from mipslam.run_control import KEEP_CHECKPOINTS  # noqa: E402
from mipslam.io.run_folder import write_bytes_atomic  # noqa: E402
from mipslam.io.tum import read_tum_trajectory  # noqa: E402
from mipslam.observer import Observer  # noqa: E402
from mipslam.pipeline import run_slam  # noqa: E402

log = logging.getLogger(__name__)

FULL_TURN_FRAMES_PER_LAP = 240  # data_synth.trajectories.FULL_TURN_MIN_FRAMES

RSS_GROWTH_FRACTION, RSS_GROWTH_MIB = 0.10, 64.0
TIME_GROWTH_RATIO = 1.5
MIN_CLASS_SAMPLES = 5  # per quarter, for a median of keyframes or of other frames
GAUSSIAN_GROWTH_FRACTION = 0.05
# Keyframes a revisit may add: one where the first lap left a gap or drift made the view look new, a few in all,
# never a count that grows with the laps (a replaced keyframe adds none). The floor keeps a map of few keyframes
# (a short run) from failing on one such keyframe.
KEYFRAME_REVISIT_FRACTION, KEYFRAME_REVISIT_MIN = 0.05, 2
FRAME_TIME_RATIO = 1.2  # median wall time per frame, late window against early one (the long-run target)
FRAME_TIME_WINDOW = 1000  # frames per window: the last 1000 against frames 1000-1999
FRAME_TIME_FULL_MIN_FRAMES = 3 * FRAME_TIME_WINDOW  # from here the two windows do not overlap
FRAME_TIME_SHORT_FRACTION = 0.1  # shorter runs: the second and the last tenth (1000 of the target's 10,000 frames)
ROLLING_MEDIAN_FRAMES = 100  # the plot's rolling median of the per-frame time
# The time panel's y-axis ends at this quantile of the per-frame times: a few spikes (frame 0 mapped from scratch,
# pose-graph solves) would flatten the rest; its legend counts the frames above.
PLOT_TIME_QUANTILE = 0.99
PLOT_SIZE_IN, PLOT_DPI = (9.0, 8.0), 110
PLOT_NAME = f"{RECORD_NAME}_curves.png"  # next to bench.md


@dataclass(frozen=True)
class Options:
    frames: int = 500
    laps: int = 0  # laps of the loop (0: as many as keep >= 240 frames per lap, at least 2)
    width: int = 80
    height: int = 60
    preset: str = "fast"
    threads: int = 1
    rows: int = 10  # rows of the tabulated curves
    keep: bool = False  # keep the sequence and the run folder in OUT/work (default: a temporary folder)
    progress: bool = False  # append one JSON line per frame to OUT/progress.jsonl while the run goes on
    summarise: str = ""  # a progress file to tabulate and check instead of running (frames and laps as its run's)
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE of the run


SMOKE = dict(frames=8, laps=2, width=40, height=30, rows=4,
             config_overrides=("mapping.first_frame_iterations=10", "mapping.iterations=3", "tracking.iterations=3"))


def rss_mib() -> float:
    """Resident set size of this process in MiB (psutil, else /proc/self/status VmRSS)."""
    try:
        import psutil
    except ImportError:
        psutil = None
    if psutil is not None:
        return psutil.Process().memory_info().rss / 2**20
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024  # kB
    return float("nan")


@dataclass(eq=False)
class FrameProbe(Observer):
    """The run's observer: samples time, RSS, Gaussians and checkpoint files once per frame (after tracking)."""

    checkpoints: Path
    progress: Path | None = None  # one JSON line per frame, flushed at once (a run cut short keeps its curve)
    frame: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)  # wall time since the previous probe
    cpu_seconds: list[float] = field(default_factory=list)  # this process's CPU time since the previous probe
    rss_mib: list[float] = field(default_factory=list)
    gaussians: list[int] = field(default_factory=list)
    checkpoint_files: list[int] = field(default_factory=list)
    keyframes_before: list[int] = field(default_factory=list)  # keyframes in the map when the frame was tracked
    last_period_s: float = float("nan")  # from the last probe to the end of the run (last frame and outputs)
    last_cpu_s: float = float("nan")
    final_gaussians: int = 0
    final_checkpoint_files: int = 0
    final_keyframes: int = 0
    _last: float | None = None
    _last_cpu: float | None = None

    def finish(self, gaussians: int, keyframes: int) -> None:
        self.last_period_s = time.perf_counter() - self._last if self._last is not None else float("nan")
        self.last_cpu_s = time.process_time() - self._last_cpu if self._last_cpu is not None else float("nan")
        self.final_gaussians = gaussians
        self.final_keyframes = keyframes
        self.final_checkpoint_files = len(list_checkpoints(self.checkpoints))

    def keyframe_flags(self) -> list[bool]:
        """Whether each frame became a keyframe: the count grew by the next probe (or by the end of the run)."""
        after = self.keyframes_before[1:] + [self.final_keyframes]
        return [later > now for now, later in zip(self.keyframes_before, after)]

    def periods(self) -> list[float]:
        """Wall seconds of the frame loop per frame: from one probe (after tracking) to the next."""
        return self.seconds[1:] + [self.last_period_s]

    def cpu_periods(self) -> list[float]:
        """CPU seconds of this process per frame (insensitive to other processes sharing the cores)."""
        return self.cpu_seconds[1:] + [self.last_cpu_s]

    def __post_init__(self):
        Observer.__init__(self)

    def on_stage(self, name: str, entering: bool) -> None:
        """At the end of each frame's tracking: time, CPU time, RSS and checkpoint files."""
        if name != "tracking" or entering:
            return
        now, cpu = time.perf_counter(), time.process_time()
        self.frame.append(int(self.frame_index))
        self.seconds.append(float("nan") if self._last is None else now - self._last)
        self.cpu_seconds.append(float("nan") if self._last_cpu is None else cpu - self._last_cpu)
        self._last, self._last_cpu = now, cpu
        self.rss_mib.append(rss_mib())
        self.checkpoint_files.append(len(list_checkpoints(self.checkpoints)))

    def on_frame(self, record, state) -> None:
        """The map as the frame's tracking saw it: Gaussians after the previous frame, keyframes before this one."""
        self.gaussians.append(state.gaussian_counts[-2] if len(state.gaussian_counts) > 1 else 0)
        self.keyframes_before.append(len(state.keyframe_frames) - (1 if record.keyframe_id >= 0 else 0))
        if self.progress is not None:
            with open(self.progress, "a", encoding="utf-8") as out:
                period, cpu_period = self.seconds[-1], self.cpu_seconds[-1]
                out.write(json.dumps({"frame": self.frame[-1], "period_before_s": None if period != period else period,
                                      "cpu_before_s": None if cpu_period != cpu_period else cpu_period,
                                      "rss_mib": self.rss_mib[-1], "gaussians": self.gaussians[-1],
                                      "checkpoint_files": self.checkpoint_files[-1],
                                      "keyframes_before": self.keyframes_before[-1]}) + "\n")


def default_laps(frames: int) -> int:
    return max(2, frames // (FULL_TURN_FRAMES_PER_LAP + 10))


def covered_frame(frames: int, laps: int) -> int:
    """The frame by which the room has been seen once: the end of the first lap (middle for one lap)."""
    return (frames - 1) // laps if laps > 1 else frames // 2


def quarter(values: list[float], which: int) -> list[float]:
    n = len(values)
    return values[which * n // 4:(which + 1) * n // 4]


def frame_costs(periods: list[float]) -> list[float]:
    """Per-frame periods (seconds) with the last one unknown (NaN): its period runs to the end of the run (final
    refinement, outputs) and is no frame's cost."""
    return periods[:-1] + [float("nan")]


def time_growth_check(probe: FrameProbe, covered: int) -> tuple[str, bool, str]:
    """The per-frame time check of the module docstring: last against first quarter of the revisits (frames after
    ``covered``), keyframes and other frames apart (one class when the probe has no keyframe counts: a progress
    file from before they were recorded). The last frame is left out, as in :func:`frame_time_check`."""
    cpu = [t for t in probe.cpu_periods()[1:] if t == t]
    kind = "CPU" if len(cpu) > 4 else "wall"  # CPU where recorded: others on the shared cores inflate wall time
    periods = probe.cpu_periods() if kind == "CPU" else probe.periods()
    periods = frame_costs(periods)
    flags = probe.keyframe_flags() if probe.keyframes_before else [None] * len(periods)
    frames = list(zip(periods, flags))  # (seconds, became a keyframe) per frame
    revisits = [(t, flag) for t, flag in frames[covered + 1:] if t == t]
    passed, parts, compared = True, [], 0
    classes = (("keyframes", True), ("other frames", False)) if probe.keyframes_before else (("all frames", None),)
    for label, flag in classes:
        first = [t for t, f in quarter(revisits, 0) if f == flag]
        last = [t for t, f in quarter(revisits, 3) if f == flag]
        if len(first) < MIN_CLASS_SAMPLES or len(last) < MIN_CLASS_SAMPLES:
            parts.append(f"{label}: {len(first)} / {len(last)} frames in the first / last quarter, too few to compare")
            continue
        median_first, median_last = statistics.median(first), statistics.median(last)
        mean_first, mean_last = statistics.fmean(first), statistics.fmean(last)
        passed &= median_last <= TIME_GROWTH_RATIO * median_first and mean_last <= TIME_GROWTH_RATIO * mean_first
        compared += 1
        parts.append(f"{label} median {median_first * 1000:.0f} -> {median_last * 1000:.0f} {kind} ms "
                     f"(ratio {median_last / median_first:.2f}), mean {mean_first * 1000:.0f} -> "
                     f"{mean_last * 1000:.0f} ms (ratio {mean_last / mean_first:.2f}), {len(first)} / {len(last)} frames")
    passed &= compared > 0  # nothing compared is no evidence of flat cost
    parts.append(f"allowed {TIME_GROWTH_RATIO} for each ratio")
    # for the reader: what a keyframe cost before loop closure ran (frame 0, mapped from scratch, left out)
    before = [t for t, f in frames[1:covered + 1] if t == t and f is not False]
    if before:
        label = "keyframes" if probe.keyframes_before else "all frames"
        parts.append(f"before the room is covered: {label} median {statistics.median(before) * 1000:.0f} {kind} ms")
    return "no growth of per-frame time over the revisits", passed, "; ".join(parts)


def keyframes_after(probe: FrameProbe) -> list[int]:
    """Keyframes in the map after each frame (the next probe's count; the end of the run's after the last)."""
    return probe.keyframes_before[1:] + [probe.final_keyframes] if probe.keyframes_before else []


def keyframe_growth_check(probe: FrameProbe, covered: int) -> tuple[str, bool, str]:
    """Keyframes added over the revisits (the end of the run against frame ``covered``, when the room has been
    seen once) are at most ``max(KEYFRAME_REVISIT_MIN, KEYFRAME_REVISIT_FRACTION * keyframes at covered)``;
    a revisit that replaces an older keyframe adds none."""
    name = "keyframes stop growing on revisits"
    if not probe.keyframes_before:
        return name, False, "no keyframe counts recorded (a progress file from before they were)"
    at_covered, at_end = probe.keyframes_before[covered], probe.final_keyframes
    added = at_end - at_covered
    allowed = max(KEYFRAME_REVISIT_MIN, KEYFRAME_REVISIT_FRACTION * at_covered)
    peak = max(keyframes_after(probe)[covered:])
    return name, added <= allowed, (f"{at_covered} keyframes when the room is covered (frame {covered}), {at_end} at "
                                    f"the end: {added:+d} over the revisits (allowed {allowed:g}: "
                                    f"max({KEYFRAME_REVISIT_MIN}, {KEYFRAME_REVISIT_FRACTION * 100:g} % of "
                                    f"{at_covered})); peak {peak}")


def frame_time_windows(frames: int) -> tuple[range, range]:
    """(early, late) windows of frame positions whose median wall times per frame :func:`frame_time_check`
    compares: frames 1000-1999 and the last 1000 from ``FRAME_TIME_FULL_MIN_FRAMES`` frames on, else the
    second and the last tenth of the run (at least one frame each)."""
    if frames >= FRAME_TIME_FULL_MIN_FRAMES:
        return range(FRAME_TIME_WINDOW, 2 * FRAME_TIME_WINDOW), range(frames - FRAME_TIME_WINDOW, frames)
    tenth = max(1, int(frames * FRAME_TIME_SHORT_FRACTION))
    return range(min(tenth, frames), min(2 * tenth, frames)), range(max(0, frames - tenth), frames)


def frame_time_check(probe: FrameProbe) -> tuple[str, bool, str]:
    """The median wall time per frame (:meth:`FrameProbe.periods`) of the late window of
    :func:`frame_time_windows` is at most ``FRAME_TIME_RATIO`` times that of the early one (wall time, as the
    long-run target states it: on shared cores it carries the other processes' load). The last frame has no time:
    its period runs to the end of the run (final refinement, outputs)."""
    name = f"median frame time, last {FRAME_TIME_WINDOW} frames vs frames {FRAME_TIME_WINDOW}-{2 * FRAME_TIME_WINDOW}"
    periods = frame_costs(probe.periods())
    flags = probe.keyframe_flags() if probe.keyframes_before else None
    early, late = frame_time_windows(len(periods))
    parts = [] if len(periods) >= FRAME_TIME_FULL_MIN_FRAMES else [
        f"run of {len(periods)} frames, under {FRAME_TIME_FULL_MIN_FRAMES}: the second tenth against the last tenth"]
    medians = []
    for window in (early, late):
        times = [periods[i] for i in window if periods[i] == periods[i]]
        label = (f"frames {probe.frame[window[0]]}-{probe.frame[window[-1]]}" if len(window) > 1 else
                 f"frame {probe.frame[window[0]]}" if window else "no frames")
        if not times:
            parts.append(f"{label}: no wall time recorded")
            continue
        share = f", {sum(flags[i] for i in window) / len(window) * 100:.0f} % keyframes" if flags else ""
        medians.append(statistics.median(times))
        parts.append(f"{label}: median {medians[-1] * 1000:.0f} wall ms ({len(times)} frames{share})")
    if len(medians) < 2:
        return name, False, "; ".join(parts + ["too few frames to compare"])
    ratio = medians[1] / medians[0]
    parts.append(f"ratio {ratio:.2f}, allowed {FRAME_TIME_RATIO}")
    return name, ratio <= FRAME_TIME_RATIO, "; ".join(parts)


def checks(probe: FrameProbe, covered: int, keep: int) -> list[tuple[str, bool, str]]:
    """(name, passed, the numbers) for the six properties of the module docstring; ``covered``: the frame by
    which the room has been seen once (:func:`covered_frame`)."""
    out = []
    rss_covered, rss_end = probe.rss_mib[covered], probe.rss_mib[-1]
    allowed = max(RSS_GROWTH_FRACTION * rss_covered, RSS_GROWTH_MIB)
    out.append(("RSS flat after the room is covered", rss_end - rss_covered <= allowed,
                f"{rss_covered:.0f} MiB at frame {covered}, {rss_end:.0f} MiB at the end "
                f"({rss_end - rss_covered:+.0f} MiB, allowed {allowed:.0f}); peak {max(probe.rss_mib):.0f} MiB"))
    out.append(time_growth_check(probe, covered))
    out.append(frame_time_check(probe))
    start = probe.gaussians[3 * len(probe.gaussians) // 4]
    end = probe.final_gaussians
    out.append(("Gaussian count plateaus", end <= (1 + GAUSSIAN_GROWTH_FRACTION) * start,
                f"{start} Gaussians at 3/4 of the run, {end} at the end ({(end / max(start, 1) - 1) * 100:+.1f} %, "
                f"allowed +{GAUSSIAN_GROWTH_FRACTION * 100:.0f} %)"))
    out.append(keyframe_growth_check(probe, covered))
    most = max(max(probe.checkpoint_files), probe.final_checkpoint_files)
    out.append(("bounded checkpoint files", most <= keep + 1,
                f"at most {most} checkpoint files on disk during the run, {probe.final_checkpoint_files} at the end "
                f"(keep_checkpoints={keep})"))
    return out


def curve_rows(probe: FrameProbe, rows: int) -> list[dict]:
    """Every ``len/rows``-th frame: median per-frame time over the stretch, RSS, Gaussians, keyframes (None when
    not recorded), checkpoint files."""
    n = len(probe.frame)
    step = max(1, n // rows)
    out = []
    for start in range(0, n, step):
        stretch = [t for t in probe.periods()[max(1, start):start + step] if t == t]
        cpu = [t for t in probe.cpu_periods()[max(1, start):start + step] if t == t]
        end = min(n, start + step) - 1
        out.append({"frames": f"{probe.frame[start]}-{probe.frame[end]}",
                    "median_ms": 1000 * statistics.median(stretch) if stretch else float("nan"),
                    "median_cpu_ms": 1000 * statistics.median(cpu) if cpu else float("nan"),
                    "rss_mib": probe.rss_mib[end], "gaussians": probe.gaussians[end],
                    "keyframes": probe.keyframes_before[end] if probe.keyframes_before else None,
                    "checkpoint_files": probe.checkpoint_files[end]})
    return out


def row_lines(rows: list[dict]) -> list[str]:
    """The curves as a markdown table."""
    lines = ["| frames | wall ms | CPU ms | RSS MiB | Gaussians | keyframes | checkpoint files |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        keyframes = "–" if row.get("keyframes") is None else row["keyframes"]
        lines.append(f"| {row['frames']} | {row['median_ms']:.0f} | {row['median_cpu_ms']:.0f} | {row['rss_mib']:.0f} | "
                     f"{row['gaussians']} | {keyframes} | {row['checkpoint_files']} |")
    return lines


def rolling_median(values: list[float], window: int) -> list[float]:
    """Median of the finite values among each value and the ``window - 1`` before it (NaN where none is)."""
    out = []
    for end in range(1, len(values) + 1):
        finite = [v for v in values[max(0, end - window):end] if v == v]
        out.append(statistics.median(finite) if finite else float("nan"))
    return out


def plot_curves(probe: FrameProbe, covered: int, path: Path, title: str) -> Path:
    """PNG at ``path``: three panels over the frame index, (a) wall time per frame in ms with its rolling median of
    ``ROLLING_MEDIAN_FRAMES`` frames, (b) keyframes in the map, (c) RSS in MiB; a dashed line at frame ``covered``
    (the room covered) in each. Returns ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    figure = Figure(figsize=PLOT_SIZE_IN, dpi=PLOT_DPI, layout="constrained")
    FigureCanvasAgg(figure)
    time_ax, keyframe_ax, rss_ax = figure.subplots(3, 1, sharex=True)
    frames = probe.frame
    wall_ms = [1000 * t for t in probe.periods()]
    finite = sorted(t for t in wall_ms if t == t)
    top = finite[int(PLOT_TIME_QUANTILE * (len(finite) - 1))] if finite else float("nan")
    above = sum(t > top for t in finite)
    time_ax.plot(frames, wall_ms, ".", ms=2.5, color="#7f7f7f", alpha=0.6,
                 label="per frame" + (f" ({above} above the axis, up to {finite[-1]:.0f} ms)" if above else ""))
    time_ax.plot(frames, rolling_median(wall_ms, ROLLING_MEDIAN_FRAMES), "-", lw=1.4, color="#1f77b4",
                 label=f"rolling median of {ROLLING_MEDIAN_FRAMES} frames")
    if top == top and top > 0:
        time_ax.set_ylim(0, top)
    time_ax.set_ylabel("wall time per frame (ms)")
    if probe.keyframes_before:
        keyframe_ax.plot(frames, keyframes_after(probe), "-", lw=1.4, color="#ff7f0e", drawstyle="steps-post")
    else:
        keyframe_ax.text(0.5, 0.5, "keyframe counts not recorded", ha="center", va="center",
                         transform=keyframe_ax.transAxes)
    keyframe_ax.set_ylabel("keyframes in the map")
    keyframe_ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    rss_ax.plot(frames, probe.rss_mib, "-", lw=1.4, color="#2ca02c")
    rss_ax.set_ylabel("RSS (MiB)")
    rss_ax.set_xlabel("frame")
    for ax in (time_ax, keyframe_ax, rss_ax):
        if covered < len(frames):
            ax.axvline(frames[covered], color="#d62728", ls="--", lw=1.0, label=f"room covered (frame {covered})")
        ax.grid(alpha=0.3)
    time_ax.legend(fontsize=8, loc="upper right")
    figure.suptitle(title, fontsize=9)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=PLOT_DPI)
    return write_bytes_atomic(path, buffer.getvalue())


def plot_line(covered: int) -> str:
    """The line of bench.md that names the plot."""
    return (f"Plot: `{PLOT_NAME}`: wall time per frame (rolling median of {ROLLING_MEDIAN_FRAMES} frames), keyframes "
            f"in the map and RSS against the frame; dashed: the room covered (frame {covered}).")


def read_progress(path: Path) -> FrameProbe:
    """A probe filled from a progress file (``long_run.progress``): the frames recorded so far; the last one's time
    and keyframe decision are not known yet (NaN, and assumed no keyframe)."""
    probe = FrameProbe(Path("."))
    for line in path.read_text(encoding="utf-8").splitlines():
        row = json.loads(line)
        probe.frame.append(row["frame"])
        probe.seconds.append(float("nan") if row["period_before_s"] is None else row["period_before_s"])
        cpu = row.get("cpu_before_s")
        probe.cpu_seconds.append(float("nan") if cpu is None else cpu)
        probe.rss_mib.append(row["rss_mib"])
        probe.gaussians.append(row["gaussians"])
        probe.checkpoint_files.append(row["checkpoint_files"])
        if "keyframes_before" in row:  # absent from files written before it was recorded
            probe.keyframes_before.append(row["keyframes_before"])
    probe.final_gaussians, probe.final_checkpoint_files = probe.gaussians[-1], probe.checkpoint_files[-1]
    if len(probe.keyframes_before) != len(probe.frame):
        probe.keyframes_before = []
    # the last recorded frame's keyframe decision is not known yet: assume none, so its time counts as a frame's
    probe.final_keyframes = probe.keyframes_before[-1] if probe.keyframes_before else 0
    return probe


def summarise_probe(probe: FrameProbe, path: Path, frames: int, laps: int, rows: int, keep: int = 2) -> str:
    """Curves and checks (markdown) of a probe read from the progress file ``path`` (:func:`read_progress`)."""
    done = len(probe.frame)
    lines = [f"{path}: {done} of {frames} frames recorded ({laps} laps); the last frame's time is not known yet", "",
             *row_lines(curve_rows(probe, rows)), ""]
    if done > covered_frame(frames, laps):
        for name, passed, text in checks(probe, covered_frame(frames, laps), keep):
            lines.append(f"- {'PASS' if passed else 'FAIL'}  {name} (so far): {text}")
    else:
        lines.append(f"the room is covered at frame {covered_frame(frames, laps)}: too early for the checks")
    return "\n".join(lines)


def summarise_progress(path: Path, frames: int, laps: int, rows: int, keep: int = 2) -> str:
    """Curves and checks (markdown) of the frames recorded so far in a progress file (``long_run.progress``)."""
    return summarise_probe(read_progress(path), path, frames, laps, rows, keep)


def git_commit() -> str:
    """The checkout's commit (and whether tracked files differ from it); MIPSLAM_COMMIT overrides it, for a
    copy of the tree outside git (e.g. ``git archive`` into a folder, so others' edits cannot change a long run)."""
    if os.environ.get("MIPSLAM_COMMIT"):
        return os.environ["MIPSLAM_COMMIT"]
    try:
        out = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True).stdout.strip()
    except OSError:
        return "unknown"
    if out.returncode != 0:
        return "unknown (not a git checkout)"
    return out.stdout.strip() + (" (with uncommitted changes)" if dirty else "")


def run(options: Options, out_dir: Path) -> ScenarioResult:
    laps = options.laps or default_laps(options.frames)
    covered = covered_frame(options.frames, laps)
    if options.summarise:
        progress = Path(options.summarise)
        probe = read_progress(progress)
        report = "\n".join([summarise_probe(probe, progress, options.frames, laps, options.rows), "",
                            plot_line(covered)])
        files = write_benchmark(out_dir, RECORD_NAME, parameters(options), {"summary_markdown": report,
                                                                            "plot": PLOT_NAME},
                                threads=options.threads, markdown=report)
        plot = plot_curves(probe, covered, out_dir / PLOT_NAME,
                           f"{progress.name}: {len(probe.frame)} of {options.frames} frames recorded ({laps} laps)")
        return ScenarioResult(files, report, plots=(plot,))
    commit = git_commit()  # now: a run can outlive the commit it started from
    work = out_dir / "work" if options.keep else Path(tempfile.mkdtemp(prefix="mipslam_long_run_"))
    try:
        sequence, run_dir = work / "sequence", work / "run"
        started = time.perf_counter()
        data_synth.generate(sequence, layout="replica", trajectory="loop", width=options.width, height=options.height,
                            frames=options.frames, laps=laps, seed=0, supersample=2, overwrite=True)
        generation_s = time.perf_counter() - started
        overrides = [f"dataset.path={sequence}", f"run.threads={options.threads}", *options.config_overrides]
        config = load_config(CONFIGS / "synthetic.yaml", preset=options.preset, overrides=overrides)
        probe = FrameProbe(run_dir / "checkpoints", out_dir / "progress.jsonl" if options.progress else None)
        rss_start = rss_mib()
        started = time.perf_counter()
        summary = run_slam(config, run_dir, evaluate=False, observer=probe)
        run_s = time.perf_counter() - started
        probe.finish(summary.gaussians, summary.keyframes)
        metrics = evaluate_trajectory(read_tum_trajectory(run_dir / "traj_gt.txt"),
                                      read_tum_trajectory(run_dir / "traj_est.txt"), association="index").to_dict()
        results = checks(probe, covered, KEEP_CHECKPOINTS)
        rows = curve_rows(probe, options.rows)
    finally:
        if not options.keep:
            shutil.rmtree(work, ignore_errors=True)
    title = (f"long run: {options.frames} frames ({laps} laps) at {options.width}x{options.height}, preset "
             f"{options.preset}, {options.threads} thread(s), commit {commit}")
    lines = [title, "",
             f"generation {generation_s:.0f} s, run {run_s:.0f} s ({options.frames / run_s:.2f} frames/s), "
             f"{summary.keyframes} keyframes, {summary.gaussians} Gaussians, {summary.flagged} frames flagged, "
             f"ATE RMSE {metrics['ate']['rmse'] * 100:.2f} cm; RSS before the run {rss_start:.0f} MiB", "",
             *row_lines(rows), ""]
    lines += [f"- {'PASS' if passed else 'FAIL'}  {name}: {text}" for name, passed, text in results]
    lines += ["", plot_line(covered)]
    report = "\n".join(lines)
    record = {
        "frames": options.frames, "laps": laps, "width": options.width, "height": options.height,
        "preset": options.preset, "threads": options.threads, "overrides": list(options.config_overrides),
        "commit": commit,
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__},
        "generation_s": generation_s, "run_s": run_s, "keyframes": summary.keyframes,
        "gaussians": summary.gaussians, "flagged": summary.flagged, "ate_rmse_m": metrics["ate"]["rmse"],
        "checks": [{"name": n, "passed": p, "detail": t} for n, p, t in results],
        "curve_rows": rows, "plot": PLOT_NAME,
        "per_frame": {"frame": probe.frame, "seconds": [None if t != t else t for t in probe.periods()],
                      "cpu_seconds": [None if t != t else t for t in probe.cpu_periods()],
                      "rss_mib": probe.rss_mib, "gaussians": probe.gaussians,
                      "checkpoint_files": probe.checkpoint_files,
                      "keyframe": probe.keyframe_flags()},
    }
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), record, threads=options.threads,
                            markdown=report)
    plot = plot_curves(probe, covered, out_dir / PLOT_NAME, title)  # after the record: a failed plot loses no run
    return ScenarioResult(files, report, passed=all(passed for _, passed, _ in results), plots=(plot,))
