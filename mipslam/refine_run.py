"""``mipslam refine RUN_DIR``: keep optimising a finished run's map over all its keyframes, beside the run.

**Start.** The run's final map (``map.ply``, which holds the run's own final refinement), its final poses
(``traj_est.txt``) and its keyframes with their frame indices and exposures (the run's latest checkpoint,
:meth:`SLAMState.from_checkpoint`); a fresh :class:`~mipslam.gaussians.GaussianOptimizer` (``mapping`` learning
rates) and a generator seeded with ``run.seed``. The steps are those of the run's final refinement
(:class:`~mipslam.refinement.KeyframeRefiner` with :func:`~mipslam.refinement.refine_options` of the run's config:
one keyframe per step, every keyframe once per pass; keyframe poses move only with ``refine.lr_poses > 0``).

**Images.** ``resolution="mapping"`` trains on the keyframes as the run read them (its ``dataset`` section);
``"native"`` reads the dataset with ``downscale`` 1 (the camera's own images and intrinsics). Either way the images
are those the camera recorded, as the run's final refinement reads them: what the run moved to one instant for
tracking (a rolling shutter's rows) is a resampled image the evaluation never compares with.

**Budget.** Refinement time (the steps' own wall time; evaluations and checkpoints excluded) and/or steps of this
session, whichever is reached first (:data:`DEFAULT_MINUTES` when neither is given).

**Outputs** in ``RUN_DIR/refined/`` (:class:`~mipslam.io.run_folder.RefinedFolder`; the run's own files are never
written): ``map.ply``, ``traj_est.txt`` and ``keyframes.txt`` (byte copies of the run's when no pose moved; with
refined keyframe poses every other frame follows its keyframes, :meth:`SLAMState.correct_keyframe_poses` with
``move_map=False``, as the run's final refinement does), ``progress.json`` (one record per evaluation: refinement
seconds, steps, Gaussians, novel-view and training-view PSNR at native resolution on a fixed subset of at most
:data:`PROGRESS_FRAMES` frames of each set, no LPIPS; the first record is the SLAM map, before any step),
``metrics.json`` (the refined map and poses evaluated with the run's own protocol,
:func:`~mipslam.evaluation.run_eval.evaluate_run`; removed when the map moves on without a new evaluation) and
``checkpoints/`` (map, optimizer, refiner state, generator, steps, seconds and the progress records; written
atomically every :data:`CHECKPOINT_EVERY_S` seconds and at the end, the newest :data:`KEEP_CHECKPOINTS` kept).

**Resume.** A later :func:`refine_run` continues from ``refined/checkpoints`` (steps and seconds accumulate; the
budget given applies to that session) and gives the same map as an uninterrupted refinement of the same total
steps (CPU, same thread count). ``restart`` starts over from the SLAM map, replacing ``refined/``. A checkpoint of
another SLAM map (the run was resumed or replaced since) or of a config that differs in keys that change results
is refused, with what to type.

**Ctrl-C.** The first finishes the current step, writes the checkpoint and the outputs (map, poses, progress) and
raises KeyboardInterrupt; a second one stops at once (nothing written; the last checkpoint stays).
"""
from __future__ import annotations

import hashlib
import logging
import math
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from mipslam.checkpoint import (Checkpoint, capture_rng_state, config_differences, list_checkpoints,
                                load_latest_checkpoint, restore_rng_state, save_checkpoint, select_prefix,
                                with_prefix)
from mipslam.config import Config, config_to_dict
from mipslam.errors import CheckpointError, ConfigError, DatasetError, EvaluationError, MipslamError
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.geometry import nearest_rigid
from mipslam.io.run_folder import RefinedFolder, RunFolder, write_bytes_atomic, write_json_atomic
from mipslam.refinement import KeyframeRefiner, RefineKeyframe, image_loader, refine_options, state_keyframes
from mipslam.mapping import MappingOptions
from mipslam.run_control import PROGRESS_LOG_S, ctrl_c_after_the_frame, resolve_device
from mipslam.state import SLAMState

log = logging.getLogger(__name__)

__all__ = ["RefineRequest", "RefineSummary", "refine_run", "DEFAULT_MINUTES", "PROGRESS_FRAMES"]

