"""Run control around the frame loop: set-up, Ctrl-C, progress, checkpoint and memory cadence, resume.

:func:`prepare_run` opens the run folder, applies the process settings (threads, allocator), restores
the state (resume) or creates it, and loads the renderer before the first frame, so no stage is
charged for it. :class:`FrameLoop` hands out the frames still to process and does what happens
between two frames: the observer's frame record, a checkpoint every ``run.checkpoint_every`` frames,
returning freed heap memory every ``RELEASE_MEMORY_EVERY`` frames, progress, and Ctrl-C; on an
interruption it writes the checkpoint a resume needs. None of it changes a result.
"""
from __future__ import annotations

import logging
import signal
import sys
import time
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import torch
from tqdm import tqdm

from mipslam.checkpoint import load_latest_checkpoint, save_checkpoint
from mipslam.config import Config, config_to_dict, config_to_yaml
from mipslam.datasets import RGBDSequence, StreamEnded, make_sequence
from mipslam.errors import CheckpointError, ConfigError, DatasetError, MipslamError
from mipslam.heap import release_free_heap
from mipslam.io.run_folder import RunFolder, write_text_atomic
from mipslam.observer import Observer
from mipslam.mapping import MappingOptions
from mipslam.state import FrameRecord, SLAMState
from mipslam.tracking import TrackingOptions

log = logging.getLogger(__name__)

KEEP_CHECKPOINTS = 2  # complete checkpoints kept on disk (the newest, and one more should it be damaged)
# Frames between returns of freed heap memory to the OS (glibc malloc_trim): without it fragmentation grows RSS by
# about 3 MiB per 100 frames on long runs (docs/robustness.md).
RELEASE_MEMORY_EVERY = 50

# tqdm's default bar, with the rate always in frames/s (tqdm turns a rate below 1 into s/frame)
_BAR_FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_noinv_fmt}{postfix}]"
# Seconds between progress log lines when there is no progress bar (stderr not a terminal: CI, nohup, a pipe).
PROGRESS_LOG_S = 5.0


@dataclass(frozen=True)
class RunSummary:
    run_dir: Path
    frames: int
    keyframes: int
    flagged: int
    gaussians: int
    seconds: float  # this session's time from its first frame on
    metrics: dict | None
    new_frames: int = 0  # frames this session processed (fewer than ``frames`` after a resume)

    def describe(self) -> str:
        rate = (f"{self.new_frames / self.seconds:.2f} frames/s this session" if self.seconds > 0 and self.new_frames
                else "no new frames this session")
        text = (f"run folder {self.run_dir}: {self.frames} frames ({rate}), "
                f"{self.keyframes} keyframes, {self.gaussians} Gaussians, {self.flagged} frames flagged")
        ate = (self.metrics or {}).get("trajectory", {}).get("ate")
        if ate:
            text += f"; ATE RMSE {ate['rmse'] * 100:.3f} cm"
        return text


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is a config error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("config key 'run.device': cuda requested but torch sees no CUDA device; use auto or cpu")
    return torch.device(name)


@dataclass
class PreparedRun:
    folder: RunFolder
    sequence: RGBDSequence
    device: torch.device
    state: SLAMState
    observer: Observer


def prepare_run(config: Config, run_dir: str | Path, *, resume: bool, observer: Observer | None) -> PreparedRun:
    """Everything before the first frame: run folder, sequence, process settings, state (restored on
    ``resume``), the observer (its timings continued on resume) and the renderer loaded."""
    if resume and not Path(run_dir).is_dir():
        raise CheckpointError(f"{run_dir}: no such run folder to resume; check the path, or start a new run with --out")
    folder = RunFolder(run_dir).create()
    folder.remove_stale_temporaries()
    sequence = make_sequence(config.dataset)
    device = resolve_device(config.run.device)
    if config.run.threads:
        torch.set_num_threads(config.run.threads)
    observer = observer or Observer(diagnostics=config.run.diagnostics)
    if resume:
        state = _restore(folder, config, device, observer)
    else:
        state = SLAMState.initial(MappingOptions.from_config(config.mapping), config.run.seed, device)
    write_text_atomic(folder.config_yaml, config_to_yaml(config))
    warm_up(config, device)
    return PreparedRun(folder, sequence, device, state, observer)


