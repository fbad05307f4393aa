"""Benchmark: kill -9 a running ``mipslam run`` at random moments, ``--resume`` it, compare with an
uninterrupted run (docs/robustness.md, "Interrupted runs").

Set-up: a tiny data_synth loop sequence (40x30, replica layout, 10 frames by default) and the
tiny-run settings of tests/test_pipeline.py with ``run.checkpoint_every=2``. One uninterrupted
reference run, then per trial:

1. start ``mipslam run CONFIG --out RUN ...`` as a child process;
2. SIGKILL it at a seeded random moment. Trials cycle through four strategies so that kills land
   in every part of the run: ``time`` (once a random frame has started, a uniform delay of up to
   the reference's median frame time), ``tracking``, ``mapping`` and ``checkpoint`` (wait until the child has
   entered that phase for the n-th time, n drawn at random, then kill at once). ``kill_resume.ctrl_c=N`` adds
   N trials that send SIGINT (Ctrl-C) instead, during ``mapping``, ``tracking`` or ``checkpoint``:
   mipslam must exit with code 130 after saving a checkpoint that resumes to the same result;
3. ``mipslam run CONFIG --resume RUN`` (or, when the child died before its first checkpoint was
   complete and ``--resume`` says so with exit code 2, a fresh ``mipslam run`` into the same folder,
   which is what a user would do);
4. compare ``traj_est.txt``, ``map.ply`` (every Gaussian parameter) and the tracking statuses of
   ``frames.json`` with the reference: identical up to float32 round-off (poses 1e-6, map 1e-5).

Where the child was when it died: the child is ``python -m mipslam.bench.scenarios.kill_resume --child MARKER --
ARGV``, which
runs ``mipslam.cli.main(ARGV)`` (exactly ``mipslam run``) with an observer
(:class:`mipslam.observer.Observer`) that writes each stage's name to the small MARKER file on entry
(a ``pwrite`` of 64 bytes, no fsync: the page cache outlives a killed process). The parent reads the
marker after the kill.

Writes a table and a summary (OUT/bench.md, OUT/bench.json); ``mipslam bench`` exits 1 on any mismatch (or
failed resume), 0 otherwise.

Run: ``mipslam bench --scenario kill_resume --out bench_out/kill_resume --set kill_resume.trials=20``
(``kill_resume.keep=true`` keeps the run folders in OUT/work).
"""
from __future__ import annotations

import functools
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import CONFIGS, REPO, parameters

TINY_SETTINGS = (
    "mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
    "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
    "run.checkpoint_every=2",
)
STRATEGIES = ("time", "tracking", "mapping", "checkpoint")
CTRL_C_STRATEGIES = ("ctrl-c:mapping", "ctrl-c:tracking", "ctrl-c:checkpoint")
POSE_TOLERANCE = 1e-6  # metres / rotation-matrix entries (float64 poses built from float32 maps)
MAP_TOLERANCE = 1e-5  # Gaussian parameters (float32)
MARKER_BYTES = 64


@dataclass(frozen=True)
class Options:
    trials: int = 20  # SIGKILL trials (the strategies cycle)
    ctrl_c: int = 6  # extra trials interrupted with SIGINT (Ctrl-C)
    seed: int = 0
    frames: int = 10
    keep: bool = False  # keep the sequence and the run folders in OUT/work (default: a temporary folder)


SMOKE = dict(trials=1, ctrl_c=0, frames=4)


# ----------------------------------------------------------------------------- the child: mipslam run with phase markers

def _child_main(marker: Path, argv: list[str]) -> int:
    """``mipslam run`` (``mipslam.cli.main(argv)``) with an observer that announces each phase in ``marker``."""
    from mipslam.cli import main
    from mipslam.observer import Observer

    # A process started in the background by a non-interactive shell inherits an ignored SIGINT; a user's
    # Ctrl-C is not ignored, so give the run Python's usual KeyboardInterrupt handler.
    signal.signal(signal.SIGINT, signal.default_int_handler)

    fd = os.open(marker, os.O_RDWR | os.O_CREAT, 0o644)
    counts: dict[str, int] = {}
    frame = [-1]

    def mark(phase: str) -> None:
        counts[phase] = counts.get(phase, 0) + 1
        text = f"{phase} {counts[phase]} {frame[0]}".encode()
        os.pwrite(fd, text.ljust(MARKER_BYTES), 0)

    class PhaseMarker(Observer):
        """Writes "frame", each stage ("tracking", "mapping", "loop", "checkpoint", "outputs", ...) on entry and
        "between" on exit."""

        def on_frame_start(self, index: int) -> None:
            frame[0] = index
            mark("frame")

        def on_stage(self, name: str, entering: bool) -> None:
            mark(name if entering else "between")

    # The CLI calls mipslam.pipeline.run_slam; give that call the observer (its public ``observer`` argument).
    import mipslam.pipeline

    mipslam.pipeline.run_slam = functools.partial(mipslam.pipeline.run_slam, observer=PhaseMarker())
    mark("startup")
    code = main(argv)
    mark("exited")
    return code