REFINE_STATE_VERSION = 1
RESOLUTIONS = ("mapping", "native")
DEFAULT_MINUTES = 10.0  # the budget when neither minutes nor iterations are given
CHECKPOINT_EVERY_S = 60.0  # wall-clock seconds between checkpoints
KEEP_CHECKPOINTS = 2
PROGRESS_FRAMES = 8  # at most this many frames of each view set in a progress record
IMAGE_CACHE_MIB = 1024  # keyframe images (and their loss masks) kept in memory; beyond it they are read again
_STREAM_KINDS = ("realsense", "realsense_bag")
_TIME_BAR = "{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
_STEP_BAR = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_noinv_fmt}{postfix}]"


@dataclass(frozen=True)
class RefineRequest:
    """One session of ``mipslam refine`` (module docstring).

    minutes / iterations: this session's budget in refinement minutes and steps, whichever is reached first
    (neither: :data:`DEFAULT_MINUTES`; iterations 0 takes no step and writes and evaluates the map as it is).
    resolution: ``mapping`` | ``native``; None = the checkpoint's when continuing, else ``mapping``.
    restart: start over from the SLAM map, replacing ``refined/``.
    eval_every_minutes: refinement minutes between progress records (0 = only before the first step and at the end).
    evaluate: the full evaluation at the end (``refined/metrics.json``).
    """

    minutes: float | None = None
    iterations: int | None = None
    resolution: str | None = None
    restart: bool = False
    eval_every_minutes: float = 1.0
    evaluate: bool = True
    checkpoint_every_s: float = CHECKPOINT_EVERY_S
    progress_frames: int = PROGRESS_FRAMES

    def __post_init__(self):
        if self.minutes is not None and not (math.isfinite(self.minutes) and self.minutes > 0):
            raise ConfigError(f"refine: minutes must be a positive number, got {self.minutes!r}")
        if self.iterations is not None and (isinstance(self.iterations, bool) or int(self.iterations) != self.iterations
                                            or self.iterations < 0):
            raise ConfigError(f"refine: iterations must be a whole number >= 0, got {self.iterations!r}")
        if self.resolution is not None and self.resolution not in RESOLUTIONS:
            raise ConfigError(f"refine: resolution must be one of {', '.join(RESOLUTIONS)}, got {self.resolution!r}")
        if not (math.isfinite(self.eval_every_minutes) and self.eval_every_minutes >= 0):
            raise ConfigError(f"refine: eval_every_minutes must be >= 0 (0 = only at the end), got "
                              f"{self.eval_every_minutes!r}")
        if not self.checkpoint_every_s > 0 or self.progress_frames < 1:
            raise ConfigError("refine: checkpoint_every_s must be > 0 and progress_frames >= 1")

    @property
    def budget_s(self) -> float | None:
        """This session's refinement seconds (None: no time limit, the steps decide)."""
        if self.minutes is not None:
            return 60.0 * self.minutes
        return None if self.iterations is not None else 60.0 * DEFAULT_MINUTES


