"""Sensor and scene extremes (docs/robustness.md): whole runs on tiny data_synth variants of one sequence.

The clean sequence: data_synth's ``loop`` trajectory (12 frames, 40x30, scene seed 0) rendered
with :func:`data_synth.render_view` and written as a Replica folder. Each variant changes it:

* ``black`` / ``saturated``: frames 5 and 6 all black / all white (depth kept);
* ``no_depth``: frames 5 and 6 without any valid depth;
* ``holes_and_noise``: every frame with 50 % depth dropouts (plus holes at depth edges) and depth
  noise of 1 cm at 1 m growing with z^2 (about 4 cm at the 2 m wall: several times a Kinect's);
* ``textureless``: frames 5 and 6 show a flat grey wall 0.5 m in front of the camera (a board held
  in front of the lens): flat colour and plane depth;
* ``jump``: from frame 6 on the camera is 30 cm to its right (a dropped frame sequence / a bump);
* ``repeated``: frame 5 repeated 20 times (the camera at rest), then the rest of the loop;
* ``zoom``: a separate dolly towards the test chart on the +x wall from 2.0 m to 0.4 m in 23
  frames, accelerating to 8 cm per frame (the chart's on-screen size grows 5x).

Every run must finish with: the frames that were not tracked flagged (exactly the broken ones where
the broken frames cannot be tracked); no NaN/Inf in any pose, map or optimizer tensor of the final
checkpoint nor in the losses of frames.json (a flagged frame's loss may be null); the Gaussian count
at or under ``mapping.max_gaussians`` after every frame; and tracking recovered: the ATE of the good
frames at most 2x the clean run's ATE on the same frames.

ATE here is the RMSE of camera positions without alignment (the run's map frame is the ground-truth
frame of frame 0; an alignment would hide a jump). At 40x30 one pixel spans 5 cm at the 1.5-2 m the
loop looks at, and the clean run's ATE is about 4 cm: these runs check robustness, not accuracy.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

import data_synth
from data_synth.scene import ROOM_MAX
from data_synth.sensor import SensorOptions, apply_depth_effects
from data_synth.writer import color_to_uint8_bgr, default_intrinsics, depth_to_uint16
from mipslam.checkpoint import load_latest_checkpoint
from mipslam.config import load_config
from mipslam.pipeline import RunSummary, run_slam

WIDTH, HEIGHT, FRAMES = 40, 30, 12
DEPTH_SCALE = 6553.5
MAX_GAUSSIANS = 600
BAD = [5, 6]  # the frames the frame-level variants break
SETTINGS = [
    "mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
    "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
    "run.checkpoint_every=0", "loop.enabled=false", f"mapping.max_gaussians={MAX_GAUSSIANS}",
]
ATE_RATIO = 2.0


# ----------------------------------------------------------------------------- building the variants

@dataclass(frozen=True)
class SceneFrame:
    T_wc: np.ndarray  # [4, 4] float64 ground truth, camera to world
    color: np.ndarray  # [H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [H, W] float32 metres, 0 = none


class Renderer:
    """Renders the scene of seed 0 at 40x30 (2x2 supersampling), caching poses already rendered."""

    def __init__(self):
        self.scene = data_synth.make_scene(0)
        self.intrinsics = default_intrinsics(WIDTH, HEIGHT)
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, T_wc: np.ndarray) -> SceneFrame:
        key = np.ascontiguousarray(T_wc).tobytes()
        if key not in self._cache:
            self._cache[key] = data_synth.render_view(self.scene, T_wc, self.intrinsics, supersample=2)
        color, depth = self._cache[key]
        return SceneFrame(T_wc, color, depth)


def write_replica(root: Path, frames: list[SceneFrame], intrinsics) -> Path:
    """A Replica folder (results/frame*.png, depth*.png, traj.txt, cam_params.json) holding ``frames``."""
    (root / "results").mkdir(parents=True)
    for i, frame in enumerate(frames):
        assert cv2.imwrite(str(root / "results" / f"frame{i:06d}.png"), color_to_uint8_bgr(frame.color))
        assert cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), depth_to_uint16(frame.depth, DEPTH_SCALE))
    (root / "traj.txt").write_text("".join(" ".join(f"{v:.17g}" for v in f.T_wc.reshape(-1)) + "\n" for f in frames))
    camera = {"w": WIDTH, "h": HEIGHT, "fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx,
              "cy": intrinsics.cy, "scale": DEPTH_SCALE}
    (root / "cam_params.json").write_text(json.dumps({"camera": camera}))
    return root


def replace_frames(frames: list[SceneFrame], indices, *, color=None, depth=None) -> list[SceneFrame]:
    out = list(frames)
    for i in indices:
        out[i] = SceneFrame(out[i].T_wc, out[i].color if color is None else color, out[i].depth if depth is None else depth)
    return out


def zoom_poses() -> np.ndarray:
    """Dolly along +x towards the chart on the +x wall: 2.0 m -> 0.4 m, speeding up to 8 cm/frame and back."""
    start = data_synth.trajectory_poses("zoom", 1)[0]  # facing the chart
    steps = [0.02, 0.04, 0.06] + [0.08] * 17 + [0.06, 0.04, 0.02]
    distances = 2.0 - np.concatenate([[0.0], np.cumsum(steps)])
    poses = np.repeat(start[None], len(distances), axis=0)
    poses[:, 0, 3] = ROOM_MAX[0] - distances  # the chart hangs on the +x wall
    return poses


def build_variant(name: str, render: Renderer) -> tuple[list[SceneFrame], list[int]]:
    """(frames, indices of the broken frames) of variant ``name``."""
    clean = [render(T) for T in data_synth.trajectory_poses("loop", FRAMES)]
    black = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    if name == "clean":
        return clean, []
    if name == "black":
        return replace_frames(clean, BAD, color=black), BAD
    if name == "saturated":
        return replace_frames(clean, BAD, color=np.ones_like(black)), BAD
    if name == "no_depth":
        return replace_frames(clean, BAD, depth=np.zeros((HEIGHT, WIDTH), np.float32)), BAD
    if name == "textureless":
        return replace_frames(clean, BAD, color=np.full_like(black, 0.6),
                              depth=np.full((HEIGHT, WIDTH), 0.5, np.float32)), BAD
    if name == "holes_and_noise":
        options = SensorOptions(depth_noise=0.01, depth_holes=0.5)
        return [SceneFrame(f.T_wc, f.color, apply_depth_effects(f.depth, options, seed=0, frame=i))
                for i, f in enumerate(clean)], []
    if name == "jump":
        right = np.eye(4)
        right[0, 3] = 0.30  # 30 cm along the camera's x axis (to its right)
        return [f if i < 6 else render(f.T_wc @ right) for i, f in enumerate(clean)], [6]
    if name == "repeated":
        return clean[:6] + [clean[5]] * 19 + clean[6:], []
    if name == "zoom":
        return [render(T) for T in zoom_poses()], []
    raise AssertionError(name)


# ----------------------------------------------------------------------------- running and measuring

@dataclass(frozen=True)
class VariantRun:
    name: str
    frames: list[SceneFrame]
    bad: list[int]
    summary: RunSummary
    frames_json: dict
    checkpoint_tensors: dict
    estimated_T_wc: np.ndarray  # [N, 4, 4]
    position_errors: np.ndarray  # [N] metres, no alignment

    @property
    def flagged(self) -> list[int]:
        return self.frames_json["flagged"]

    def ate(self, indices) -> float:
        errors = self.position_errors[list(indices)]
        return float(np.sqrt(np.mean(errors ** 2)))


def run_variant(name: str, render: Renderer, root: Path, *extra_settings: str) -> VariantRun:
    frames, bad = build_variant(name, render)
    sequence = write_replica(root / f"seq_{name}", frames, render.intrinsics)
    config = load_config("synthetic",
                         overrides=[f"dataset.path={sequence}", "dataset.kind=replica", *SETTINGS, *extra_settings])
    run_dir = root / f"run_{name}"
    summary = run_slam(config, run_dir, evaluate=False)
    checkpoint = load_latest_checkpoint(run_dir / "checkpoints")
    estimated = checkpoint.tensors["frames.T_wc"].numpy()  # [N, 4, 4]
    truth = np.stack([f.T_wc for f in frames])
    errors = np.linalg.norm(estimated[:, :3, 3] - truth[:, :3, 3], axis=1)
    return VariantRun(name, frames, bad, summary, json.loads((run_dir / "frames.json").read_text()),
                      checkpoint.tensors, estimated, errors)


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer()


@pytest.fixture(scope="module")
def clean_run(renderer, tmp_path_factory) -> VariantRun:
    return run_variant("clean", renderer, tmp_path_factory.mktemp("extremes"))


def assert_finite_everywhere(run: VariantRun) -> None:
    """No NaN/Inf in the final state (poses, map, optimizer moments, RNG-free numbers) nor in frames.json."""
    flagged_positions = [i for i, f in enumerate(run.frames_json["frames"]) if f["index"] in run.flagged]
    for name, tensor in run.checkpoint_tensors.items():
        if not tensor.is_floating_point():
            continue
        if name == "frames.tracking_loss":  # a frame whose loss could not be computed is flagged
            keep = np.ones(len(tensor), dtype=bool)
            keep[flagged_positions] = False
            tensor = tensor[keep]
        assert bool(np.isfinite(tensor.numpy()).all()), f"{run.name}: non-finite values in {name}"
    for frame in run.frames_json["frames"]:
        loss = frame["tracking_loss"]
        assert (loss is not None and math.isfinite(loss)) or frame["index"] in run.flagged, (run.name, frame)


def test_clean_run_is_the_baseline(clean_run):
    assert clean_run.summary.frames == FRAMES and clean_run.flagged == []
    assert_finite_everywhere(clean_run)
    # 40x30 pixels: one pixel is ~5 cm at the wall; the baseline must at least be pixel-accurate.
    assert clean_run.ate(range(FRAMES)) < 0.06, clean_run.position_errors


EXPECTED_FLAGS = {"black": BAD, "saturated": BAD, "no_depth": BAD, "textureless": BAD,
                  "holes_and_noise": [], "repeated": [], "zoom": []}


@pytest.mark.parametrize("name", ["black", "saturated", "no_depth", "textureless", "holes_and_noise", "repeated",
                                  "zoom"])
def test_extreme_input_run_finishes_flagged_finite_capped_and_recovers(name, renderer, clean_run, tmp_path):
    run = run_variant(name, renderer, tmp_path)
    assert run.summary.frames == len(run.frames)
    assert run.flagged == EXPECTED_FLAGS[name], (name, [f["status"] for f in run.frames_json["frames"]])
    for index in run.flagged:  # a flagged frame is not mapped (no keyframe from it)
        assert run.frames_json["frames"][index]["keyframe_id"] == -1
    assert_finite_everywhere(run)
    counts = [f["gaussians"] for f in run.frames_json["frames"]]
    assert max(counts) <= MAX_GAUSSIANS and run.summary.gaussians <= MAX_GAUSSIANS
    if name == "repeated":
        # at rest (frames 5-24 are one image): no keyframe is added, and the estimate settles: over the
        # last 10 repeats it stays within 3 cm (three fifths of a pixel's footprint at the wall). At 40x30 the
        # settling is chaotic: with mapping.lr_poses anywhere in 0.6-1.5e-4 this spread ranged over 0.32-1.69 cm,
        # with either motion model, and the same code gives 2.45 cm on a CPU with AVX-512 (other rounding in
        # torch's linear algebra); a wandering estimate moves by many centimetres.
        assert run.summary.keyframes == clean_run.summary.keyframes
        settled = run.estimated_T_wc[15:25, :3, 3]
        spread = float(np.linalg.norm(settled - settled.mean(axis=0), axis=1).max())
        assert spread < 0.03, (spread, np.round(run.position_errors[5:25] * 100, 1))
        good = range(len(run.frames))
        baseline = clean_run.ate(range(FRAMES))
    elif name == "zoom":  # another trajectory: held to the clean loop's ATE (same scene, camera and settings)
        good = range(len(run.frames))
        baseline = clean_run.ate(range(FRAMES))
    else:
        good = [i for i in range(FRAMES) if i not in run.bad]
        baseline = clean_run.ate(good)
    ate = run.ate(good)
    assert ate <= ATE_RATIO * baseline, (f"{name}: ATE of the good frames {ate * 100:.2f} cm, clean run "
                                         f"{baseline * 100:.2f} cm; errors (cm) {np.round(run.position_errors * 100, 1)}")


def test_gaussian_cap_binds_from_the_first_keyframe(renderer, clean_run, tmp_path):
    """A cap below what the first keyframe alone would add (~300 Gaussians at 40x30, stride 2)."""
    cap = 120
    run = run_variant("zoom", renderer, tmp_path, f"mapping.max_gaussians={cap}")
    counts = [f["gaussians"] for f in run.frames_json["frames"]]
    assert max(counts) == cap and run.summary.gaussians <= cap, counts
    assert run.summary.frames == len(run.frames)
    assert_finite_everywhere(run)


# Without relocalisation tracking accepted a pose 27 cm off (loss 1.4x its running level; the failure ratio is 5)
# and the error decayed by only ~3-6 cm per frame; pipeline.relocalise aligns such a frame to the previous one.
def test_sudden_30cm_jump_is_flagged_or_tracked_and_tracking_recovers(renderer, clean_run, tmp_path):
    run = run_variant("jump", renderer, tmp_path)
    assert run.summary.frames == FRAMES
    assert_finite_everywhere(run)
    assert max(f["gaussians"] for f in run.frames_json["frames"]) <= MAX_GAUSSIANS
    # the jump frame is either flagged or tracked to within 2 pixels' footprint at the wall (~10 cm)
    assert 6 in run.flagged or run.position_errors[6] < 0.10, run.position_errors
    good = [i for i in range(FRAMES) if i != 6]
    assert run.ate(good) <= ATE_RATIO * clean_run.ate(good), np.round(run.position_errors * 100, 1)


# ----------------------------------------------------------------------------- the table of docs/robustness.md

def print_table() -> None:
    """Run every variant once and print the table of docs/robustness.md (``python tests/test_robustness_extremes.py``)."""
    import tempfile
    import time

    render = Renderer()
    root = Path(tempfile.mkdtemp(prefix="mipslam_extremes_"))
    clean = run_variant("clean", render, root)
    print("| variant | frames | flagged | keyframes | max Gaussians | ATE good (cm) | clean (cm) | ratio | "
          "worst broken-frame error (cm) | s |")
    for name in ["clean", "black", "saturated", "no_depth", "textureless", "holes_and_noise", "repeated", "zoom", "jump"]:
        started = time.perf_counter()
        run = clean if name == "clean" else run_variant(name, render, root)
        if name in ("repeated", "zoom"):
            good, baseline = range(len(run.frames)), clean.ate(range(FRAMES))
        else:
            good = [i for i in range(FRAMES) if i not in run.bad]
            baseline = clean.ate(good)
        worst = max((float(run.position_errors[i]) * 100 for i in run.bad), default=float("nan"))
        print(f"| {name} | {len(run.frames)} | {run.flagged} | {run.summary.keyframes} | "
              f"{max(f['gaussians'] for f in run.frames_json['frames'])} | {run.ate(good) * 100:.2f} | "
              f"{baseline * 100:.2f} | {run.ate(good) / baseline:.2f} | {worst:.1f} | {time.perf_counter() - started:.1f} |")


if __name__ == "__main__":
    print_table()
