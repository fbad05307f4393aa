"""How accurate loop edges are, against how accurate their information says they are (docs/tracking.md,
"Loop closure").

Frame pairs (i, i + gap) of a sequence with ground truth are registered by the loop stage's verification
(the loop stage's registration options, from the config) from their ground-truth relative pose, perturbed by a
random motion of ``perturb_m`` / ``perturb_deg`` standard deviation per axis. For the pairs it accepts:
the translation (cm) and rotation (deg) of the error ``inv(T_gt) T_ij`` (median and 90th percentile),
against the standard deviations the edge's information claims (``sqrt`` of the diagonal of its inverse,
the norm over the three axes). A ratio well above 1 means the pose graph trusts the edges more than they
deserve.

    mipslam bench --scenario loop_edges --set dataset.path=../shared/data/tum_fr1_rpy_300

``loop_edges.gt_time_shift_s=S`` adds S seconds to a TUM folder's ground-truth stamps before they are
interpolated at the frames' times: an error that shrinks at some shift belongs to the ground truth's timing.
``loop_edges.config`` is the sequence's config, a YAML file or a built-in's name (default: the built-in config of
the ``dataset.path`` folder's kind, as ``mipslam bench SEQUENCE`` picks it, else ``tum``); config keys
(``--set loop.KEY=...``) override it; ``loop_edges.synth_frames=N`` runs on a data_synth loop of N frames generated
into OUT instead.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import CONFIGS, parameters, sequence_config, synth_sequence
from mipslam.config import Config, load_config
from mipslam.datasets import make_sequence
from mipslam.errors import MipslamError
from mipslam.evaluation.loop_edges import fitness_bins
from mipslam.geometry.se3 import rotation_angle, se3_exp, se3_inverse
from mipslam.loop.closer import LoopOptions
from mipslam.loop.registration import register_rgbd_pair

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Options:
    config: str = ""  # the sequence's config (its dataset and loop sections); "" = the built-in <kind> of dataset.path
    gaps: tuple[int, ...] = (30, 60, 120)  # frames between the two frames of a pair
    first_every: int = 9  # a pair starts at every this many-th frame
    perturb_m: float = 0.02  # standard deviation per axis of the start's translation error (m)
    perturb_deg: float = 1.5  # ... and of its rotation error (deg)
    seed: int = 0  # of the perturbations
    synth_frames: int = 0  # > 0: a data_synth loop of this many frames (OUT/sequence) instead of the config's
    synth_size: str = "160x120"  # WIDTHxHEIGHT of that sequence
    # seconds added to the ground truth's timestamps before it is interpolated at the frames' times (TUM layout):
    # an error that shrinks at some shift is the ground truth's timing, not the registration's
    gt_time_shift_s: float = 0.0
    # the accepted pairs again by their overlap (the verification's fitness: the fraction of source points with a
    # correspondence), in bins between these edges: how the error depends on how much of the view the pair shares
    fitness_bins: tuple[float, ...] = (0.3, 0.5, 0.75, 1.0)
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE, e.g. dataset.path=...


SMOKE = dict(config=str(CONFIGS / "synthetic.yaml"), gaps=(2,), first_every=3, synth_frames=8, synth_size="96x72")


def _error(T_est: torch.Tensor, T_gt: torch.Tensor) -> tuple[float, float]:
    """Translation (cm) and rotation (deg) of ``inv(T_gt) T_est``, both [4, 4] float64."""
    E = se3_inverse(T_gt) @ T_est
    return float(E[:3, 3].norm()) * 100, math.degrees(float(rotation_angle(E[:3, :3])))


def _claimed(information: torch.Tensor) -> tuple[float, float]:
    """Norm of the per-axis standard deviations (cm, deg) of an information [6, 6] in the order [rho, phi]."""
    variances = torch.linalg.pinv(information.to(torch.float64)).diagonal().clamp_min(0)
    return float(variances[:3].sum().sqrt()) * 100, math.degrees(float(variances[3:].sum().sqrt()))


def _stats(values: list[float]) -> tuple[float, float]:
    return (float(np.median(values)), float(np.percentile(values, 90))) if values else (math.nan, math.nan)


def _by_fitness(edges: tuple[float, ...], fitness: list[float], errors_t: list[float], errors_r: list[float],
                claimed_t: list[float]) -> list[dict]:
    """Median errors (cm, deg) and claimed translation (cm) of the accepted pairs whose fitness lies in each bin
    [edges[b], edges[b + 1]) (the last bin closed)."""
    return [{"fitness": [low, high], "accepted": len(pick),
             "error_t_cm_median": _stats([errors_t[n] for n in pick])[0],
             "error_r_deg_median": _stats([errors_r[n] for n in pick])[0],
             "claimed_t_cm_median": _stats([claimed_t[n] for n in pick])[0]}
            for (low, high), pick in zip(zip(edges[:-1], edges[1:]), fitness_bins(fitness, edges))]


def _shifted_ground_truth(config: Config, frame_times: np.ndarray, shift_s: float) -> tuple[torch.Tensor, np.ndarray]:
    """The TUM folder's groundtruth.txt with ``shift_s`` added to its stamps, at ``frame_times`` [N] (seconds).
    -> (T_wc [N, 4, 4] float64, valid [N] bool)"""
    from mipslam.datasets.tum import poses_at_times, read_ground_truth

    path = Path(config.dataset.path).expanduser() / "groundtruth.txt"
    if config.dataset.kind != "tum" or not path.is_file():
        raise MipslamError(f"loop_edges.gt_time_shift_s shifts the groundtruth.txt of a sequence read as TUM "
                           f"(dataset.kind=tum); {config.dataset.path} is read as {config.dataset.kind}"
                           f"{'' if path.is_file() else ' and has no groundtruth.txt'}: leave the shift at 0 there")
    gt_times, gt_poses = read_ground_truth(path)
    return poses_at_times(gt_times + shift_s, gt_poses, np.asarray(frame_times, dtype=np.float64),
                          config.dataset.association_tolerance_s)


def run(options: Options, out_dir: Path) -> ScenarioResult:
    if not options.gaps or min(options.gaps) < 1 or options.first_every < 1:
        raise MipslamError("loop_edges.gaps must be positive frame counts and loop_edges.first_every >= 1")
    if len(options.fitness_bins) < 2 or list(options.fitness_bins) != sorted(set(options.fitness_bins)):
        raise MipslamError("loop_edges.fitness_bins must be at least two increasing fitness values, e.g. 0.3,0.5,0.75,1")
    overrides = list(options.config_overrides)
    if options.synth_frames > 0:
        overrides.insert(0, f"dataset.path={synth_sequence(out_dir, options.synth_size, options.synth_frames)}")
    config = load_config(sequence_config(options.config, overrides), overrides=overrides)
    sequence = make_sequence(config.dataset)
    if sequence.gt_T_wc is None:
        raise MipslamError(f"{config.dataset.path}: the sequence has no ground truth; loop_edges needs it")
    gt_T_wc, gt_valid = sequence.gt_T_wc, sequence.gt_valid
    if options.gt_time_shift_s != 0:
        gt_T_wc, gt_valid = _shifted_ground_truth(config, sequence.timestamps, options.gt_time_shift_s)
    registration = LoopOptions.from_config(config.loop, depth_noise_power=config.dataset.depth_noise_power)\
        .registration_options()
    generator = torch.Generator().manual_seed(options.seed)
    sigma = torch.tensor([options.perturb_m] * 3 + [math.radians(options.perturb_deg)] * 3, dtype=torch.float64)
    pairs = [(i, i + gap) for i in range(0, len(sequence), options.first_every) for gap in options.gaps
             if i + gap < len(sequence) and bool(gt_valid[i]) and bool(gt_valid[i + gap])]
    errors_t, errors_r, claimed_t, claimed_r, fitness = [], [], [], [], []
    for i, j in pairs:
        frame_i, frame_j = sequence[i], sequence[j]
        T_gt = se3_inverse(gt_T_wc[i].to(torch.float64)) @ gt_T_wc[j].to(torch.float64)
        start = se3_exp(torch.randn(6, generator=generator, dtype=torch.float64) * sigma) @ T_gt
        result = register_rgbd_pair(frame_i.color, frame_i.depth, frame_j.color, frame_j.depth, frame_i.intrinsics,
                                    start, registration)
        if not result.accepted:
            continue
        t, r = _error(result.T_ij.to(torch.float64), T_gt)
        s_t, s_r = _claimed(result.information)
        errors_t.append(t), errors_r.append(r), claimed_t.append(s_t), claimed_r.append(s_r)
        fitness.append(result.fitness)
    err_t, err_r, cl_t, cl_r = _stats(errors_t), _stats(errors_r), _stats(claimed_t), _stats(claimed_r)
    results = {"pairs": len(pairs), "accepted": len(errors_t),
               "error_t_cm_median": err_t[0], "error_t_cm_p90": err_t[1],
               "error_r_deg_median": err_r[0], "error_r_deg_p90": err_r[1],
               "claimed_t_cm_median": cl_t[0], "claimed_r_deg_median": cl_r[0],
               "ratio_t": err_t[0] / cl_t[0] if cl_t[0] > 0 else math.nan,
               "ratio_r": err_r[0] / cl_r[0] if cl_r[0] > 0 else math.nan}
    results["by_fitness"] = _by_fitness(options.fitness_bins, fitness, errors_t, errors_r, claimed_t)
    log.info("loop edges: %s", results)
    report = "\n".join([
        f"**{config.dataset.path}**, registration `{registration.method}`, gaps {list(options.gaps)} frames, "
        f"start perturbed by {options.perturb_m * 100:g} cm / {options.perturb_deg:g} deg per axis", "",
        "| pairs (accepted) | error t median / p90 [cm] | claimed t [cm] | error r median / p90 [deg] | "
        "claimed r [deg] | error / claimed (t, r) |",
        "|---|---:|---:|---:|---:|---:|",
        f"| {len(pairs)} ({len(errors_t)}) | {err_t[0]:.2f} / {err_t[1]:.2f} | {cl_t[0]:.3f} | "
        f"{err_r[0]:.2f} / {err_r[1]:.2f} | {cl_r[0]:.3f} | {results['ratio_t']:.1f}, {results['ratio_r']:.1f} |",
        "", "By overlap (the verification's fitness):", "",
        "| fitness | accepted | error t median [cm] | error r median [deg] | claimed t [cm] |", "|---|---:|---:|---:|---:|",
        *(f"| {row['fitness'][0]:g}-{row['fitness'][1]:g} | {row['accepted']} | {row['error_t_cm_median']:.2f} | "
          f"{row['error_r_deg_median']:.2f} | {row['claimed_t_cm_median']:.3f} |" for row in results["by_fitness"])])
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), results, threads=torch.get_num_threads(),
                            markdown=report)
    return ScenarioResult(files, report)