def warm_up(config: Config, device: torch.device) -> None:
    """Load the renderer's compiled CPU backend (built at install; never compiled here) and, where a stage
    registers RGB-D frames with it, Open3D (an import of about a second) before the first frame, so no stage's
    time includes them. A missing Open3D is reported by the stage that needs it."""
    from mipslam.render.cpu import warm_up as warm_up_renderer

    if config.render.backend != "torch" and device.type == "cpu":
        warm_up_renderer()
    if config.loop.enabled or TrackingOptions.dense_start or config.tracking.relocalise_loss_ratio > 0:
        from mipslam.loop.registration import load_open3d

        try:
            load_open3d()
        except MipslamError as exc:
            log.debug("Open3D not loaded at set-up: %s", exc)


def write_checkpoint(folder: RunFolder, state: SLAMState, config: Config, observer: Observer) -> Path:
    """The state, and the observer's timings beside it (a resumed run's timings.json covers every session)."""
    with observer.stage("checkpoint", timed=False):
        tensors, metadata = state.to_checkpoint()
        metadata["timings"] = observer.timing_lists()
        return save_checkpoint(folder.checkpoints, tensors, metadata, config=config_to_dict(config),
                               keep=KEEP_CHECKPOINTS)


def _restore(folder: RunFolder, config: Config, device: torch.device, observer: Observer) -> SLAMState:
    if not folder.checkpoints.is_dir():
        raise CheckpointError(f"{folder.root}: nothing to resume (no checkpoints/ folder); start a run without --resume")
    checkpoint = load_latest_checkpoint(folder.checkpoints, current_config=config_to_dict(config))
    state = SLAMState.from_checkpoint(checkpoint.tensors, checkpoint.metadata, MappingOptions.from_config(config.mapping),
                                      device)
    observer.restore(checkpoint.metadata.get("timings", {}))
    log.info("resuming %s from %s (frame %d)", folder.root, checkpoint.path.name, state.next_frame)
    return state


@contextmanager
def ctrl_c_after_the_frame(unit: str = "frame") -> Iterator[list[bool]]:
    """While the frame loop runs, a first Ctrl-C (SIGINT) only asks to stop: the current frame is
    completed, so the checkpoint written then holds a consistent state (a frame interrupted inside
    mapping would leave keyframe, window, map and loop-closure state out of step, and such a
    checkpoint cannot be resumed). A second Ctrl-C interrupts at once. Yields a list that becomes
    non-empty when a stop was asked for. Where handlers cannot be set (not the main thread), Ctrl-C
    keeps its default behaviour. ``unit``: what is completed, in the message (``mipslam refine``: a step)."""
    requested: list[bool] = []

    def ask_to_stop(signum, frame):
        if requested:
            raise KeyboardInterrupt
        requested.append(True)
        log.warning("Ctrl-C: stopping after the current %s (press Ctrl-C again to stop at once)", unit)

    try:
        previous = signal.signal(signal.SIGINT, ask_to_stop)
    except ValueError:  # not the main thread
        yield requested
        return
    try:
        yield requested
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)


class Progress:
    """On a terminal a tqdm bar (frames/s, keyframes, Gaussians, tracking loss); otherwise (stderr not a
    terminal: CI, nohup, a pipe) a log line after the first frame, every ``PROGRESS_LOG_S`` seconds, and
    after the last frame. Rates count this session's frames from the first one, after set-up."""

    def __init__(self, total: int, start_frame: int, *, interval_s: float = PROGRESS_LOG_S):
        self.total, self.start_frame, self.interval_s = total, start_frame, interval_s
        self.bar = tqdm(total=total, initial=start_frame, desc="mipslam", unit="frame", dynamic_ncols=True,
                        disable=None, file=sys.stderr, bar_format=_BAR_FORMAT)
        self.started = self.last = time.perf_counter()

    def frame_done(self, state: SLAMState, record: FrameRecord) -> None:
        if not self.bar.disable:
            self.bar.set_postfix(OrderedDict(keyframes=len(state.keyframe_frames), gaussians=len(state.gaussian_map),
                                             loss=f"{record.tracking_loss:.4f}"), refresh=False)
            self.bar.update(1)
            return
        now = time.perf_counter()
        done = state.next_frame - self.start_frame
        if done > 1 and now - self.last < self.interval_s and state.next_frame < self.total:
            return
        self.last = now
        rate = done / max(now - self.started, 1e-9)
        log.info("frame %d/%d, %.2f frames/s, %d keyframes, %d Gaussians, tracking loss %.4f", state.next_frame,
                 self.total, rate, len(state.keyframe_frames), len(state.gaussian_map), record.tracking_loss)

    def close(self) -> None:
        self.bar.close()