def read_marker(marker: Path) -> tuple[str, int, int]:
    """(phase, how many times it was entered, frame index) as the child last wrote it."""
    try:
        fields = marker.read_bytes().decode(errors="replace").split()
    except FileNotFoundError:
        return "not_started", 0, -1
    if len(fields) != 3:
        return "not_started", 0, -1
    return fields[0], int(fields[1]), int(fields[2])


# ----------------------------------------------------------------------------- set-up and comparison

@dataclass(frozen=True)
class Setup:
    sequence: Path
    config: Path
    settings: tuple[str, ...]
    reference: Path
    reference_seconds: float  # the reference child from its start to its exit
    run_seconds: float  # the reference child from the end of its imports (marker "startup") to its exit
    frames: int
    keyframes: int = 0  # of the reference run: how often mapping runs
    frame_seconds: float = 0.0  # median time of one frame of the reference (first frame, with any build, left out)


def mipslam_argv(setup: Setup, *, out: Path | None = None, resume: Path | None = None) -> list[str]:
    argv = ["run", str(setup.config), "--no-eval"]
    argv += ["--out", str(out)] if out is not None else ["--resume", str(resume)]
    for item in (f"dataset.path={setup.sequence}", *setup.settings):
        argv += ["--set", item]
    return argv


def child_command(marker: Path, argv: list[str]) -> list[str]:
    return [sys.executable, "-m", "mipslam.bench.scenarios.kill_resume", "--child", str(marker), "--", *["-q", *argv]]


def child_environment() -> dict[str, str]:
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(name, "1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH", "")]))
    return env


