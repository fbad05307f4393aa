"""The only frame loop: frame -> tracking -> keyframe decision -> mapping -> loop closure -> record.

A table of contents: :func:`process_frame` is one frame as a list of stage steps, :func:`run_slam` the
run as a list of phases. Each step lives in its stage's module and takes the state and its own stage
(built from its own config section): :func:`~mipslam.tracking.track_frame`,
:func:`~mipslam.keyframes.keyframe_decision` and :func:`~mipslam.keyframes.insert_keyframe`,
:func:`~mipslam.mapping.map_keyframe`, :func:`~mipslam.loop.closer.close_loops`,
:func:`~mipslam.mapping.refine_map`. Run control (set-up, Ctrl-C, progress, checkpoint cadence,
resume) is :mod:`mipslam.run_control`; stage timings and diagnostics go to an
:class:`~mipslam.observer.Observer`. Single process, deterministic for a seed on CPU. With
``loop.enabled: false`` the loop-closure stage is not built and nothing of it runs.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from mipslam.config import Config
from mipslam.datasets import FrameCache, RGBDSequence, make_sequence
from mipslam.frontend import Frontend
from mipslam.io.run_folder import write_json_atomic
from mipslam.keyframes import KeyframeOptions, insert_keyframe, keyframe_decision
from mipslam.local_ba import LocalBAOptions, LocalBundleAdjuster
from mipslam.loop.closer import LoopCloser, LoopOptions, VerificationHook, close_loops
from mipslam.mapping import Mapper, MappingOptions, map_keyframe, refine_after_correction, refine_map
from mipslam.refinement import refine_options
from mipslam.observer import Observer
from mipslam.run_control import FrameLoop, PreparedRun, RunSummary, prepare_run, resolve_device, write_checkpoint
from mipslam.sensor_sync import SensorTiming, predicted_velocity, recorded_velocity, synchronised, tracked_velocity
from mipslam.state import FrameRecord, SLAMState
from mipslam.tracking import Tracker, TrackingOptions, TrackingResult, track_frame
from mipslam.types import Frame

# Keyframes' images kept in memory for mapping and loop verification (MiB; a 320x240 keyframe takes 1.2 MiB); the
# others are read again from the sequence when needed.
KEYFRAME_CACHE_MIB = 256
# The final refinement reads the recorded images at no coarser than this downscale of the camera's resolution:
# Replica room0 (read at 1/4) novel views at 1200x680 (docs/mapping.md)
REFINE_MAX_DOWNSCALE = 2

log = logging.getLogger(__name__)

__all__ = ["run_slam", "process_frame", "Stages", "PipelineHooks", "RunSummary", "resolve_device"]


@dataclass(frozen=True)
class PipelineHooks:
    """Fault injection for tests and benchmarks; a normal run has none. (To observe a run without changing
    it, pass an :class:`~mipslam.observer.Observer` subclass to :func:`run_slam`.)

    after_tracking(frame index, tracking result, state) -> result: replaces a frame's tracking
        result before anything else sees it (e.g. a biased odometer that makes the run drift);
    loop_verification(candidate keyframe, query keyframe, result) -> result: replaces a loop
        verification (e.g. a deliberately wrong loop edge);
    constants: stage constants replaced for an experiment, ``{"loop.min_keyframe_gap": 6}`` (a stage's options
        field: TrackingOptions, MappingOptions, KeyframeOptions, LoopOptions, LocalBAOptions as "local_ba"), never
        config keys.
    """

    after_tracking: Callable[[int, TrackingResult, SLAMState], TrackingResult] | None = None
    loop_verification: VerificationHook | None = None
    constants: Mapping[str, Any] = field(default_factory=dict)

    def options(self, section: str, options: Any) -> Any:
        """``options`` (a stage's options of config section ``section``) with this hook's constants for it."""
        values = {key.split(".", 1)[1]: value for key, value in self.constants.items()
                  if key.split(".", 1)[0] == section}
        return replace(options, **values) if values else options


@dataclass
class Stages:
    """The stages of one run, each built from its own config section (``loop`` is None when disabled), the
    frames they read, the map's frame (``T_wc_first`` [4, 4] float64: the first frame's pose) and what of the
    frames' timing the run undoes (``timing``, :mod:`mipslam.sensor_sync`)."""

    tracker: Tracker
    mapper: Mapper
    keyframes: KeyframeOptions
    frames: FrameCache
    T_wc_first: torch.Tensor
    loop: LoopCloser | None = None
    observer: Observer = field(default_factory=Observer)
    hooks: PipelineHooks = field(default_factory=PipelineHooks)
    frontend: Frontend | None = None
    timing: SensorTiming = SensorTiming()
    local_ba: LocalBundleAdjuster | None = None  # None: off (``local_ba.enabled`` false)

    @classmethod
    def build(cls, config: Config, sequence: RGBDSequence, device: torch.device, hooks: PipelineHooks | None = None,
              observer: Observer | None = None) -> "Stages":
        hooks, observer = hooks or PipelineHooks(), observer or Observer()
        capacity = config.keyframes.window_size + config.keyframes.random_past + 2
        noise = config.dataset.depth_noise_power  # a property of the sensor that tracking and loop verification share
        loop = (LoopCloser(hooks.options("loop", LoopOptions.from_config(config.loop, depth_noise_power=noise)),
                           verification_hook=hooks.loop_verification, observer=observer)
                if config.loop.enabled else None)
        local_ba_options = hooks.options("local_ba", LocalBAOptions.from_config(config.local_ba))
        local_ba = LocalBundleAdjuster(local_ba_options) if local_ba_options.enabled else None
        observer.declare("read", "tracking", "keyframe", "mapping", *(("local_ba",) if local_ba is not None else ()),
                         *(("loop", "pgo") if loop is not None else ()))
        frames = FrameCache(sequence, device, capacity, read_ahead=sequence.random_access,
                            kept_bytes=KEYFRAME_CACHE_MIB * 2**20)
        observer.attach(frames)
        frontend = Frontend(config.frontend) if config.frontend.method != "none" else None
        if frontend is not None:
            frames.on_read_ahead = frontend.detect_ahead
        tracking = hooks.options("tracking", TrackingOptions.from_config(config.tracking, depth_noise_power=noise))
        timing = SensorTiming(tracking.align_depth_time, config.dataset.rolling_shutter_readout_s)
        mapping = hooks.options("mapping", MappingOptions.from_config(config.mapping))
        return cls(Tracker(tracking, config.render), Mapper(mapping, config.render),
                   hooks.options("keyframes", KeyframeOptions.from_config(config.keyframes)), frames, first_pose(sequence), loop, observer, hooks,
                   frontend, timing, local_ba)


