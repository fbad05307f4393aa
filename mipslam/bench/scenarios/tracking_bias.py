"""Benchmark: how far tracking settles from the truth against a map that mapping fitted to one true view.

A diagnostic for the bias of the tracking optimum (docs/mapping.md). Frame 0
of a data_synth sequence is mapped at its ground-truth pose, as the pipeline maps its first frame (the
preset's ``mapping.first_frame_iterations``). Then:

* coverage: the map rendered at the true poses of frames 0 and 4. Quantiles of the rendered opacity ``A``
  over pixels with valid depth, and two median depth biases over the pixels tracking uses (``A`` at least
  ``tracking.opacity_threshold``): the raw depth ``D = sum T a z`` against the sensor depth ``d``
  (``D / d - 1``, what mapping's depth term drives to 0), and the opacity-normalised depth
  (``(D / A) / d - 1``, where the Gaussians actually sit). When ``A < 1`` the raw term pushes the
  Gaussians outward by about ``1 / A - 1``.
* tracking: frames 2, 4, ..., 10 tracked from their true poses with the preset's tracker, and the
  estimate's error expressed in the true camera frame (OpenCV axes: x right, y down, z forward):
  translation in mm, rotation vector in mrad, and the iterations used.

* pure motions (``tracking_bias.pure_motions=true``): frame 0's camera turned about its own y (yaw) or x (pitch) axis, or
  moved along its x axis, rendered by data_synth's ray caster (8-bit colour, as the sequence stores it), and
  tracked from the true pose. A pure rotation's image does not depend on depth, so its error separates the
  map's lateral placement from its depth.

An unbiased tracker against a faithful map would stay at the truth; the printed error is the bias a SLAM
run starts from on every frame.

Run: ``mipslam bench --scenario tracking_bias --out bench_out/bias [--set tracking_bias.sequence=SEQUENCE]
[--set tracking_bias.preset=fast] [--set KEY=VALUE ...]``, SEQUENCE a data_synth folder; by default a data_synth
loop of 240 frames at 160x120 (``mipslam synth --out seq160 --format replica --trajectory loop --width 160
--height 120 --frames 240``) is generated into OUT/sequence. OUT/bench.md has the tables, OUT/bench.json the numbers.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import logging  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import data_synth  # noqa: E402
from mipslam.bench.record import write_benchmark  # noqa: E402
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult  # noqa: E402
from mipslam.bench.scenarios.checkout import CONFIGS, optional_path, parameters, synth_sequence  # noqa: E402
from mipslam.config import Config, load_config  # noqa: E402
from mipslam.datasets import make_sequence  # noqa: E402
from mipslam.gaussians import ActivatedGaussians  # noqa: E402
from mipslam.geometry import se3_exp, se3_inverse, so3_log  # noqa: E402
from mipslam.mapping import MappingOptions, MappingView  # noqa: E402
from mipslam.pipeline import Stages, resolve_device  # noqa: E402
from mipslam.rendering import render_view  # noqa: E402
from mipslam.state import SLAMState  # noqa: E402
from mipslam.types import Frame  # noqa: E402

log = logging.getLogger(__name__)

COVERAGE_FRAMES = (0, 4)
TRACKED_FRAMES = (2, 4, 6, 8, 10)
OPACITY_QUANTILES = (0.05, 0.25, 0.5, 0.75)
# (name, camera-frame axis 0/1/2 = x/y/z, rotation rad or None, translation m or None)
PURE_MOTIONS = (("yaw -25 mrad", 1, -0.025, None), ("yaw -50 mrad", 1, -0.05, None), ("yaw -100 mrad", 1, -0.1, None),
                ("yaw +50 mrad", 1, 0.05, None), ("pitch +50 mrad", 0, 0.05, None),
                ("x -40 mm", 0, None, -0.04), ("x -100 mm", 0, None, -0.1))


@dataclass(frozen=True)
class Options:
    sequence: str = ""  # a data_synth folder ("": generate a loop of synth_frames frames into OUT/sequence)
    synth_frames: int = 240
    synth_size: str = "160x120"  # WIDTHxHEIGHT of the generated loop
    preset: str = "fast"
    threads: int = 1
    pure_motions: bool = False  # also track pure rotations and translations of frame 0's camera
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE


SMOKE = dict(synth_frames=11, synth_size="40x30", pure_motions=True,
             config_overrides=("mapping.first_frame_iterations=20", "tracking.iterations=6"))


def camera_motion(axis: int, angle: float | None, offset: float | None) -> torch.Tensor:
    """A rotation by ``angle`` rad about, or a translation by ``offset`` m along, camera axis ``axis``.  -> [4, 4]"""
    xi = torch.zeros(6, dtype=torch.float64)  # [rho, phi]
    if offset is not None:
        xi[axis] = offset
    if angle is not None:
        xi[3 + axis] = angle
    return se3_exp(xi)


def pose_error(T_wc_true: torch.Tensor, T_wc_est: torch.Tensor) -> tuple[list[float], list[float]]:
    """Error of an estimate in the true camera frame.  T_wc [4, 4] -> (translation mm [3], rotation mrad [3]):
    the translation and rotation vector of ``T_true^-1 T_est``."""
    E = se3_inverse(T_wc_true.to(torch.float64)) @ T_wc_est.to(torch.float64)
    return (E[:3, 3] * 1000).tolist(), (so3_log(E[:3, :3]) * 1000).tolist()


@torch.no_grad()
def coverage(gaussians: ActivatedGaussians, frame: Frame, T_wc: torch.Tensor, config: Config) -> dict:
    """Rendered opacity quantiles and median depth biases of the map seen from ``T_wc`` (see the module text).

    T_wc [4, 4] float64 camera-to-world; ``frame.depth`` [H, W] metres (0 = no measurement). The biases are
    fractions (0.01 = 1 %), medians over the pixels tracking uses; ``fraction_used`` is their share of all pixels.
    """
    out = render_view(gaussians, se3_inverse(T_wc), frame.intrinsics, config.render)
    valid = frame.depth > 0
    used = valid & (out.alpha >= config.tracking.opacity_threshold)
    quantiles = torch.quantile(out.alpha[valid], torch.tensor(OPACITY_QUANTILES, dtype=out.alpha.dtype,
                                                              device=out.alpha.device))
    raw = out.depth[used] / frame.depth[used] - 1
    normalised = out.depth[used] / out.alpha[used] / frame.depth[used] - 1
    return {"opacity_quantiles": dict(zip(map(str, OPACITY_QUANTILES), quantiles.tolist())),
            "fraction_used": float(used.float().mean()),
            "raw_depth_bias": float(raw.median()), "normalised_depth_bias": float(normalised.median())}


def run(options: Options, out_dir: Path) -> ScenarioResult:
    sequence_dir = optional_path(options.sequence)
    if sequence_dir is None:
        sequence_dir = synth_sequence(out_dir, options.synth_size, options.synth_frames, supersample=4)
    torch.set_num_threads(options.threads)
    overrides = [f"dataset.path={sequence_dir.resolve()}", f"dataset.max_frames={max(TRACKED_FRAMES) + 1}",
                 *options.config_overrides]
    config = load_config(CONFIGS / "synthetic.yaml", preset=options.preset, overrides=overrides)
    sequence = make_sequence(config.dataset)
    device = resolve_device(config.run.device)
    state = SLAMState.initial(MappingOptions.from_config(config.mapping), config.run.seed, device)
    stages = Stages.build(config, sequence, device)
    T_wc_true = sequence.gt_T_wc

    first = stages.frames[0]
    view = MappingView(0, first.color, first.depth, T_wc_true[0], torch.zeros(2, device=device), first.intrinsics,
                       False)
    stages.mapper.map_keyframe(state.gaussian_map, state.optimizer, [view],
                               iterations=config.mapping.first_frame_iterations, generator=state.generator,
                               frame_index=0)
    gaussians = state.gaussian_map.activated().detached()

    lines = [f"Map of frame 0 at its true pose ({len(state.gaussian_map)} Gaussians), seen from frames "
             f"{', '.join(map(str, COVERAGE_FRAMES))}:", "",
             f"| frame | opacity q{'/'.join(str(int(100 * p)) for p in OPACITY_QUANTILES)} | pixels used | "
             "median D/d - 1 | median (D/A)/d - 1 |", "|---:|---|---:|---:|---:|"]
    results: dict = {"preset": options.preset, "overrides": list(options.config_overrides), "gaussians": len(state.gaussian_map),
                     "coverage": {}, "tracking": []}
    for k in COVERAGE_FRAMES:
        c = coverage(gaussians, stages.frames[k], T_wc_true[k], config)
        results["coverage"][k] = c
        q = " / ".join(f"{v:.4f}" for v in c["opacity_quantiles"].values())
        lines.append(f"| {k} | {q} | {c['fraction_used']:.3f} | {100 * c['raw_depth_bias']:+.2f} % | "
                     f"{100 * c['normalised_depth_bias']:+.2f} % |")
    lines += ["", "| frame | moved [mm] | error t x / y / z [mm] | rotation x / y / z [mrad] | iterations |",
              "|---:|---:|---|---|---:|"]
    for k in TRACKED_FRAMES:
        tracked = stages.tracker.track(gaussians, stages.frames[k], T_wc_true[k], None)
        translation, rotation = pose_error(T_wc_true[k], tracked.T_wc)
        moved = float((T_wc_true[k][:3, 3] - T_wc_true[0][:3, 3]).norm()) * 1000
        results["tracking"].append({"frame": k, "moved_mm": moved, "translation_mm": translation,
                                    "rotation_mrad": rotation, "iterations": tracked.iterations})
        lines.append(f"| {k} | {moved:.0f} | {translation[0]:+.2f} / {translation[1]:+.2f} / {translation[2]:+.2f} | "
                     f"{rotation[0]:+.2f} / {rotation[1]:+.2f} / {rotation[2]:+.2f} | {tracked.iterations} |")
    if options.pure_motions:
        scene = data_synth.load_scene(sequence_dir)
        supersample = int(data_synth.read_synth_json(sequence_dir)["render"]["supersample"])  # as the frames
        results["pure_motions"] = []
        lines += ["", "| pure motion of frame 0's camera | error t x / y / z [mm] | rotation x / y / z [mrad] | "
                      "iterations |", "|---|---|---|---:|"]
        for name, axis, angle, offset in PURE_MOTIONS:
            T_wc = T_wc_true[0].to(torch.float64) @ camera_motion(axis, angle, offset)
            color, depth = data_synth.render_view(scene, T_wc, first.intrinsics, supersample=supersample)
            color = np.round(color * 255.0) / 255.0  # stored as 8-bit, like the sequence's frames
            frame = Frame(first.index, first.timestamp, torch.from_numpy(color).float().to(device),
                          torch.from_numpy(depth).float().to(device), first.intrinsics, T_wc)
            tracked = stages.tracker.track(gaussians, frame, T_wc, None)
            translation, rotation = pose_error(T_wc, tracked.T_wc)
            results["pure_motions"].append({"motion": name, "translation_mm": translation, "rotation_mrad": rotation,
                                            "iterations": tracked.iterations})
            lines.append(f"| {name} | {translation[0]:+.2f} / {translation[1]:+.2f} / {translation[2]:+.2f} | "
                         f"{rotation[0]:+.2f} / {rotation[1]:+.2f} / {rotation[2]:+.2f} | {tracked.iterations} |")
    report = "\n".join(lines)
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), results, threads=options.threads,
                            markdown=report)
    return ScenarioResult(files, report)
