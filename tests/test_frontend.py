"""The feature front-end of tracking (mipslam/frontend.py): known rigid motions, lost detection, relocalisation."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import data_synth
from mipslam.mapping import MappingOptions
from mipslam.tracking import TrackingOptions
from mipslam.config import FrontendConfig, load_config
from mipslam.datasets import make_sequence
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.io.tum import read_tum_trajectory
from mipslam.mapping import Mapper, MappingView
from mipslam.pipeline import run_slam
from mipslam.tracking import Tracker
from mipslam.frontend import (FeatureOptions, FrameFeatures, Frontend, _projection_gate, estimate_relative_pose,
                              extract_features, guided_matches, match_features, mutual_ratio_pairs)
from mipslam.render import cpu as cpu_backend
from mipslam.geometry.se3 import rotation_angle, se3_exp
from mipslam.types import Frame, Intrinsics

WIDTH, HEIGHT = 160, 120


def _texture(seed: int = 0, size: int = 512) -> np.ndarray:
    """[size, size, 3] float32 in [0, 1]: smoothed noise summed over octaves (blobs of many sizes, no repeats)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size, 3), np.float32)
    for cells, weight in ((4, 0.4), (16, 0.3), (64, 0.2), (256, 0.1)):
        out += weight * cv2.resize(rng.random((cells, cells, 3)).astype(np.float32), (size, size),
                                   interpolation=cv2.INTER_CUBIC)
    return np.clip(out, 0.0, 1.0)


def _plane_view(T_w_c: torch.Tensor, intrinsics: Intrinsics, texture: np.ndarray, index: int) -> Frame:
    """Exact RGB-D view of the textured plane z = 2 + 0.3 x (world metres, texture over x, y in [-2, 2])."""
    K_inv = torch.linalg.inv(intrinsics.matrix(torch.float64))
    v, u = torch.meshgrid(torch.arange(intrinsics.height, dtype=torch.float64),
                          torch.arange(intrinsics.width, dtype=torch.float64), indexing="ij")
    rays_c = torch.stack([u, v, torch.ones_like(u)], -1) @ K_inv.T  # [H, W, 3], z = 1
    R, origin = T_w_c[:3, :3], T_w_c[:3, 3]
    rays_w = rays_c @ R.T
    normal, offset = torch.tensor([-0.3, 0.0, 1.0], dtype=torch.float64), 2.0  # n . p = offset
    t = (offset - origin @ normal) / (rays_w @ normal)  # [H, W] ray parameter = camera z (rays have z_c = 1)
    points = origin + t[..., None] * rays_w
    size = texture.shape[0]
    map_x = ((points[..., 0] + 2.0) / 4.0 * (size - 1)).float().numpy()
    map_y = ((points[..., 1] + 2.0) / 4.0 * (size - 1)).float().numpy()
    color = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return Frame(index, float(index), torch.from_numpy(color), t.float(), intrinsics, T_w_c)


@pytest.fixture(scope="module")
def texture():
    return _texture()


@pytest.fixture(scope="module")
def intrinsics():
    return Intrinsics(fx=200.0, fy=200.0, cx=(WIDTH - 1) / 2, cy=(HEIGHT - 1) / 2, width=WIDTH, height=HEIGHT)