# ----------------------------------------------------------------------------- one frame

def process_frame(stages: Stages, state: SLAMState, index: int, timestamp: float) -> FrameRecord:
    """Track, decide, map, close loops and record frame ``index`` (``timestamp`` seconds); returns its record."""
    observe = stages.observer.stage
    with observe("read"):
        frame = stages.frames[index]
    stages.frames.prefetch(index + 1)
    with observe("tracking"):
        tracked = track_frame(stages.tracker, state, frame_for_tracking(stages, state, frame), stages.frames,
                              stages.T_wc_first, stages.frontend, at_start=frame_at_start(stages, state, frame))
        if stages.hooks.after_tracking is not None:
            tracked = stages.hooks.after_tracking(index, tracked, state)
        frame = frame_after_tracking(stages, state, frame, tracked)
    with observe("keyframe"):
        is_keyframe = tracked.ok and keyframe_decision(stages.keyframes, state, stages.frames, frame,
                                                       tracked.T_wc, tracked.map_coverage).is_keyframe
    record = state.append_frame(index, timestamp, tracked, is_keyframe)
    if stages.timing.moves_colour_only(frame):
        stages.frames.adjust_when_read(index)  # the colour rows, moved by the record's motion when read again
    if is_keyframe:
        with observe("mapping"):
            window = insert_keyframe(stages.keyframes, state, stages.frames, record)
            if stages.local_ba is not None:
                with observe("local_ba"):
                    stages.local_ba.adjust_window(state, stages.frames)
            map_keyframe(stages.mapper, state, stages.frames, record, window)
        if stages.loop is not None:
            with observe("loop"):
                close_loops(stages.loop, state, stages.frames, stages.mapper.render_config,
                            partial(refine_after_correction, stages.mapper, state, stages.frames))
    return state.end_frame(tracked, stages.tracker.config.running_loss_momentum)


def frame_for_tracking(stages: Stages, state: SLAMState, frame: Frame) -> Frame:
    """``frame`` with its depth at the colour instant by the motion model, for tracking's start
    (:mod:`mipslam.sensor_sync`). Its colour rows wait for the start's own motion (:func:`frame_at_start`): the
    features and the start's judge do not need them moved, and each move costs a resampling of the image."""
    timing = replace(stages.timing, readout_s=0.0)
    if not timing.moves(frame):
        return frame
    return synchronised(frame, predicted_velocity(state, frame), timing)


def frame_at_start(stages: Stages, state: SLAMState, frame: Frame) -> Callable[[torch.Tensor], Frame] | None:
    """For tracking's refinement: the chosen start pose T_wc [4, 4] -> ``frame`` at its colour instant by the
    motion from the previous frame to that pose, a measurement of this frame's own motion where the motion model
    repeats the last one's (on a camera that shakes back and forth the two differ most). None: nothing moves."""
    if not stages.timing.moves(frame):
        return None
    return lambda T_wc_start: frame_at_pose(stages, state, frame, T_wc_start)


def frame_at_pose(stages: Stages, state: SLAMState, frame: Frame, T_wc: torch.Tensor, tracked: bool = True) -> Frame:
    """``frame`` at its colour instant by the motion from the newest recorded frame to ``T_wc`` [4, 4] (the frame
    unmoved when that motion is not known: no earlier frame, or ``tracked`` False)."""
    previous = state.frames[-1] if state.frames else None
    return synchronised(frame, tracked_velocity(previous, frame, T_wc, tracked), stages.timing)