@dataclass(frozen=True)
class RefineSummary:
    """What a session of :func:`refine_run` did and where its results are."""

    run_dir: Path
    refined_dir: Path
    resolution: str
    image_size: tuple[int, int]
    keyframes: int
    gaussians: int
    steps: int  # in all sessions
    seconds: float  # refinement seconds in all sessions
    session_steps: int
    session_seconds: float
    resumed: bool
    stopped: str  # why this session ended: budget | non-finite loss
    poses_refined: bool
    progress: tuple[dict, ...]
    metrics: dict | None  # refined/metrics.json (None: not evaluated)
    slam_metrics: dict | None  # the run's metrics.json, for comparison
    report: Path | None

    def describe(self) -> str:
        session = (f"{self.session_steps} steps in {self.session_seconds:.1f} s this session"
                   + (f" ({self.steps} steps, {self.seconds:.1f} s in all)" if self.resumed else ""))
        lines = [f"refined {self.refined_dir}: {session} over {self.keyframes} keyframes at "
                 f"{self.resolution} resolution {self.image_size[0]}x{self.image_size[1]}, {self.gaussians} Gaussians"
                 + ("; keyframe poses refined" if self.poses_refined else "")
                 + ("" if self.stopped == "budget" else f"; stopped: {self.stopped}")]
        if len(self.progress) >= 1:
            first, last = self.progress[0], self.progress[-1]
            for views, name in (("novel", "novel views"), ("training", "training views")):
                before, after = first.get(f"{views}_psnr"), last.get(f"{views}_psnr")
                if before is not None and after is not None:
                    lines.append(f"{name} PSNR ({last.get(f'{views}_frames')} frames, native resolution, progress "
                                 f"subset): {before:.2f} dB at step {first['steps']} -> {after:.2f} dB at step "
                                 f"{last['steps']}")
        rows = _headline_rows(self.metrics)
        if rows:
            slam = _headline_rows(self.slam_metrics)
            for views, row in rows.items():
                text = f"full evaluation, {views} views ({row['frames']} frames, {row['width']}x{row['height']}): "
                before = slam.get(views)
                if before is not None and before.get("psnr") is not None and row.get("psnr") is not None:
                    text += f"PSNR {before['psnr']:.2f} -> {row['psnr']:.2f} dB, SSIM {before['ssim']:.4f} -> " \
                            f"{row['ssim']:.4f}"
                    if before.get("lpips") is not None and row.get("lpips") is not None:
                        text += f", LPIPS {before['lpips']:.4f} -> {row['lpips']:.4f}"
                    text += " (SLAM map -> refined)"
                else:
                    text += f"PSNR {_number(row.get('psnr'))} dB, SSIM {row['ssim']:.4f}"
                lines.append(text)
            ate = (self.metrics or {}).get("trajectory", {}).get("ate")
            if ate and self.poses_refined:
                lines.append(f"ATE RMSE of the refined poses {ate['rmse'] * 100:.3f} cm")
            lines.append(f"metrics: {self.refined_dir / 'metrics.json'}")
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return "\n".join(lines)