def _errors(T_est: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    E = torch.linalg.inv(T_true) @ T_est
    return float(E[:3, 3].norm()), math.degrees(float(rotation_angle(E[:3, :3])))


IDENTITY = torch.eye(4, dtype=torch.float64)
# A start is good when the render-based refinement can take it from there: within a few pixels of the truth
# (1 degree is 3.5 px at this focal length; 3 cm at 2 m is 3 px). ORB keypoints at 160x120 sit ~0.5 px off.
BASIN_M, BASIN_DEG = 0.03, 1.0
SMALL = (0.03, 0.0, 0.01, 0.0, 0.02, 0.0)  # 3 cm sideways, ~1 degree
LARGE = (0.05, -0.02, 0.1, 0.05, 0.21, -0.04)  # ~12.5 degrees and 11 cm: 45 px, far outside a render basin


@pytest.mark.parametrize("motion", [SMALL, LARGE])
@pytest.mark.parametrize("use_prior", [True, False])
def test_recovers_a_known_rigid_motion(texture, intrinsics, motion, use_prior):
    """With a prior of "no motion" the guided search misses the large motion and the global match finds it."""
    T_ref_cur = se3_exp(torch.tensor(motion, dtype=torch.float64))
    reference = _plane_view(IDENTITY, intrinsics, texture, 0)
    current = _plane_view(T_ref_cur, intrinsics, texture, 1)
    options = FeatureOptions()
    result = estimate_relative_pose(extract_features(reference.color, reference.depth, intrinsics, options),
                                    extract_features(current.color, current.depth, intrinsics, options),
                                    intrinsics, options, IDENTITY if use_prior else None)
    assert result.ok, result.reason
    assert result.inliers >= options.min_inliers
    t_err, r_err = _errors(result.T_rc, T_ref_cur)
    assert t_err < BASIN_M and r_err < BASIN_DEG, (t_err, r_err)


def test_a_pose_far_from_the_prior_is_not_trusted(texture, intrinsics):
    """A prior 1 m away from the truth: the features find the truth, which no hand-held step explains."""
    T_ref_cur = se3_exp(torch.tensor(SMALL, dtype=torch.float64))
    reference = _plane_view(IDENTITY, intrinsics, texture, 0)
    current = _plane_view(T_ref_cur, intrinsics, texture, 1)
    options = FeatureOptions()
    prior = se3_exp(torch.tensor((1.0, 0.0, 0.0, 0.0, 0.0, 0.0), dtype=torch.float64))
    result = estimate_relative_pose(extract_features(reference.color, reference.depth, intrinsics, options),
                                    extract_features(current.color, current.depth, intrinsics, options),
                                    intrinsics, options, prior)
    assert not result.ok and result.reason == "far_from_prior"


def test_unrelated_frames_are_not_trusted(texture, intrinsics):
    """A textured view against a random-noise image: the features must not claim a pose."""
    reference = _plane_view(IDENTITY, intrinsics, texture, 0)
    generator = torch.Generator().manual_seed(0)
    noise = Frame(1, 1.0, torch.rand(HEIGHT, WIDTH, 3, generator=generator),
                  torch.full((HEIGHT, WIDTH), 2.0), intrinsics)
    options = FeatureOptions()
    result = estimate_relative_pose(extract_features(reference.color, reference.depth, intrinsics, options),
                                    extract_features(noise.color, noise.depth, intrinsics, options), intrinsics,
                                    options)
    assert not result.ok
    assert result.reason in ("too_few_matches", "pnp_failed", "too_few_inliers", "low_inlier_ratio")


def test_blank_image_falls_back_to_the_motion_model(texture, intrinsics):
    frontend = Frontend(FrontendConfig())
    reference = _plane_view(IDENTITY, intrinsics, texture, 0)
    blank = Frame(1, 1.0, torch.full((HEIGHT, WIDTH, 3), 0.5), torch.zeros(HEIGHT, WIDTH), intrinsics)
    prediction = se3_exp(torch.tensor(SMALL, dtype=torch.float64))
    start = frontend.start(blank, reference, IDENTITY, prediction)
    assert start.source == "motion_model" and torch.equal(start.T_wc, prediction)
    assert start.reason == "too_few_matches"


def test_start_and_relocalisation_give_world_poses(texture, intrinsics):
    """start() chains the reference's world pose; relocalise() picks the keyframe whose features agree."""
    T_w_ref = se3_exp(torch.tensor((0.2, 0.1, -0.1, 0.0, 0.0, 0.1), dtype=torch.float64))
    T_w_cur = T_w_ref @ se3_exp(torch.tensor(LARGE, dtype=torch.float64))
    reference = _plane_view(T_w_ref, intrinsics, texture, 0)
    current = _plane_view(T_w_cur, intrinsics, texture, 1)
    elsewhere = Frame(2, 2.0, torch.from_numpy(_texture(seed=1)[:HEIGHT, :WIDTH].copy()), torch.full((HEIGHT, WIDTH), 2.0),
                      intrinsics)
    frontend = Frontend(FrontendConfig())
    start = frontend.start(current, reference, T_w_ref, T_w_ref)  # the motion model says "no motion"
    assert start.source == "features" and start.reference_index == 0
    t_err, r_err = _errors(start.T_wc, T_w_cur)
    assert t_err < BASIN_M and r_err < BASIN_DEG
    # keyframes newest first: the newest shows another texture, the older one what the frame sees
    found = frontend.relocalise(current, [(elsewhere, IDENTITY), (reference, T_w_ref)])
    assert found is not None and found.source == "relocalised" and found.reference_index == 0
    t_err, r_err = _errors(found.T_wc, T_w_cur)
    assert t_err < BASIN_M and r_err < BASIN_DEG
    assert frontend.relocalise(current, [(elsewhere, IDENTITY)]) is None  # lost: nothing agrees


def test_start_reads_the_reference_only_where_its_features_are_not_cached(texture, intrinsics):
    """start_from() asks for the reference frame only on a cache miss (reading a cached frame again may resample
    its images), and gives what start() gives with the frame in hand."""
    T_w_cur = se3_exp(torch.tensor(LARGE, dtype=torch.float64))
    reference = _plane_view(IDENTITY, intrinsics, texture, 0)
    current = _plane_view(T_w_cur, intrinsics, texture, 1)
    reads = []

    def read() -> Frame:
        reads.append(reference.index)
        return reference

    frontend = Frontend(FrontendConfig())
    first = frontend.start_from(current, reference.index, read, IDENTITY, IDENTITY)
    assert reads == [0] and first.source == "features"
    again = frontend.start_from(current, reference.index, read, IDENTITY, IDENTITY)
    assert reads == [0] and torch.equal(again.T_wc, first.T_wc)  # cached: not read again
    in_hand = Frontend(FrontendConfig()).start(current, reference, IDENTITY, IDENTITY)
    assert torch.equal(in_hand.T_wc, first.T_wc) and in_hand.inliers == first.inliers


def _same_features(a: FrameFeatures, b: FrameFeatures) -> bool:
    return (np.array_equal(a.keypoints, b.keypoints) and np.array_equal(a.descriptors, b.descriptors)
            and np.array_equal(a.points_c, b.points_c, equal_nan=True) and np.array_equal(a.octaves, b.octaves))


def test_keypoints_detected_ahead_are_the_ones_detected_when_asked(texture, intrinsics):
    """detect_ahead (the read-ahead thread's) gives features() exactly what it computes itself; a frame whose
    colour was replaced since (re-timed) is detected anew, from its own image."""
    frame = _plane_view(IDENTITY, intrinsics, texture, 0)
    expected = extract_features(frame.color, frame.depth, intrinsics, FeatureOptions())
    assert len(expected) > 50
    ahead = Frontend(FrontendConfig())
    ahead.detect_ahead(frame)
    assert frame.index in ahead._ahead
    assert _same_features(ahead.features(frame), expected)
    assert frame.index not in ahead._ahead  # taken, not kept twice

    other = _plane_view(se3_exp(torch.tensor(SMALL, dtype=torch.float64)), intrinsics, texture, 0)
    stale = Frontend(FrontendConfig())
    stale.detect_ahead(frame)  # frame 0 as read ahead ...
    moved = replace(frame, color=other.color)  # ... and as tracked, with another image
    assert _same_features(stale.features(moved),
                          extract_features(other.color, frame.depth, intrinsics, FeatureOptions()))

    bounded = Frontend(FrontendConfig())
    for index in range(Frontend.AHEAD_FRAMES + 3):  # never asked for: the oldest are dropped
        bounded.detect_ahead(replace(frame, index=index))
    assert list(bounded._ahead) == list(range(3, Frontend.AHEAD_FRAMES + 3))


def test_off_means_motion_model(texture, intrinsics):
    frontend = Frontend(FrontendConfig(method="none"))
    frame = _plane_view(IDENTITY, intrinsics, texture, 0)
    assert frontend.start(frame, frame, IDENTITY, IDENTITY).source == "motion_model"
    assert frontend.relocalise(frame, [(frame, IDENTITY)]) is None


def test_matching_is_mutual_and_ratio_tested():
    rng = np.random.default_rng(0)
    train = rng.integers(0, 256, size=(50, 32), dtype=np.uint8)
    query = train[[3, 7, 11]].copy()
    pairs = match_features(query, train, ratio=0.85, max_hamming=64)
    assert pairs.tolist() == [[0, 3], [1, 7], [2, 11]]
    duplicated = np.concatenate([train, train[[3]]])  # two identical best matches: ambiguous, dropped
    assert 0 not in match_features(query, duplicated, ratio=0.85, max_hamming=64)[:, 0].tolist()
    allowed = np.ones((3, 50), bool)
    allowed[1, 7] = False  # the guided search does not let query 1 reach its twin
    candidates = np.argwhere(allowed)
    assert [1, 7] not in match_features(query, train, ratio=0.85, max_hamming=64, candidates=candidates).tolist()


def _masked_brute_force(query, train, ratio, max_hamming, allowed):
    """OpenCV's brute-force matcher with a mask, and the same mutual and ratio tests (the guided search's
    former implementation): the reference of the candidate-pair matcher."""
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    forward = matcher.knnMatch(query, train, k=2, mask=allowed.astype(np.uint8))
    backward = matcher.match(train, query, mask=allowed.T.astype(np.uint8).copy())
    return mutual_ratio_pairs(forward, backward, ratio, max_hamming)


def test_matching_among_candidate_pairs_equals_opencvs_masked_brute_force():
    # descriptors of few distinct bits: many equal distances, so the tie-breaking must match OpenCV's too
    rng = np.random.default_rng(1)
    for _ in range(60):
        m, n = rng.integers(2, 40, size=2)
        bits = int(rng.integers(1, 6))
        query = rng.integers(0, 2 ** bits, size=(m, 32)).astype(np.uint8)
        train = rng.integers(0, 2 ** bits, size=(n, 32)).astype(np.uint8)
        allowed = rng.random((m, n)) < rng.uniform(0.05, 1.0)
        for ratio, max_hamming in ((0.85, 64), (1.0, 30)):
            expected = _masked_brute_force(query, train, ratio, max_hamming, allowed)
            got = match_features(query, train, ratio, max_hamming, candidates=np.argwhere(allowed))
            np.testing.assert_array_equal(got, expected)


def _random_features(rng, count: int, bits: int, width: int, height: int) -> FrameFeatures:
    """Keypoints on a coarse grid (ties in position), descriptors of few distinct bits (ties in distance),
    points with some missing depth (NaN) and some behind a camera that turns away."""
    keypoints = (rng.integers(0, 40, size=(count, 2)) * [width / 40, height / 40]).astype(np.float32)
    descriptors = rng.integers(0, 2 ** bits, size=(count, 32)).astype(np.uint8)
    points = np.concatenate([rng.uniform(-2, 2, size=(count, 2)), rng.uniform(-0.5, 4, size=(count, 1))], axis=1)
    points[rng.random(count) < 0.1] = np.nan
    return FrameFeatures(keypoints, descriptors, points)


@pytest.mark.skipif(not cpu_backend.is_available(), reason="the compiled CPU library is not built")
def test_compiled_guided_matching_equals_the_k_d_tree_reference():
    rng = np.random.default_rng(3)
    intrinsics = Intrinsics(fx=150.0, fy=150.0, cx=80.0, cy=60.0, width=WIDTH, height=HEIGHT)
    library = cpu_backend.load_extension()
    compared = 0
    for trial in range(80):
        reference = _random_features(rng, int(rng.integers(0, 300)), int(rng.integers(1, 6)), WIDTH, HEIGHT)
        current = _random_features(rng, int(rng.integers(0, 300)), int(rng.integers(1, 6)), WIDTH, HEIGHT)
        T_rc = se3_exp(torch.tensor(rng.normal(0, [0.3, 0.3, 0.3, 0.5, 0.5, 0.5]), dtype=torch.float64))
        radius = float(rng.choice([0.0, 0.02, 0.1, 0.5, 2.0]))
        options = FeatureOptions(guided_radius=radius, ratio_test=float(rng.choice([0.85, 1.0])),
                                 max_hamming=int(rng.choice([64, 20])))
        expected = match_features(current.descriptors, reference.descriptors, options.ratio_test,
                                  options.max_hamming, _projection_gate(reference, current, intrinsics, T_rc, radius))
        np.testing.assert_array_equal(guided_matches(reference, current, intrinsics, T_rc, options), expected)
        compared += len(expected)
    assert compared > 100  # the trials found matches to compare
    # projections far outside the image and an exact hit at radius 0
    keypoints = np.array([[10.0, 10.0], [20.0, 5.0]])
    descriptors = np.zeros((2, 32), np.uint8)
    far = np.array([[1e300, -1e300], [10.0, 10.0]])
    np.testing.assert_array_equal(
        library.guided_match(keypoints, far, np.array([0, 1]), 0.0, descriptors, descriptors, 0.85, 64), [[0, 1]])
    with pytest.raises(RuntimeError, match="reference point 5"):
        library.guided_match(keypoints, far, np.array([0, 5]), 1.0, descriptors, descriptors, 0.85, 64)


# ----------------------------------------------------------------------------- with the tracker and the pipeline

@pytest.fixture(scope="module")
def small_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "seq"
    data_synth.generate(out, layout="replica", trajectory="loop", width=64, height=48, frames=6, seed=0, supersample=1)
    return out


def _config(sequence: Path, *extra: str):
    return load_config("synthetic",
                       overrides=[f"dataset.path={sequence}", "mapping.first_frame_iterations=30", "mapping.iterations=8",
                                  "tracking.iterations=10", "keyframes.window_size=3", "run.threads=1", *extra])


def test_best_start_prefers_the_pose_the_map_explains(small_sequence):
    config = _config(small_sequence)
    sequence = make_sequence(config.dataset)
    frame, T_wc = sequence[0], sequence.gt_T_wc[0]
    gmap = GaussianMap.empty()
    optimizer = GaussianOptimizer.from_config(gmap, MappingOptions.from_config(config.mapping))
    mapper = Mapper(MappingOptions.from_config(config.mapping), config.render)
    view = MappingView(0, frame.color, frame.depth, T_wc, torch.zeros(2), frame.intrinsics, optimize_pose=False)
    mapper.densify(gmap, optimizer, view, frame_index=0)
    mapper.optimize(gmap, optimizer, [view], 30, torch.Generator().manual_seed(0))
    gaussians = gmap.activated().detached()
    wrong = T_wc @ se3_exp(torch.tensor([0.04, 0.0, 0.0, 0.0, 0.05, 0.0], dtype=torch.float64))
    for scale in (1.0, 0.5):  # at the full and at a reduced tracking resolution
        tracker = Tracker(replace(TrackingOptions.from_config(config.tracking), resolution_scale=scale), config.render)
        assert tracker.best_start(gaussians, frame, [wrong, T_wc]) == 1
        assert tracker.best_start(gaussians, frame, [T_wc, wrong]) == 0
        assert tracker.best_start(gaussians, frame, [T_wc, T_wc]) == 0  # a tie keeps the preferred (first) start
    result = Tracker(replace(TrackingOptions.from_config(config.tracking), resolution_scale=0.5), config.render).track(gaussians, frame, wrong, None)
    assert result.ok and 0 < result.valid_fraction <= 1


@pytest.mark.parametrize("method", ["orb_pnp", "none"])
def test_a_tiny_run_with_and_without_the_front_end(small_sequence, tmp_path, method):
    summary = run_slam(_config(small_sequence, f"frontend.method={method}", "tracking.resolution_scale=0.5",
                               "run.evaluate_at_end=false", "loop.enabled=false"), tmp_path / "run", evaluate=False)
    assert summary.frames == 6 and summary.flagged == 0 and summary.keyframes >= 1
    poses = read_tum_trajectory(tmp_path / "run" / "traj_est.txt").T_wc
    gt = make_sequence(_config(small_sequence).dataset).gt_T_wc.numpy()
    assert np.isfinite(poses).all()
    assert np.abs(poses[:, :3, 3] - gt[:, :3, 3]).max() < 0.05  # metres: tracking followed the lap