def frame_after_tracking(stages: Stages, state: SLAMState, frame: Frame, tracked: TrackingResult) -> Frame:
    """``frame`` at its colour instant by its tracked motion, cached for the later stages. Where only the colour
    rows move (no depth offset to undo), the frame is returned as it is and the cache moves them when a later
    stage reads it (``FrameCache.adjust``: the same motion, from the frame's record): the keyframe decision reads
    the depth alone, and most frames are never read again (:func:`process_frame` asks for it once the frame's
    record, which the cache's adjustment reads, exists)."""
    if not stages.timing.moves(frame) or stages.timing.moves_colour_only(frame):
        return frame
    moved = frame_at_pose(stages, state, frame, tracked.T_wc, tracked.ok)
    if moved is not frame:
        stages.frames.put(moved)
    return moved


# ----------------------------------------------------------------------------- the run

def final_refinement_images(config: Config, sequence: RGBDSequence) -> RGBDSequence | None:
    """The images the final refinement trains on: the recorded ones, read at no coarser than
    1/``REFINE_MAX_DOWNSCALE`` of the camera's resolution (a map refined at a quarter of it stays blurred at
    the camera's own; Replica room0 reads at 1/4); None for a stream that cannot be read again (a live camera:
    the refinement then trains on the frames the run kept)."""
    if not sequence.random_access:
        return None
    if config.dataset.downscale <= REFINE_MAX_DOWNSCALE:
        return sequence
    return make_sequence(replace(config.dataset, downscale=REFINE_MAX_DOWNSCALE))


def run_slam(config: Config, run_dir: str | Path, *, resume: bool = False, evaluate: bool = True,
             hooks: PipelineHooks | None = None, observer: Observer | None = None) -> RunSummary:
    """Run SLAM on the configured sequence into ``run_dir`` (resuming from its last good checkpoint).

    ``hooks``: fault injection for tests and benchmarks (:class:`PipelineHooks`); ``observer``: stage
    timings, diagnostics and events (default: an :class:`~mipslam.observer.Observer` with
    ``run.diagnostics``). Set-up is not timed; the frames are, from the first one on.
    """
    run = prepare_run(config, run_dir, resume=resume, observer=observer)
    state, observer = run.state, run.observer
    stages = Stages.build(config, run.sequence, run.device, hooks, observer)
    if stages.timing.active:  # old keyframes read again get the images their tracking gave them
        stages.frames.adjust = lambda frame: synchronised(frame, recorded_velocity(state, frame), stages.timing)
    started, start_frame = time.perf_counter(), state.next_frame
    try:
        with FrameLoop(run, config) as loop:
            for index, timestamp in loop:
                loop.frame_done(process_frame(stages, state, index, timestamp))
    finally:
        stages.frames.close()
    write_checkpoint(run.folder, state, config, observer)
    # The refinement shapes this session's outputs, not the checkpoint: a run resumed to go further starts from
    # the state the frames left (as an uninterrupted run would), and resuming a finished run repeats it exactly.
    if config.refine.passes and len(state.gaussian_map):
        with observer.stage("refine"):
            refine_map(stages.mapper, state, stages.frames, refine_options(config), config.refine.passes,
                       final_refinement_images(config, stages.frames.sequence))
    metrics = _write_outputs(run, config, evaluate)
    return RunSummary(run.folder.root, state.next_frame, len(state.keyframe_frames),
                      sum(not f.tracked for f in state.frames), len(state.gaussian_map),
                      time.perf_counter() - started if state.next_frame > start_frame else 0.0, metrics,
                      new_frames=state.next_frame - start_frame)


def first_pose(sequence: RGBDSequence) -> torch.Tensor:
    """The map's frame: the first frame's ground-truth pose where known (so the estimate and the ground
    truth share a frame before alignment), else the identity.  -> [4, 4] float64 camera-to-world"""
    gt = sequence.gt_T_wc
    if gt is not None and bool(sequence.gt_valid[0]):
        return gt[0].to(torch.float64).clone()
    return torch.eye(4, dtype=torch.float64)


def _write_outputs(run: PreparedRun, config: Config, evaluate: bool) -> dict | None:
    from mipslam.outputs import write_run_outputs

    with run.observer.stage("outputs", timed=False):
        write_run_outputs(run.folder, run.state, run.sequence, config, run.observer.timing_summary())
    if not (evaluate and config.run.evaluate_at_end):
        return None
    if not run.folder.traj_gt.is_file():  # a camera, a recording, a TUM folder without groundtruth.txt
        log.info("no ground truth for this sequence: the run is not evaluated")
        return None
    from mipslam.evaluation.run_eval import evaluate_run

    metrics = evaluate_run(run.folder.root)
    write_json_atomic(run.folder.metrics, metrics)
    return metrics
