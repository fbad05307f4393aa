"""The only frame loop: frame -> tracking -> keyframe decision -> mapping -> loop closure -> record -> checkpoint.

:func:`run_slam` builds the stages (each from its own config section), restores or creates the
:class:`~mipslam.state.SLAMState`, runs :func:`process_frame` on every frame, and writes the run
folder (DESIGN.md "Outputs of a run"). Single process, deterministic for a seed on CPU; a
checkpoint every ``run.checkpoint_every`` frames, at the end, and on Ctrl-C. With
``loop.enabled: false`` the loop-closure stage is not built and nothing of it runs.
"""
from __future__ import annotations

import logging
import math
import signal
import time
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import torch
from tqdm import tqdm

from mipslam.checkpoint import load_latest_checkpoint, save_checkpoint
from mipslam.heap import release_free_heap, set_mmap_threshold
from mipslam.config import Config, config_to_dict, config_to_yaml
from mipslam.datasets import RGBDSequence, make_sequence
from mipslam.errors import CheckpointError, ConfigError, DatasetError, MipslamError
from mipslam.evaluation.image_metrics import psnr
from mipslam.frontend import Frontend
from mipslam.geometry import se3_inverse
from mipslam.io.run_folder import RunFolder, write_json_atomic, write_text_atomic
from mipslam.keyframes import covisibility, decide_keyframe, select_random_past, update_window_from_config
from mipslam.losses.photometric import apply_affine_exposure
from mipslam.loop.closer import KeyframeView, LoopCloser, LoopStep, VerificationHook, path_motion, tracking_quality
from mipslam.loop.registration import RegistrationOptions, register_rgbd_odometry
from mipslam.mapping import Mapper, MappingResult, MappingView
from mipslam.rendering import render_view
from mipslam.state import FrameRecord, SLAMState, update_running_loss
from mipslam.tracking import Tracker, TrackingResult, constant_velocity_prediction, initial_result
from mipslam.types import Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunSummary:
    run_dir: Path
    frames: int
    keyframes: int
    flagged: int
    gaussians: int
    seconds: float
    metrics: dict | None

    def describe(self) -> str:
        fps = self.frames / self.seconds if self.seconds > 0 else math.nan
        text = (f"run folder {self.run_dir}: {self.frames} frames ({fps:.2f} frames/s this session), "
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


class FrameCache:
    """The last few frames read from the sequence (mapping revisits keyframes), moved to ``device``."""

    def __init__(self, sequence: RGBDSequence, device: torch.device, capacity: int):
        self.sequence, self.device, self.capacity = sequence, device, max(1, capacity)
        self._frames: OrderedDict[int, Frame] = OrderedDict()

    def __getitem__(self, index: int) -> Frame:
        if index in self._frames:
            self._frames.move_to_end(index)
            return self._frames[index]
        frame = self.sequence[index]
        frame = replace(frame, color=frame.color.to(self.device), depth=frame.depth.to(self.device))
        self._frames[index] = frame
        while len(self._frames) > self.capacity:
            self._frames.popitem(last=False)
        return frame


@dataclass(frozen=True)
class PipelineHooks:
    """Fault injection for tests and benchmarks; a normal run has none.

    after_tracking(frame index, tracking result, state) -> result: replaces a frame's tracking
        result before anything else sees it (e.g. a biased odometer that makes the run drift);
    loop_verification(candidate keyframe, query keyframe, result) -> result: replaces a loop
        verification (e.g. a deliberately wrong loop edge).
    """

    after_tracking: Callable[[int, TrackingResult, SLAMState], TrackingResult] | None = None
    loop_verification: VerificationHook | None = None


@dataclass
class Stages:
    """The stages of one run, each built from its own config section (``loop`` is None when disabled)."""

    config: Config
    tracker: Tracker
    mapper: Mapper
    frames: FrameCache
    loop: LoopCloser | None = None
    hooks: PipelineHooks = field(default_factory=PipelineHooks)
    frontend: Frontend | None = None

    @classmethod
    def build(cls, config: Config, sequence: RGBDSequence, device: torch.device,
              hooks: PipelineHooks | None = None) -> "Stages":
        hooks = hooks or PipelineHooks()
        capacity = config.keyframes.window_size + config.keyframes.random_past + 2
        loop = LoopCloser(config.loop, verification_hook=hooks.loop_verification) if config.loop.enabled else None
        return cls(config, Tracker(config.tracking, config.render), Mapper(config.mapping, config.render),
                   FrameCache(sequence, device, capacity), loop, hooks, Frontend(config.frontend))


@contextmanager
def _timed(state: SLAMState, stage: str):
    start = time.perf_counter()
    yield
    state.add_timing(stage, time.perf_counter() - start)


# ----------------------------------------------------------------------------- one frame

def process_frame(stages: Stages, state: SLAMState, index: int, timestamp: float, T_wc_first: torch.Tensor) -> FrameRecord:
    """Track, decide, map, close loops and record one frame; returns its record (also appended to ``state``)."""
    frame = stages.frames[index]
    with _timed(state, "tracking"):
        tracked = track(stages, state, frame, T_wc_first)
        if stages.hooks.after_tracking is not None:
            tracked = stages.hooks.after_tracking(index, tracked, state)
    with _timed(state, "keyframe"):
        decision = decide_keyframe(stages.config.keyframes, frame.depth, tracked.T_wc, frame.intrinsics.matrix(),
                                   *_last_keyframe(stages, state)) if tracked.ok else None
    is_keyframe = bool(decision is not None and decision.is_keyframe)
    record = FrameRecord(index, timestamp, tracked.T_wc, tracked.exposure, tracked.status, tracked.loss,
                         tracked.iterations, len(state.keyframe_frames) if is_keyframe else -1,
                         state.last_keyframe_id() if state.last_keyframe_id() is not None else -1,
                         T_wc_tracked=tracked.T_wc)
    state.frames.append(record)
    with _timed(state, "mapping"):
        if is_keyframe:
            map_keyframe(stages, state, record)
    if stages.loop is not None:
        close_loops(stages, state, is_keyframe)
    if tracked.status == "ok":
        state.running_loss = update_running_loss(state.running_loss, tracked.loss)
    state.gaussian_counts.append(len(state.gaussian_map))
    return state.frames[-1]


def track(stages: Stages, state: SLAMState, frame: Frame, T_wc_first: torch.Tensor) -> TrackingResult:
    """Tracking against the frozen map; the first frame (or any frame while the map is empty) defines the pose."""
    previous = state.frames[-2:]
    if not previous:
        return initial_result(T_wc_first)
    prediction = constant_velocity_prediction(previous[-1].T_wc, previous[-1].T_wc_tracked,
                                              previous[-2].T_wc_tracked if len(previous) == 2 else None)
    start = frontend_start(stages, state, frame, prediction)
    if len(state.gaussian_map) == 0:
        return initial_result(start.T_wc)
    detached = state.gaussian_map.activated().detached()
    T_wc_start = start.T_wc
    if start.source == "features":  # the render loss judges between the motion model's pose and the features'
        T_wc_start = (prediction, start.T_wc)[stages.tracker.best_start(detached, frame, [prediction, start.T_wc])]
    result = stages.tracker.track(detached, frame, T_wc_start, state.running_loss)
    result = relocalise_keyframes(stages, state, frame, detached, result)
    result = relocalise(stages, state, frame, detached, result)
    return replace(result, T_wc=nearest_rigid(result.T_wc))


def frontend_start(stages: Stages, state: SLAMState, frame: Frame, prediction: torch.Tensor):
    """Tracking's start: the feature front-end against the newest tracked frame, or the motion model."""
    reference = next((f for f in reversed(state.frames) if f.tracked), None)
    if stages.frontend is None or reference is None:
        return Frontend.motion_model(prediction)
    return stages.frontend.start(frame, stages.frames[reference.index], reference.T_wc, prediction)


def relocalise_keyframes(stages: Stages, state: SLAMState, frame: Frame, gaussians,
                         result: TrackingResult) -> TrackingResult:
    """A frame whose tracking failed is matched to the newest keyframes (features + PnP) and tracked again from
    the best match; it stays failed (not mapped) when no keyframe agrees or the retry fails too."""
    if result.ok or stages.frontend is None or not state.keyframe_frames:
        return result
    newest = [state.frames[p] for p in reversed(state.keyframe_frames)][: stages.config.frontend.relocalise_keyframes]
    start = stages.frontend.relocalise(frame, [(stages.frames[r.index], r.T_wc) for r in newest])
    if start is None:
        return result
    retry = stages.tracker.track(gaussians, frame, start.T_wc, state.running_loss)
    if retry.ok:
        log.info("frame %d: relocalised against frame %d (%d feature inliers; tracking had failed: %s)",
                 frame.index, start.reference_index, start.inliers, result.status)
        return retry
    return result


# Dense RGB-D odometry (Open3D's coarse-to-fine hybrid term, as loop verification uses) that
# relocalises a frame against the previous one; the bounds accept up to a 1 m / 45 deg jump.
_RELOCALISE_REGISTRATION = RegistrationOptions(method="rgbd_odometry", pixel_stride=1, min_points=100,
                                               max_correction_m=1.0, max_correction_deg=45.0)


def relocalise(stages: Stages, state: SLAMState, frame: Frame, gaussians, result: TrackingResult) -> TrackingResult:
    """Re-track a frame from a pose found by RGB-D alignment to the previous frame; returns the better result.

    Runs when the tracking loss stays above ``tracking.relocalise_loss_ratio`` times its running level
    (the camera jumped, was bumped, or frames were dropped: the motion model started tracking far from
    the truth and its small steps could not get there); the lower loss wins. Ratio 0 turns it off.
    """
    running = state.running_loss
    ratio = stages.config.tracking.relocalise_loss_ratio
    if (ratio <= 0 or running is None or result.status not in ("ok", "loss_jump") or not state.frames
            or result.loss <= ratio * running or not state.frames[-1].tracked):
        return result
    previous = state.frames[-1]
    before = stages.frames[previous.index]
    T_wc_prev = previous.T_wc.to(torch.float64)
    try:
        aligned = register_rgbd_odometry(before.color, before.depth, frame.color, frame.depth, frame.intrinsics,
                                         se3_inverse(T_wc_prev) @ result.T_wc.to(torch.float64),
                                         _RELOCALISE_REGISTRATION)
    except MipslamError as exc:  # Open3D unavailable: keep tracking's result
        log.debug("relocalisation skipped: %s", exc)
        return result
    if not aligned.accepted:
        return result
    retry = stages.tracker.track(gaussians, frame, T_wc_prev @ aligned.T_ij, running)
    if retry.ok and (not result.ok or retry.loss < result.loss):
        log.info("frame %d: relocalised (tracking loss %.4f, %.1fx its running level; %.4f after a %.2f m, %.1f deg "
                 "RGB-D alignment to frame %d)", frame.index, result.loss, result.loss / running, retry.loss,
                 aligned.correction_m, aligned.correction_deg, previous.index)
        return retry
    return result


def nearest_rigid(T_wc: torch.Tensor) -> torch.Tensor:
    """The rigid transform nearest to ``T_wc`` (rotation block projected onto SO(3) by SVD), float64.

    T_wc [4, 4] -> [4, 4]. Tracking and mapping compose poses in the map's float32; their 1e-7
    departures from orthonormality would otherwise grow through the constant-velocity prediction
    ``T_prev T_prev2^-1 T_prev`` (which inverts by transposition) by a factor ~2.4 per frame.
    """
    T = T_wc.to(torch.float64).clone()
    U, _, Vh = torch.linalg.svd(T[:3, :3])
    d = torch.sign(torch.linalg.det(U @ Vh))
    T[:3, :3] = U @ torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d])) @ Vh
    T[3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    return T


def _last_keyframe(stages: Stages, state: SLAMState):
    kf = state.last_keyframe_id()
    if kf is None:
        return None, None, None
    record = state.keyframe_record(kf)
    keyframe = stages.frames[record.index]
    return keyframe.depth, record.T_wc, keyframe.intrinsics.matrix()


def map_keyframe(stages: Stages, state: SLAMState, record: FrameRecord) -> MappingResult:
    """Register the new keyframe, update the window and optimise the map over it."""
    cfg = stages.config
    new_id = record.keyframe_id
    state.keyframe_frames.append(len(state.frames) - 1)
    frame = stages.frames[record.index]
    overlaps = {}
    for kf in state.window:
        other = state.keyframe_record(kf)
        overlaps[kf] = covisibility(frame.depth, record.T_wc, frame.intrinsics.matrix(), stages.frames[other.index].depth,
                                    other.T_wc)
    state.window = list(update_window_from_config(state.window, new_id, overlaps, cfg.keyframes).window)
    past = select_random_past(range(len(state.keyframe_frames)), state.window, cfg.keyframes.random_past, state.generator)
    views = [_mapping_view(stages, state, kf) for kf in (*state.window, *past)]
    iterations = cfg.mapping.first_frame_iterations if new_id == 0 else cfg.mapping.iterations
    result = stages.mapper.map_keyframe(state.gaussian_map, state.optimizer, views, iterations=iterations,
                                        generator=state.generator, frame_index=record.index)
    for keyframe_id, T_wc in result.refined_T_wc:
        state.set_keyframe_pose(keyframe_id, nearest_rigid(T_wc))
    return result


def _mapping_view(stages: Stages, state: SLAMState, keyframe_id: int) -> MappingView:
    record = state.keyframe_record(keyframe_id)
    frame = stages.frames[record.index]
    return MappingView(keyframe_id, frame.color, frame.depth, record.T_wc, record.exposure.to(frame.color.device),
                       frame.intrinsics, optimize_pose=keyframe_id != 0)


# ----------------------------------------------------------------------------- loop closure

def close_loops(stages: Stages, state: SLAMState, is_keyframe: bool) -> LoopStep | None:
    """The loop-closure stage on a new keyframe (:class:`~mipslam.loop.closer.LoopCloser`); an applied
    correction moves the keyframes, the other frames and the map. Times "loop" and "pgo" on every frame."""
    start = time.perf_counter()
    step = None
    if is_keyframe:
        keyframe_id = state.last_keyframe_id()
        record = state.keyframe_record(keyframe_id)
        since = state.keyframe_frames[keyframe_id - 1] if keyframe_id > 0 else len(state.frames) - 1
        path_m, path_rad = path_motion(torch.stack([f.T_wc for f in state.frames[since:]]))
        odometry = (path_m, path_rad, tracking_quality(record.tracking_loss, state.running_loss))
        step = stages.loop.process_keyframe(state.loop, _keyframe_view(stages, state, keyframe_id),
                                            state.keyframe_poses(), odometry,
                                            lambda other: _keyframe_view(stages, state, other))
        state.loop = step.state
        state.loop_log["candidates"].extend(c.to_dict() for c in step.candidates)
        if step.optimisation is not None:
            entry = step.optimisation.to_dict()
            if step.corrected_T_wc is not None:
                entry.update(correct_map(stages, state, step))
            state.loop_log["optimisations"].append(entry)
    pgo_seconds = step.pgo_seconds if step is not None else 0.0
    state.add_timing("loop", time.perf_counter() - start - pgo_seconds)
    state.add_timing("pgo", pgo_seconds)
    return step


def correct_map(stages: Stages, state: SLAMState, step: LoopStep) -> dict:
    """Apply an accepted pose-graph correction and measure the map before and after it.

    The check renders the map at the loop's keyframes (the query and its loop partners) and
    compares with their images (PSNR, dB): before the correction at the old poses, then at the
    new poses with the map not yet moved (what correcting only the poses would give), after the
    Gaussians moved with their anchor keyframes, and after ``loop.refine_iterations`` mapping steps
    over those keyframes at their corrected (then fixed) poses (:func:`refine_after_correction`).
    """
    check = sorted({step.optimisation.query_keyframe, *(i for i, _ in step.optimisation.new_loop_edges)})
    start = time.perf_counter()
    before = [_keyframe_psnr(stages, state, k, state.keyframe_record(k).T_wc) for k in check]
    poses_only = [_keyframe_psnr(stages, state, k, step.corrected_T_wc[k]) for k in check]
    T_wc_old = state.keyframe_poses()
    moved = state.correct_keyframe_poses(step.corrected_T_wc)
    moved_only = [_keyframe_psnr(stages, state, k, state.keyframe_record(k).T_wc) for k in check]
    if not stages.loop.keeps_correction(before, moved_only):
        state.correct_keyframe_poses(T_wc_old)
        state.loop = stages.loop.without_loop_edges(state.loop, step.optimisation.new_loop_edges)
        log.info("loop correction at keyframe %d undone: the moved map renders keyframes %s at %.2f dB, %.2f dB before",
                 step.optimisation.query_keyframe, check, sum(moved_only) / len(moved_only), sum(before) / len(before))
        return {"gaussians_moved": 0, "psnr_keyframes": check, "psnr_before_db": before,
                "psnr_poses_only_db": poses_only, "psnr_moved_db": moved_only, "refine_iterations": 0,
                "psnr_after_db": before, "applied": False, "undone": True,
                "map_correction_s": time.perf_counter() - start}
    refine_iterations = refine_after_correction(stages, state, check)
    after = [_keyframe_psnr(stages, state, k, state.keyframe_record(k).T_wc) for k in check]
    log.info("loop correction at keyframe %d: moved %d Gaussians; map PSNR at keyframes %s %.2f -> %.2f dB "
             "(%.2f dB with the poses alone corrected, %.2f dB with the map moved before refinement)",
             step.optimisation.query_keyframe, moved, check, sum(before) / len(before), sum(after) / len(after),
             sum(poses_only) / len(poses_only), sum(moved_only) / len(moved_only))
    return {"gaussians_moved": moved, "psnr_keyframes": check, "psnr_before_db": before,
            "psnr_poses_only_db": poses_only, "psnr_moved_db": moved_only, "refine_iterations": refine_iterations,
            "psnr_after_db": after, "map_correction_s": time.perf_counter() - start}


def refine_after_correction(stages: Stages, state: SLAMState, keyframe_ids: list[int]) -> int:
    """Mapping steps over the loop's keyframes at their corrected poses (held fixed); returns the steps.

    Moving Gaussians with their anchors cannot undo what mapping did before the correction: old
    Gaussians re-fitted from drifted views sit where those views put them. ``loop.refine_iterations``
    steps of the mapping loss over the loop's keyframes (no densification, no pose updates, so the
    pose-graph solution stands) reconcile the map with the corrected poses.
    """
    iterations = stages.config.loop.refine_iterations
    if iterations == 0 or len(state.gaussian_map) == 0:
        return 0
    views = [replace(_mapping_view(stages, state, k), optimize_pose=False) for k in keyframe_ids]
    stages.mapper.optimize(state.gaussian_map, state.optimizer, views, iterations, state.generator)
    return iterations


def refine_map(stages: Stages, state: SLAMState) -> int:
    """The final refinement: ``mapping.final_iterations`` mapping steps after the last frame, one keyframe per
    step, every keyframe once per pass in an order drawn from the run's generator; poses fixed. Returns the
    steps taken (fewer if a loss turned non-finite; the map then keeps its last finite state)."""
    iterations, count = stages.config.mapping.final_iterations, len(state.keyframe_frames)
    if iterations == 0 or count == 0:
        return 0
    passes = -(-iterations // count)
    order = torch.cat([torch.randperm(count, generator=state.generator) for _ in range(passes)])[:iterations]
    views = (_mapping_view(stages, state, int(k)) for k in order)  # Mapper.refine never moves a pose
    losses = stages.mapper.refine(state.gaussian_map, state.optimizer, views)
    if losses:
        n = min(count, len(losses))
        log.info("final refinement: %d steps over %d keyframes; mean mapping loss %.4f over the first %d steps, "
                 "%.4f over the last %d", len(losses), count, sum(losses[:n]) / n, n, sum(losses[-n:]) / n, n)
    return len(losses)


def _keyframe_view(stages: Stages, state: SLAMState, keyframe_id: int) -> KeyframeView:
    record = state.keyframe_record(keyframe_id)
    frame = stages.frames[record.index]
    return KeyframeView(keyframe_id, record.index, frame.color, frame.depth, frame.intrinsics)


@torch.no_grad()
def _keyframe_psnr(stages: Stages, state: SLAMState, keyframe_id: int, T_wc: torch.Tensor) -> float:
    """PSNR (dB) of the map rendered at ``T_wc`` [4, 4] against keyframe ``keyframe_id``'s image."""
    record = state.keyframe_record(keyframe_id)
    frame = stages.frames[record.index]
    gmap = state.gaussian_map
    out = render_view(gmap.activated(), se3_inverse(T_wc.to(torch.float64)).to(device=gmap.device, dtype=gmap.dtype),
                      frame.intrinsics, stages.config.render)
    exposure = record.exposure.to(out.color)
    return float(psnr(apply_affine_exposure(out.color, exposure[0], exposure[1]).clamp(0, 1), frame.color))


# ----------------------------------------------------------------------------- the run

@contextmanager
def _ctrl_c_after_the_frame():
    """While the frame loop runs, a first Ctrl-C (SIGINT) only asks to stop: the current frame is
    completed, so the checkpoint written then holds a consistent state (a frame interrupted inside
    mapping would leave keyframe, window, map and loop-closure state out of step, and such a
    checkpoint cannot be resumed). A second Ctrl-C interrupts at once. Yields a list that becomes
    non-empty when a stop was asked for. Where handlers cannot be set (not the main thread), Ctrl-C
    keeps its default behaviour."""
    requested: list[bool] = []

    def ask_to_stop(signum, frame):
        if requested:
            raise KeyboardInterrupt
        requested.append(True)
        log.warning("Ctrl-C: stopping after the current frame (press Ctrl-C again to stop at once)")

    try:
        previous = signal.signal(signal.SIGINT, ask_to_stop)
    except ValueError:  # not the main thread
        yield requested
        return
    try:
        yield requested
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)


class _ProgressLog:
    """A log line every ``PROGRESS_LOG_S`` seconds when the progress bar is off (stderr not a terminal:
    CI, nohup, a batch queue), so a long run still says how far it is."""

    PROGRESS_LOG_S = 30.0

    def __init__(self, total: int, start_frame: int):
        self.total, self.start_frame = total, start_frame
        self.started = self.last = time.perf_counter()

    def frame_done(self, state: SLAMState, record: FrameRecord, bar_disabled: bool) -> None:
        now = time.perf_counter()
        if not bar_disabled or (now - self.last < self.PROGRESS_LOG_S and state.next_frame < self.total):
            return
        self.last = now
        rate = (state.next_frame - self.start_frame) / max(now - self.started, 1e-9)
        log.info("frame %d/%d, %.2f frames/s, %d keyframes, %d Gaussians, tracking loss %.4f", state.next_frame,
                 self.total, rate, len(state.keyframe_frames), len(state.gaussian_map), record.tracking_loss)


def run_slam(config: Config, run_dir: str | Path, *, resume: bool = False, evaluate: bool = True,
             hooks: PipelineHooks | None = None) -> RunSummary:
    """Run SLAM on the configured sequence into ``run_dir`` (resuming from its last good checkpoint).

    ``hooks``: fault injection for tests and benchmarks (:class:`PipelineHooks`); None in normal runs.
    """
    if resume and not Path(run_dir).is_dir():
        raise CheckpointError(f"{run_dir}: no such run folder to resume; check the path, or start a new run with --out")
    folder = RunFolder(run_dir).create()
    folder.remove_stale_temporaries()
    sequence = make_sequence(config.dataset)
    device = resolve_device(config.run.device)
    if config.run.threads:
        torch.set_num_threads(config.run.threads)
    if config.run.mmap_threshold_kib:
        set_mmap_threshold(config.run.mmap_threshold_kib * 1024)
    state = _restore(folder, config, device) if resume else SLAMState.initial(config.mapping, config.run.seed, device)
    write_text_atomic(folder.config_yaml, config_to_yaml(config))
    stages = Stages.build(config, sequence, device, hooks)
    T_wc_first = _first_pose(sequence)
    started, start_frame = time.perf_counter(), state.next_frame
    bar = tqdm(range(state.next_frame, len(sequence)), desc="mipslam", unit="frame", initial=state.next_frame,
               total=len(sequence), dynamic_ncols=True, disable=None)
    frame_complete = True  # False while process_frame runs: the state is then half-updated
    progress = _ProgressLog(len(sequence), start_frame)
    try:
        with _ctrl_c_after_the_frame() as stop_requested:
            for index in bar:
                frame_complete = False
                record = process_frame(stages, state, index, float(sequence.timestamps[index]), T_wc_first)
                frame_complete = True
                if not record.tracked:
                    log.warning("frame %d: tracking failed (%s); kept the motion-model pose", index, record.status)
                if config.run.checkpoint_every and state.next_frame % config.run.checkpoint_every == 0:
                    _checkpoint(folder, state, config)
                if config.run.release_memory_every and state.next_frame % config.run.release_memory_every == 0:
                    release_free_heap()  # fragmentation, not live data, would otherwise grow RSS
                bar.set_postfix(gaussians=len(state.gaussian_map), loss=f"{record.tracking_loss:.4f}", refresh=False)
                progress.frame_done(state, record, bar.disable)
                if stop_requested:
                    raise KeyboardInterrupt
    except KeyboardInterrupt:
        if frame_complete:
            _checkpoint(folder, state, config)
            log.warning("interrupted: state saved after frame %d; continue with --resume %s", state.next_frame - 1,
                        folder.root)
        else:  # a second Ctrl-C inside a frame: its half-done state must not become a checkpoint
            log.warning("interrupted inside frame %d: not saved; --resume %s continues from the last checkpoint",
                        state.next_frame - 1, folder.root)
        raise
    except DatasetError:
        if frame_complete or state.next_frame == index:  # the frame could not be read: nothing of it is in the state
            _checkpoint(folder, state, config)
            log.warning("state saved after frame %d; fix the file and continue with --resume %s", state.next_frame - 1,
                        folder.root)
        raise
    finally:
        bar.close()
    _checkpoint(folder, state, config)
    # The refinement shapes this session's outputs, not the checkpoint: a run resumed to go further starts from
    # the state the frames left (as an uninterrupted run would), and resuming a finished run repeats it exactly.
    if config.mapping.final_iterations and len(state.gaussian_map):
        start = time.perf_counter()
        refine_map(stages, state)
        state.add_timing_to_last_frame("refine", time.perf_counter() - start)
    from mipslam.outputs import write_run_outputs

    write_run_outputs(folder, state, sequence, config)
    metrics = None
    if evaluate and config.run.evaluate_at_end:
        from mipslam.evaluation.run_eval import evaluate_run

        metrics = evaluate_run(folder.root)
        write_json_atomic(folder.metrics, metrics)
    return RunSummary(folder.root, state.next_frame, len(state.keyframe_frames),
                      sum(not f.tracked for f in state.frames), len(state.gaussian_map),
                      time.perf_counter() - started if state.next_frame > start_frame else 0.0, metrics)


def _first_pose(sequence: RGBDSequence) -> torch.Tensor:
    """The map's frame: the first frame's ground-truth pose where known (so the estimate and the ground
    truth share a frame before alignment), else the identity."""
    gt = sequence.gt_T_wc
    if gt is not None and bool(sequence.gt_valid[0]):
        return gt[0].to(torch.float64).clone()
    return torch.eye(4, dtype=torch.float64)


def _checkpoint(folder: RunFolder, state: SLAMState, config: Config) -> Path:
    tensors, metadata = state.to_checkpoint()
    return save_checkpoint(folder.checkpoints, tensors, metadata, config=config_to_dict(config),
                           keep=config.run.keep_checkpoints)


def _restore(folder: RunFolder, config: Config, device: torch.device) -> SLAMState:
    if not folder.checkpoints.is_dir():
        raise CheckpointError(f"{folder.root}: nothing to resume (no checkpoints/ folder); start a run without --resume")
    checkpoint = load_latest_checkpoint(folder.checkpoints, current_config=config_to_dict(config))
    state = SLAMState.from_checkpoint(checkpoint.tensors, checkpoint.metadata, config.mapping, device)
    log.info("resuming %s from %s (frame %d)", folder.root, checkpoint.path.name, state.next_frame)
    return state