def prepare(workdir: Path, *, frames: int = 10, width: int = 40, height: int = 30,
            reference_in_process: bool = False) -> Setup:
    """Generate the sequence and run the uninterrupted reference (a child process like the trials, or
    with ``reference_in_process`` :func:`mipslam.pipeline.run_slam` here, as the CLI calls it)."""
    import data_synth

    workdir.mkdir(parents=True, exist_ok=True)
    sequence = workdir / "sequence"
    if not (sequence / "synth.json").is_file():
        data_synth.generate(sequence, layout="replica", trajectory="loop", width=width, height=height, frames=frames,
                            seed=0, supersample=2, overwrite=True)
    setup = Setup(sequence, CONFIGS / "synthetic.yaml", TINY_SETTINGS, workdir / "reference", 0.0, 0.0, frames)
    shutil.rmtree(setup.reference, ignore_errors=True)
    if reference_in_process:
        from mipslam.config import load_config
        from mipslam.pipeline import run_slam

        started = time.perf_counter()
        config = load_config(setup.config, overrides=[f"dataset.path={sequence}", *setup.settings])
        run_slam(config, setup.reference, evaluate=False)
        seconds = time.perf_counter() - started
        return Setup(sequence, setup.config, setup.settings, setup.reference, seconds, seconds, frames,
                     _keyframes(setup.reference), seconds / frames)
    marker = workdir / "reference.marker"
    marker.unlink(missing_ok=True)
    started = time.perf_counter()
    child = subprocess.Popen(child_command(marker, mipslam_argv(setup, out=setup.reference)), env=child_environment(),
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    imported = None
    frame_started: dict[int, float] = {}
    while child.poll() is None:
        phase, _, frame = read_marker(marker)
        if imported is None and phase != "not_started":
            imported = time.perf_counter()
        if frame >= 0 and frame not in frame_started:
            frame_started[frame] = time.perf_counter()
        time.sleep(0.01)
    seconds = time.perf_counter() - started
    if child.returncode != 0:
        raise RuntimeError(f"reference run failed (exit {child.returncode}): {child.stderr.read().strip()[-2000:]}")
    run_seconds = seconds - (imported - started) if imported is not None else seconds
    starts = [frame_started[k] for k in sorted(frame_started) if k >= 1]  # frame 0 may include the renderer's build
    steps = sorted(b - a for a, b in zip(starts, starts[1:]))
    frame_seconds = steps[len(steps) // 2] if steps else run_seconds / frames
    return Setup(sequence, setup.config, setup.settings, setup.reference, seconds, run_seconds, frames,
                 _keyframes(setup.reference), frame_seconds)


def _keyframes(run: Path) -> int:
    return sum(f["keyframe_id"] >= 0 for f in json.loads((run / "frames.json").read_text())["frames"])


def compare_runs(reference: Path, run: Path) -> dict[str, float | bool | str]:
    """Largest differences between two finished run folders (poses, every map parameter, statuses)."""
    import numpy as np

    from mipslam.io.ply import read_map_ply
    from mipslam.io.tum import read_tum_trajectory

    ref_traj, traj = read_tum_trajectory(reference / "traj_est.txt"), read_tum_trajectory(run / "traj_est.txt")
    if ref_traj.T_wc.shape != traj.T_wc.shape or not np.array_equal(ref_traj.timestamps, traj.timestamps):
        return {"pose_diff": float("inf"), "map_diff": float("inf"), "same": False,
                "why": f"{len(traj.timestamps)} poses, reference {len(ref_traj.timestamps)}"}
    pose_diff = float(np.abs(ref_traj.T_wc - traj.T_wc).max())
    ref_map, run_map = read_map_ply(reference / "map.ply"), read_map_ply(run / "map.ply")
    if len(ref_map) != len(run_map):
        return {"pose_diff": pose_diff, "map_diff": float("inf"), "same": False,
                "why": f"{len(run_map)} Gaussians, reference {len(ref_map)}"}
    map_diff = 0.0
    for name in ("means", "log_scales", "quats_wxyz", "opacity_logits", "colors_raw"):
        a, b = getattr(ref_map, name), getattr(run_map, name)
        if a.numel():
            map_diff = max(map_diff, float((a - b).detach().abs().max()))
    statuses = [[f["status"] for f in json.loads((folder / "frames.json").read_text())["frames"]]
                for folder in (reference, run)]
    same = pose_diff <= POSE_TOLERANCE and map_diff <= MAP_TOLERANCE and statuses[0] == statuses[1]
    why = "" if same else ("statuses differ" if statuses[0] != statuses[1] else "values differ beyond round-off")
    return {"pose_diff": pose_diff, "map_diff": map_diff, "same": same, "why": why}


# ----------------------------------------------------------------------------- one trial

@dataclass(frozen=True)
class TrialResult:
    trial: int
    strategy: str
    kill_after_s: float
    phase_at_kill: str
    frame_at_kill: int
    finished_before_kill: bool
    checkpoints_after_kill: int
    resumed_from_frame: int  # frames done by the checkpoint resumed from (-1: restarted without one)
    resume_exit_code: int
    pose_diff: float
    map_diff: float
    checkpoints_at_end: int
    ok: bool
    note: str


def _checkpoint_frames(run: Path) -> tuple[int, int]:
    """(number of complete checkpoints, frames done by the newest usable one or -1)."""
    from mipslam.checkpoint import list_checkpoints, load_latest_checkpoint
    from mipslam.errors import CheckpointError

    files = list_checkpoints(run / "checkpoints")
    if not files:
        return 0, -1
    try:
        return len(files), int(load_latest_checkpoint(run / "checkpoints").metadata["next_frame"])
    except CheckpointError:
        return len(files), -1


def resume_in_process(setup: Setup, run_dir: Path) -> tuple[int, str]:
    """``mipslam run --resume`` through :func:`mipslam.pipeline.run_slam` in this process (no second
    interpreter start-up; what the test uses). Returns (exit code as the CLI would give it, message)."""
    from mipslam.config import load_config
    from mipslam.errors import MipslamError
    from mipslam.pipeline import run_slam

    config = load_config(setup.config, overrides=[f"dataset.path={setup.sequence}", *setup.settings])
    try:
        run_slam(config, run_dir, resume=True, evaluate=False)
    except MipslamError as exc:
        return 2, f"error: {exc}"
    return 0, ""


def run_trial(setup: Setup, workdir: Path, trial: int, strategy: str, rng: random.Random,
              *, poll_s: float = 0.0005, timeout_s: float = 600.0, in_process_resume: bool = False,
              occurrence: int | None = None) -> TrialResult:
    """Start the run, kill it (``strategy``), resume it and compare with the reference.

    ``in_process_resume``: resume with :func:`resume_in_process` instead of a second ``mipslam run``
    process (same library call as the CLI; saves an interpreter start-up in tests). ``occurrence``: interrupt
    at this entry into the phase (1 = the first) instead of a random one."""
    run_dir, marker = workdir / f"trial{trial:03d}", workdir / f"trial{trial:03d}.marker"
    shutil.rmtree(run_dir, ignore_errors=True)
    marker.unlink(missing_ok=True)
    env = child_environment()
    # How often each phase occurs in a whole run (tracking: every frame but the first; mapping: keyframes).
    # How often each phase occurs (tracking: every frame but the first; mapping: from the second keyframe
    # on, the first is mapped before any checkpoint exists; checkpoints: every 2 frames).
    interrupt = signal.SIGINT if strategy.startswith("ctrl-c:") else signal.SIGKILL
    phase_wanted = strategy.removeprefix("ctrl-c:")
    first_and_last = {"tracking": (1, max(1, setup.frames - 1)), "mapping": (min(2, setup.keyframes), setup.keyframes),
                      "checkpoint": (1, max(1, setup.frames // 2)), "time": (0, 0)}[phase_wanted]
    target_count = rng.randint(*first_and_last) if occurrence is None else occurrence
    # "time": a random frame, then a random moment within about one frame's time (robust to the machine's load)
    target_frame = rng.randint(0, setup.frames - 1) if phase_wanted == "time" else 0
    delay = rng.uniform(0.0, setup.frame_seconds or setup.run_seconds / setup.frames) if phase_wanted == "time" else 0.0
    started = time.perf_counter()
    imported = None
    child = subprocess.Popen(child_command(marker, mipslam_argv(setup, out=run_dir)), env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        while child.poll() is None and time.perf_counter() - started < timeout_s:
            phase, count, frame_now = read_marker(marker)
            if phase_wanted == "time":
                if imported is None and phase != "not_started" and frame_now >= target_frame:
                    imported = time.perf_counter()  # the target frame has started
                if imported is not None and time.perf_counter() - imported >= delay:
                    break
            elif phase == phase_wanted and count >= target_count:
                break
            time.sleep(poll_s)
        finished = child.poll() is not None
        at_signal = read_marker(marker)
        if not finished:
            child.send_signal(interrupt)
        child.wait(timeout=timeout_s)
        interrupted_code = child.returncode
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    kill_after = time.perf_counter() - started
    # SIGKILL: where the child died; Ctrl-C: where it was when the signal was sent (it then exits on its own)
    phase, _, frame = read_marker(marker) if interrupt == signal.SIGKILL else at_signal
    checkpoints, resumed_from = _checkpoint_frames(run_dir)
    note = ""
    if interrupt == signal.SIGINT and not finished and interrupted_code != 130:
        note = f"Ctrl-C gave exit code {interrupted_code}, expected 130"
    if in_process_resume:
        code, message = resume_in_process(setup, run_dir)
    else:
        resumed = subprocess.run(child_command(marker, mipslam_argv(setup, resume=run_dir)), env=env,
                                 capture_output=True, text=True, timeout=timeout_s)
        code, message = resumed.returncode, resumed.stderr
    if code == 2 and ("no checkpoint" in message or "nothing to resume" in message):
        note = "no complete checkpoint yet: restarted"
        restarted = subprocess.run(child_command(marker, mipslam_argv(setup, out=run_dir)), env=env,
                                   capture_output=True, text=True, timeout=timeout_s)
        code, message = restarted.returncode, restarted.stderr
    if code != 0:
        last = message.strip().splitlines()[-1] if message.strip() else ""
        return TrialResult(trial, strategy, kill_after, phase, frame, finished, checkpoints, resumed_from, code,
                           float("inf"), float("inf"), 0, False, f"resume failed: {last}")
    diff = compare_runs(setup.reference, run_dir)
    at_end, _ = _checkpoint_frames(run_dir)
    bounded = at_end <= 3  # KEEP_CHECKPOINTS=2, plus one when killed between a rename and the pruning
    ok = bool(diff["same"]) and bounded and not note.startswith("Ctrl-C gave")
    note = "; ".join(filter(None, [note, str(diff["why"]), "" if bounded else f"{at_end} checkpoint files"]))
    return TrialResult(trial, strategy, kill_after, phase, frame, finished, checkpoints, resumed_from, code,
                       float(diff["pose_diff"]), float(diff["map_diff"]), at_end, ok, note)


def run_trials(workdir: Path, *, trials: int = 20, seed: int = 0, frames: int = 10, setup: Setup | None = None,
               strategies: tuple[str, ...] = STRATEGIES, ctrl_c_trials: int = 0,
               in_process_resume: bool = False) -> tuple[Setup, list[TrialResult]]:
    """Prepare (unless ``setup`` is given) and run ``trials`` SIGKILL trials (the strategies cycle), then
    ``ctrl_c_trials`` SIGINT trials (cycling through :data:`CTRL_C_STRATEGIES`)."""
    setup = setup or prepare(workdir, frames=frames)
    rng = random.Random(seed)
    plan = [strategies[i % len(strategies)] for i in range(trials)]
    plan += [CTRL_C_STRATEGIES[i % len(CTRL_C_STRATEGIES)] for i in range(ctrl_c_trials)]
    results = [run_trial(setup, workdir, trial, strategy, rng, in_process_resume=in_process_resume)
               for trial, strategy in enumerate(plan)]
    return setup, results


# ----------------------------------------------------------------------------- report

def format_table(setup: Setup, results: list[TrialResult]) -> str:
    lines = [f"reference: {setup.frames} frames, {setup.keyframes} keyframes, {setup.reference_seconds:.1f} s "
             f"uninterrupted ({setup.run_seconds:.1f} s after the imports, median frame {setup.frame_seconds:.2f} s)",
             "", "| trial | strategy | kill s | phase at kill | frame | ckpts | resumed@ | rc | max abs dT | "
             "max abs dmap | end ckpts | result |", "|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in results:
        lines.append(f"| {r.trial} | {r.strategy} | {r.kill_after_s:.2f} | {r.phase_at_kill} | {r.frame_at_kill} | "
                     f"{r.checkpoints_after_kill} | {r.resumed_from_frame} | {r.resume_exit_code} | {r.pose_diff:.2e} | "
                     f"{r.map_diff:.2e} | {r.checkpoints_at_end} | "
                     f"{'ok' if r.ok else 'MISMATCH'}{(' (' + r.note + ')') if r.note else ''} |")
    return "\n".join(lines)


def summary(results: list[TrialResult]) -> dict:
    phases: dict[str, int] = {}
    for r in results:
        phases[r.phase_at_kill] = phases.get(r.phase_at_kill, 0) + 1
    finite = [r for r in results if r.ok]
    kills = [r for r in results if not r.strategy.startswith("ctrl-c")]
    return {
        "trials": len(results),
        "mismatches": sum(not r.ok for r in results),
        "sigkill_trials": len(kills),
        "sigkill_mismatches": sum(not r.ok for r in kills),
        "ctrl_c_trials": len(results) - len(kills),
        "ctrl_c_mismatches": sum(not r.ok for r in results if r.strategy.startswith("ctrl-c")),
        "phases_at_kill": phases,
        "finished_before_kill": sum(r.finished_before_kill for r in results),
        "restarted_without_checkpoint": sum(r.resumed_from_frame < 0 for r in results),
        "max_pose_diff": max((r.pose_diff for r in finite), default=0.0),
        "max_map_diff": max((r.map_diff for r in finite), default=0.0),
    }


def run(options: Options, out_dir: Path) -> ScenarioResult:
    from mipslam.bench.record import write_benchmark

    work = out_dir / "work" if options.keep else Path(tempfile.mkdtemp(prefix="mipslam_kill_resume_"))
    try:
        setup, results = run_trials(work, trials=options.trials, seed=options.seed, frames=options.frames,
                                    ctrl_c_trials=options.ctrl_c)
    finally:
        if not options.keep:
            shutil.rmtree(work, ignore_errors=True)
    totals = summary(results)
    report = format_table(setup, results) + "\n\n" + "\n".join(f"- {k}: {v}" for k, v in totals.items())
    files = write_benchmark(out_dir, RECORD_NAME, {**parameters(options), "settings": list(setup.settings)},
                            {"summary": totals, "trials": [asdict(r) for r in results],
                             "reference_seconds": setup.reference_seconds, "frames": setup.frames},
                            threads=1, markdown=report)
    return ScenarioResult(files, report, passed=totals["mismatches"] == 0)


if __name__ == "__main__":  # the child process of a trial: mipslam run with phase markers
    if len(sys.argv) < 4 or sys.argv[1] != "--child" or sys.argv[3] != "--":
        sys.exit("usage: python -m mipslam.bench.scenarios.kill_resume --child MARKER -- MIPSLAM_ARGS...")
    sys.exit(_child_main(Path(sys.argv[2]), sys.argv[4:]))