class FrameLoop:
    """The frames still to process, and what happens between two of them (module docstring).

    Use as ``with FrameLoop(...) as loop: for index in loop: ...; loop.frame_done(record)``: the context
    writes the checkpoint an interruption needs (Ctrl-C, a frame that cannot be read) and re-raises.
    """

    def __init__(self, run: PreparedRun, config: Config):
        self.run, self.config = run, config
        self.total = len(run.sequence)
        self.index: int | None = None
        self.frame_complete = True  # False while a frame is processed: the state is then half-updated

    def __iter__(self) -> Iterator[tuple[int, float]]:
        """(index, timestamp in seconds) of every frame still to process. A camera or a recording that ends
        (:class:`~mipslam.datasets.StreamEnded`, raised when its next timestamp is asked for) ends the run
        there, as the end of a sequence does."""
        for index in range(self.run.state.next_frame, self.total):
            try:
                timestamp = float(self.run.sequence.timestamps[index])
            except StreamEnded as exc:
                log.info("%s", exc)
                return
            self.index, self.frame_complete = index, False
            self.run.observer.begin_frame(index)
            yield index, timestamp

    def frame_done(self, record: FrameRecord) -> None:
        """After frame ``record.index``: observer, cadence work, progress; honours a Ctrl-C asked during it."""
        run, cfg = self.run, self.config.run
        state = run.state
        self.frame_complete = True
        run.observer.end_frame(record, state)
        if not record.tracked:
            log.warning("frame %d: tracking failed (%s); kept the motion-model pose", record.index, record.status)
        if cfg.checkpoint_every and state.next_frame % cfg.checkpoint_every == 0:
            write_checkpoint(run.folder, state, self.config, run.observer)
        if state.next_frame % RELEASE_MEMORY_EVERY == 0:
            release_free_heap()  # fragmentation, not live data, would otherwise grow RSS
        self._progress.frame_done(state, record)
        if self._stop_requested:
            raise KeyboardInterrupt

    def __enter__(self) -> "FrameLoop":
        self._progress = Progress(self.total, self.run.state.next_frame)
        self._ctrl_c = ctrl_c_after_the_frame()
        self._stop_requested = self._ctrl_c.__enter__()
        return self

    def __exit__(self, kind, error, traceback) -> bool:
        try:
            self._progress.close()
            self._save_after(kind)
        finally:
            self._ctrl_c.__exit__(kind, error, traceback)
        return False

    def _save_after(self, kind) -> None:
        run = self.run
        state, root = run.state, run.folder.root
        if kind is not None and issubclass(kind, KeyboardInterrupt):
            if self.frame_complete:
                write_checkpoint(run.folder, state, self.config, run.observer)
                log.warning("interrupted: state saved after frame %d; continue with --resume %s",
                            state.next_frame - 1, root)
            else:  # a second Ctrl-C inside a frame: its half-done state must not become a checkpoint
                log.warning("interrupted inside frame %d: not saved; --resume %s continues from the last checkpoint",
                            state.next_frame - 1, root)
        elif kind is not None and issubclass(kind, DatasetError):
            # the frame could not be read: nothing of it is in the state
            if self.frame_complete or state.next_frame == self.index:
                write_checkpoint(run.folder, state, self.config, run.observer)
                log.warning("state saved after frame %d; fix the file and continue with --resume %s",
                            state.next_frame - 1, root)