def _number(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _headline_rows(metrics: dict | None) -> dict[str, dict]:
    """views -> the scale-1 row in the run's mode of a metrics dict's render table (novel views first)."""
    render = (metrics or {}).get("render")
    if not isinstance(render, dict) or not render.get("rows"):
        return {}
    mode = render.get("protocol", {}).get("renderer", {}).get("run_mode")
    rows: dict[str, dict] = {}
    for row in sorted(render["rows"], key=lambda r: (r.get("views") != "novel", abs(math.log(r["scale"])),
                                                     r["mode"] != mode)):
        rows.setdefault(row.get("views", "all"), row)
    return rows


# ----------------------------------------------------------------------------- the run to refine

@dataclass
class _Start:
    """What the refinement starts from (module docstring)."""

    config: Config
    state: SLAMState  # frames with the run's final poses (traj_est.txt), keyframes, exposures; its map unused
    poses: torch.Tensor  # [F, 4, 4] float64, the run's final poses
    keyframes: list[RefineKeyframe]
    map_sha256: str


def _check_run(folder: RunFolder) -> Config:
    """The run's config, after checking that the folder holds a finished run (MipslamError naming what is
    missing and what to do)."""
    from mipslam.evaluation.run_files import read_run_config

    root = folder.root
    if not root.exists():
        raise MipslamError(f"{root}: no such run folder; give the folder 'mipslam run' wrote")
    if not root.is_dir():
        raise MipslamError(f"{root}: is not a run folder (not a folder at all); give the folder 'mipslam run' wrote")
    if not folder.config_yaml.is_file():
        raise MipslamError(f"{folder.config_yaml}: missing; is {root} a run folder written by 'mipslam run'?")
    if not list_checkpoints(folder.checkpoints):
        raise MipslamError(f"{root}: no checkpoint in {folder.checkpoints}; is this a run folder written by "
                           "'mipslam run'? (mipslam refine reads the run's keyframes from its latest checkpoint)")
    for path in (folder.map_ply, folder.traj_est):
        if not path.is_file():
            raise MipslamError(f"{path}: missing; the run has not finished (a run writes it at its end): finish it "
                               f"with mipslam run --resume {root}, then refine it")
    for path in (root / "run.json", root / "frames.json"):
        if not path.is_file():
            raise MipslamError(f"{path}: missing; is {root} a complete run folder written by 'mipslam run'?")
    config = read_run_config(folder)
    if config.dataset.kind in _STREAM_KINDS:
        raise MipslamError(f"{root}: the run read a {config.dataset.kind} stream; its keyframe images cannot be read "
                           "again, so it cannot be refined")
    return config


def _load_start(folder: RunFolder, config: Config) -> _Start:
    from mipslam.io.tum import read_tum_trajectory

    checkpoint = load_latest_checkpoint(folder.checkpoints)
    state = SLAMState.from_checkpoint(checkpoint.tensors, checkpoint.metadata, MappingOptions.from_config(config.mapping),
                                      torch.device("cpu"))
    trajectory = read_tum_trajectory(folder.traj_est)
    if len(trajectory) != len(state.frames):
        raise MipslamError(f"{folder.traj_est}: {len(trajectory)} poses but the run's latest checkpoint "
                           f"{checkpoint.path.name} holds {len(state.frames)} frames; the run folder is inconsistent "
                           f"(finish the run with mipslam run --resume {folder.root})")
    for record, stamp in zip(state.frames, trajectory.timestamps):
        if abs(record.timestamp - float(stamp)) > 1e-4 * max(1.0, abs(record.timestamp)):
            raise MipslamError(f"{folder.traj_est}: pose at t={float(stamp)} does not match the checkpoint's frame "
                               f"{record.index} (t={record.timestamp}); the run folder is inconsistent")
    if not state.keyframe_frames:
        raise MipslamError(f"{folder.root}: the run has no keyframes; there is nothing to refine over")
    poses = torch.from_numpy(trajectory.T_wc.copy()).to(torch.float64)
    state.set_poses(poses)
    return _Start(config, state, poses, state_keyframes(state), _sha256(folder.map_ply))


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _open_sequence(config: Config, resolution: str):
    """The run's dataset as the refinement reads it: as the run did (mapping) or with downscale 1 (native)."""
    from mipslam.datasets import make_sequence

    path = Path(config.dataset.path).expanduser() if config.dataset.path else None
    if path is None or not path.is_dir():
        raise DatasetError(path, "the run's dataset folder (config.yaml dataset.path) is not there; mipslam refine "
                                 "trains on its keyframe images: put the dataset back where the run read it")
    cfg = config.dataset if resolution == "mapping" else replace(config.dataset, downscale=1)
    return make_sequence(cfg)


def _keyframe_loader(sequence, state: SLAMState, device: torch.device, keyframes):
    """``load(keyframe)`` for the refiner: the keyframe's frame as the camera recorded it (as the run's final
    refinement reads it: :func:`mipslam.mapping.refine_map`)."""
    stamps = sequence.timestamps
    for keyframe in keyframes:
        record = state.frames[state.keyframe_frames[keyframe.keyframe_id]]
        if keyframe.frame_index >= len(sequence) or abs(float(stamps[keyframe.frame_index]) - record.timestamp) > \
                1e-4 * max(1.0, abs(record.timestamp)):
            raise DatasetError(sequence.root, f"frame {keyframe.frame_index} (keyframe {keyframe.keyframe_id}) is not "
                                              "the one the run read; was the dataset changed since the run?")
    return image_loader(sequence.__getitem__, device)


def _image_cache_size(width: int, height: int, keyframes: int) -> int:
    """How many keyframes' images and masks fit in :data:`IMAGE_CACHE_MIB` (at least one, at most all)."""
    per_keyframe = width * height * (4 * 4 + 4)  # colour and depth float32, masks
    return max(1, min(keyframes, IMAGE_CACHE_MIB * 2**20 // per_keyframe))


# ----------------------------------------------------------------------------- checkpoints

@dataclass
class _Progress:
    """Steps, seconds, progress records and sessions of the refinement so far (all sessions)."""

    steps: int = 0
    seconds: float = 0.0
    records: list[dict] = field(default_factory=list)
    sessions: list[dict] = field(default_factory=list)


def _save(refined: RefinedFolder, config: Config, gmap: GaussianMap, optimizer: GaussianOptimizer,
          refiner: KeyframeRefiner, generator: torch.Generator, progress: _Progress, resolution: str,
          start: _Start) -> Path:
    tensors = {**with_prefix("map", {k: v.detach().cpu() for k, v in gmap.state_dict().items()}),
               **with_prefix("optim", {k: v.detach().cpu() for k, v in optimizer.state_dict().items()}),
               **with_prefix("refiner", refiner.state_dict())}
    rng_tensors, rng_meta = capture_rng_state({"refine": generator})
    tensors.update(rng_tensors)
    metadata = {"refine_state_version": REFINE_STATE_VERSION, "steps": progress.steps, "seconds": progress.seconds,
                "resolution": resolution, "keyframes": len(start.keyframes), "slam_map_sha256": start.map_sha256,
                "records": progress.records, "sessions": progress.sessions, "rng": rng_meta}
    return save_checkpoint(refined.checkpoints, tensors, metadata, config=config_to_dict(config), keep=KEEP_CHECKPOINTS)


def _latest_checkpoint(refined: RefinedFolder) -> Checkpoint | None:
    if not list_checkpoints(refined.checkpoints):
        return None
    return load_latest_checkpoint(refined.checkpoints)


def _check_continuation(checkpoint: Checkpoint, config: Config, start: _Start, resolution: str, run_root: Path) -> None:
    """A refinement checkpoint continues only the same refinement: of the same SLAM map, config and resolution."""
    meta = checkpoint.metadata
    again = f"start the refinement over with mipslam refine {run_root} --restart"
    if meta.get("refine_state_version") != REFINE_STATE_VERSION:
        raise CheckpointError(f"{checkpoint.path}: refinement state version {meta.get('refine_state_version')!r}, "
                              f"this mipslam reads version {REFINE_STATE_VERSION}; {again}")
    if meta.get("slam_map_sha256") != start.map_sha256:
        raise CheckpointError(f"{checkpoint.path}: refines another SLAM map than {run_root / 'map.ply'} (the run was "
                              f"resumed or replaced since the refinement started); {again}")
    differences = config_differences(checkpoint.config, config_to_dict(config))
    if differences:
        raise CheckpointError(f"{checkpoint.path}: the run's config.yaml differs from the one the refinement started "
                              f"with in keys that change results ({'; '.join(differences)}); {again}")
    if meta.get("resolution") != resolution:
        raise CheckpointError(f"{checkpoint.path}: the refinement trains at {meta.get('resolution')} resolution; "
                              f"continue it with --resolution {meta.get('resolution')}, or {again} "
                              f"--resolution {resolution}")
    if meta.get("keyframes") != len(start.keyframes):
        raise CheckpointError(f"{checkpoint.path}: refines {meta.get('keyframes')} keyframes, the run has "
                              f"{len(start.keyframes)}; {again}")


# ----------------------------------------------------------------------------- outputs

def _frame_poses(start: _Start, refiner: KeyframeRefiner) -> torch.Tensor:
    """Every frame's pose [F, 4, 4] float64: the run's, or with refined keyframe poses every frame following its
    keyframes (as the run's final refinement applies them)."""
    refined = refiner.refined_poses()
    if not refined:
        return start.poses
    state = start.state
    state.set_poses(start.poses)
    keyframe_poses = state.keyframe_poses()
    for keyframe_id, T_wc in refined:
        keyframe_poses[keyframe_id] = nearest_rigid(T_wc)
    state.correct_keyframe_poses(keyframe_poses, move_map=False)
    poses = state.poses()
    state.set_poses(start.poses)
    return poses


def _write_outputs(folder: RunFolder, start: _Start, gmap: GaussianMap, refiner: KeyframeRefiner,
                   progress: _Progress, resolution: str, image_size: tuple[int, int]) -> None:
    from mipslam.io.ply import write_map_ply
    from mipslam.io.tum import write_tum_trajectory

    refined = folder.refined
    write_map_ply(refined.map_ply, gmap)
    if refiner.refined_poses():
        poses = _frame_poses(start, refiner)
        frames = start.state.frames
        stamps = torch.tensor([f.timestamp for f in frames], dtype=torch.float64)
        write_tum_trajectory(refined.traj_est, stamps, poses)
        positions = start.state.keyframe_frames
        write_tum_trajectory(refined.keyframes, stamps[positions], poses[positions])
    else:  # exactly the run's poses: its own files
        write_bytes_atomic(refined.traj_est, folder.traj_est.read_bytes())
        if folder.keyframes.is_file():
            write_bytes_atomic(refined.keyframes, folder.keyframes.read_bytes())
    write_json_atomic(refined.progress, _progress_file(folder, start, progress, resolution, image_size))
    if refined.metrics.is_file():  # an evaluation of an earlier state of the map no longer describes it
        try:
            import json

            evaluated = json.loads(refined.metrics.read_text(encoding="utf-8")).get("refinement", {}).get("steps")
        except (OSError, ValueError, AttributeError):
            evaluated = None
        if evaluated != progress.steps:
            refined.metrics.unlink()


def _progress_file(folder: RunFolder, start: _Start, progress: _Progress, resolution: str,
                   image_size: tuple[int, int]) -> dict:
    return {
        "run_dir": str(folder.root),
        "columns": {
            "records": "one per evaluation during the refinement: refinement seconds (the steps' own time, all "
                       "sessions), steps, Gaussians, session, and the PSNR (dB) of the novel views (MonoGS's every 5th "
                       "frame that is not a keyframe) and the training views (keyframes), rendered at native "
                       f"resolution from the refined poses, on a fixed subset of at most {PROGRESS_FRAMES} frames of "
                       "each set (their count: *_frames), no exposure compensation, no LPIPS; the first record is the "
                       "SLAM map before any step",
            "sessions": "each run of mipslam refine: when it started, its steps and seconds, how it ended",
        },
        "resolution": resolution,
        "image_size": list(image_size),
        "keyframes": len(start.keyframes),
        "steps": progress.steps,
        "seconds": progress.seconds,
        "sessions": progress.sessions,
        "records": progress.records,
    }


def _progress_record(context, gmap: GaussianMap, poses: torch.Tensor, progress: _Progress, session: int,
                     frames: int) -> dict:
    """PSNR of the novel and training views on the fixed subset (module docstring)."""
    from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render

    with torch.no_grad():
        current = replace(context, gaussians=gmap.activated().detached(), T_wc_est=poses.to(torch.float64))
    evaluation = evaluate_render(current, RenderEvalOptions(frames="split", resolution="native", scales=(1.0,),
                                                            lpips=False, showcase=False, max_frames=frames))
    record: dict[str, Any] = {"seconds": round(progress.seconds, 3), "steps": progress.steps,
                              "gaussians": len(gmap), "session": session}
    for views in ("novel", "training"):
        row = next((r for r in evaluation.rows if r.views == views), None)
        record[f"{views}_psnr"] = None if row is None or not math.isfinite(row.psnr) else round(row.psnr, 4)
        record[f"{views}_frames"] = 0 if row is None else row.frames
    return record


# ----------------------------------------------------------------------------- progress display

class _Display:
    """A tqdm bar on a terminal (refinement seconds of the session's budget, or steps without a time budget);
    otherwise a log line every ``PROGRESS_LOG_S`` seconds (as :class:`mipslam.run_control.Progress`)."""

    def __init__(self, request: RefineRequest, interval_s: float = PROGRESS_LOG_S):
        self.budget_s, self.iterations = request.budget_s, request.iterations
        self.by_time = self.budget_s is not None
        total = self.budget_s if self.by_time else self.iterations
        self.bar = tqdm(total=total, desc="refine", unit="s" if self.by_time else "step", dynamic_ncols=True,
                        disable=None, file=sys.stderr, bar_format=_TIME_BAR if self.by_time else _STEP_BAR)
        self.interval_s, self.last = interval_s, time.perf_counter()

    def step(self, seconds: float, session_steps: int, session_seconds: float, steps: int, loss: float) -> None:
        if not self.bar.disable:
            self.bar.set_postfix(OrderedDict(step=steps, loss=f"{loss:.4f}"), refresh=False)
            if self.by_time:
                self.bar.update(min(seconds, max(0.0, self.budget_s - self.bar.n)))
            else:
                self.bar.update(1)
            return
        now = time.perf_counter()
        if session_steps > 1 and now - self.last < self.interval_s:
            return
        self.last = now
        budget = [f"{session_seconds:.0f}/{self.budget_s:.0f} s" if self.by_time else f"{session_seconds:.0f} s"]
        if self.iterations is not None:
            budget.append(f"{session_steps}/{self.iterations} steps")
        log.info("refine: step %d (%s this session), loss %.4f", steps, ", ".join(budget), loss)

    def close(self) -> None:
        self.bar.close()


# ----------------------------------------------------------------------------- the refinement

def refine_run(run_dir: str | Path, request: RefineRequest = RefineRequest()) -> RefineSummary:
    """Refine the map of the finished run in ``run_dir`` for ``request``'s budget (module docstring).

    Raises MipslamError (a folder that is not a finished run, a dataset that is gone, a checkpoint that does not
    continue this refinement), and KeyboardInterrupt after a Ctrl-C (the state saved, see the module docstring).
    """
    folder = RunFolder(run_dir)
    config = _check_run(folder)
    refined = folder.refined
    if request.restart and refined.root.exists():
        refined.remove()
        log.warning("--restart: removed the earlier refinement in %s", refined.root)
    checkpoint = _latest_checkpoint(refined)
    resolution = request.resolution or (checkpoint.metadata.get("resolution") if checkpoint else None) or "mapping"
    start = _load_start(folder, config)
    if checkpoint is not None:
        _check_continuation(checkpoint, config, start, resolution, folder.root)
    sequence = _open_sequence(config, resolution)
    device = resolve_device(config.run.device)
    if config.run.threads:
        torch.set_num_threads(config.run.threads)
    _warm_up(config, device)

    if checkpoint is not None:
        gmap = GaussianMap.from_state_dict(select_prefix("map", checkpoint.tensors), device=device)
    else:
        from mipslam.io.ply import read_map_ply

        gmap = read_map_ply(folder.map_ply, device=device)
    optimizer = GaussianOptimizer.from_config(gmap, MappingOptions.from_config(config.mapping))
    generator = torch.Generator(device="cpu")
    generator.manual_seed(config.run.seed)
    intrinsics = sequence.intrinsics
    image_size = (intrinsics.width, intrinsics.height)
    load = _keyframe_loader(sequence, start.state, device, start.keyframes)
    refiner = KeyframeRefiner(gmap, optimizer, start.keyframes, load, refine_options(config), config.render, generator,
                              cache_size=_image_cache_size(*image_size, len(start.keyframes)))
    progress = _Progress()
    if checkpoint is not None:
        tensors, meta = checkpoint.tensors, checkpoint.metadata
        optimizer.load_state_dict({k: v.to(device) for k, v in select_prefix("optim", tensors).items()})
        try:
            refiner.load_state_dict(select_prefix("refiner", tensors))
        except (ValueError, KeyError) as exc:
            raise CheckpointError(f"{checkpoint.path}: cannot continue the refinement ({exc}); start it over with "
                                  f"mipslam refine {folder.root} --restart") from exc
        restore_rng_state(tensors, meta["rng"], {"refine": generator})
        progress = _Progress(int(meta["steps"]), float(meta["seconds"]), list(meta.get("records") or []),
                             list(meta.get("sessions") or []))
        log.info("continuing the refinement of %s from %s (step %d, %.1f s of refinement)", folder.root,
                 checkpoint.path.name, progress.steps, progress.seconds)
    refined.create()
    refined.remove_stale_temporaries()
    session_number = len(progress.sessions) + 1
    session = {"session": session_number, "started_utc": _utc_now(), "steps": 0, "seconds": 0.0, "end": "running",
               "resolution": resolution}
    progress.sessions.append(session)

    context = None

    def record_progress() -> None:
        nonlocal context
        if context is None:
            from mipslam.evaluation.render_eval import load_render_context

            context = load_render_context(folder.root, device=device)
        if progress.records and progress.records[-1]["steps"] == progress.steps:
            return
        started = time.perf_counter()
        progress.records.append(_progress_record(context, gmap, _frame_poses(start, refiner), progress,
                                                 session_number, request.progress_frames))
        record = progress.records[-1]
        log.info("refine: step %d, %.1f s: novel views %s dB, training views %s dB (%d + %d frames, native "
                 "resolution; evaluated in %.1f s)", progress.steps, progress.seconds, _number(record["novel_psnr"]),
                 _number(record["training_psnr"]), record["novel_frames"], record["training_frames"],
                 time.perf_counter() - started)

    def save() -> Path:
        path = _save(refined, config, gmap, optimizer, refiner, generator, progress, resolution, start)
        _write_outputs(folder, start, gmap, refiner, progress, resolution, image_size)
        return path

    budget_s, iterations = request.budget_s, request.iterations
    every_s = 60.0 * request.eval_every_minutes
    next_eval = (math.floor(progress.seconds / every_s) + 1) * every_s if every_s > 0 else math.inf
    if not progress.records:  # the SLAM map, before any step: what the refinement starts from
        record_progress()
    display = _Display(request)
    step_complete, stopped = True, "budget"
    last_checkpoint = time.perf_counter()
    try:
        with ctrl_c_after_the_frame("step") as stop_requested:
            while True:
                if stop_requested:
                    raise KeyboardInterrupt
                if (budget_s is not None and session["seconds"] >= budget_s) or \
                        (iterations is not None and session["steps"] >= iterations):
                    break
                if progress.seconds >= next_eval:
                    record_progress()
                    next_eval = (math.floor(progress.seconds / every_s) + 1) * every_s
                    continue  # a Ctrl-C during the evaluation stops here
                if time.perf_counter() - last_checkpoint >= request.checkpoint_every_s:
                    _save(refined, config, gmap, optimizer, refiner, generator, progress, resolution, start)
                    last_checkpoint = time.perf_counter()
                step_complete = False
                started = time.perf_counter()
                loss = refiner.step()
                elapsed = time.perf_counter() - started
                step_complete = True
                if loss is None:
                    stopped = "non-finite loss (the map keeps its last finite state)"
                    log.warning("refine: the loss of step %d is not finite; stopping (the map keeps its last finite "
                                "state)", progress.steps + 1)
                    break
                progress.steps += 1
                progress.seconds += elapsed
                session["steps"] += 1
                session["seconds"] += elapsed
                display.step(elapsed, session["steps"], session["seconds"], progress.steps, loss)
    except KeyboardInterrupt:
        display.close()
        if step_complete:
            session["end"] = "interrupted"
            save()
            log.warning("interrupted: refinement saved after step %d (%.1f s of refinement) in %s; continue with: "
                        "mipslam refine %s", progress.steps, progress.seconds, refined.root, folder.root)
        else:  # a second Ctrl-C inside a step: its half-done state must not become a checkpoint
            log.warning("interrupted inside step %d: not saved; mipslam refine %s continues from the last checkpoint",
                        progress.steps + 1, folder.root)
        raise
    display.close()
    session["end"] = stopped
    record_progress()  # the end of the session (skipped when no step was taken since the last record)
    save()
    log.info("refine: %d steps, %.1f s of refinement in all; outputs in %s", progress.steps, progress.seconds,
             refined.root)
    metrics = _evaluate(folder, progress, resolution, refiner) if request.evaluate else None
    report = _write_report(folder)
    return RefineSummary(folder.root, refined.root, resolution, image_size, len(start.keyframes), len(gmap),
                         progress.steps, progress.seconds, session["steps"], session["seconds"], checkpoint is not None,
                         stopped, bool(refiner.refined_poses()), tuple(progress.records), metrics,
                         _read_json(folder.metrics), report)


def _warm_up(config: Config, device: torch.device) -> None:
    """The renderer's compiled CPU backend loaded before the first step, so no step's time includes it."""
    if config.render.backend != "torch" and device.type == "cpu":
        from mipslam.render.cpu import warm_up

        warm_up()


def _utc_now() -> str:
    import datetime

    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _read_json(path: Path) -> dict | None:
    import json

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _evaluate(folder: RunFolder, progress: _Progress, resolution: str, refiner: KeyframeRefiner) -> dict | None:
    """refined/metrics.json: the refined map and poses with the run's own protocol (None without ground truth)."""
    from mipslam.evaluation.run_eval import evaluate_run

    refined = folder.refined
    if not folder.traj_gt.is_file():
        log.info("no ground truth for this run's sequence: the refined map is not evaluated")
        return None
    log.info("evaluating the refined map with the run's own protocol")
    try:
        metrics = evaluate_run(folder.root, map_ply=refined.map_ply.relative_to(folder.root),
                               traj_est=refined.traj_est.relative_to(folder.root), report=False)
    except KeyboardInterrupt:
        log.warning("interrupted during the evaluation: the refined map and its checkpoint are saved; evaluate it "
                    "with mipslam refine %s --iterations 0", folder.root)
        raise
    except EvaluationError as exc:
        log.warning("the refined map could not be evaluated: %s", exc)
        return None
    metrics["refinement"] = {"steps": progress.steps, "seconds": progress.seconds, "resolution": resolution,
                             "keyframes": len(refiner.keyframes), "poses_refined": bool(refiner.refined_poses())}
    write_json_atomic(refined.metrics, metrics)
    return metrics


def _write_report(folder: RunFolder) -> Path | None:
    """The run's report page rebuilt with its Refinement section (None when the run has no report yet)."""
    from mipslam.evaluation.report import write_report_page

    if not folder.metrics.is_file() and not folder.report.is_dir():
        return None
    return write_report_page(folder.root).html
