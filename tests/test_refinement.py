"""The map refinement over keyframes (mipslam/refinement.py): its loss, passes, poses and resumable state."""
from __future__ import annotations

import pytest
import torch

from mipslam.mapping import MappingOptions
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.geometry import se3_inverse
from mipslam.refinement import MEANS_LR_FINAL_RATIO, KeyframeImage, KeyframeRefiner, RefineKeyframe, RefineOptions
from tiny_runs import map_of_first_frame


@pytest.fixture(scope="module")
def two_view_problem(tmp_path_factory):
    """A map of frame 0 (40 mapping steps) and two keyframes (frames 0 and 1 at their true poses) of a 40x30 loop."""
    import data_synth

    seq = tmp_path_factory.mktemp("refine") / "seq"
    data_synth.generate(seq, layout="replica", trajectory="loop", width=40, height=30, frames=3, seed=0, supersample=2)
    config, sequence, gmap, _, _ = map_of_first_frame(seq, 40)
    frames = [sequence[i] for i in range(2)]
    keyframes = [RefineKeyframe(i, i, sequence.gt_T_wc[i].to(torch.float64), torch.zeros(2)) for i in range(2)]
    return config, gmap.detached(), frames, keyframes


def _refiner(problem, options: RefineOptions, seed: int = 0, decay_steps: int = 0) -> KeyframeRefiner:
    config, params, frames, keyframes = problem
    gmap = GaussianMap(params)
    optimizer = GaussianOptimizer.from_config(gmap, MappingOptions.from_config(config.mapping))

    def load(keyframe: RefineKeyframe) -> KeyframeImage:
        frame = frames[keyframe.frame_index]
        return KeyframeImage(frame.color, frame.depth, frame.intrinsics)

    return KeyframeRefiner(gmap, optimizer, keyframes, load, options, config.render, torch.Generator().manual_seed(seed),
                           decay_steps=decay_steps)


def _mean_loss(refiner: KeyframeRefiner) -> float:
    """The refinement loss over every keyframe at its current pose, without stepping."""
    total = 0.0
    with torch.no_grad():
        for position in range(len(refiner.keyframes)):
            image, masks = refiner._image(position)
            T_cw = se3_inverse(refiner.T_wc(position)).to(refiner.map.dtype)
            total += float(refiner.loss(image, masks, T_cw, refiner.keyframes[position].exposure, None))
    return total / len(refiner.keyframes)


def test_steps_lower_the_loss_and_visit_every_keyframe_once_per_pass(two_view_problem):
    refiner = _refiner(two_view_problem, RefineOptions())
    before = _mean_loss(refiner)
    visited = []
    image_of = refiner._image
    refiner._image = lambda position: (visited.append(position), image_of(position))[1]
    for _ in range(6):
        assert refiner.step() is not None
    refiner._image = image_of
    after = _mean_loss(refiner)
    assert refiner.steps == 6
    assert all(sorted(visited[k:k + 2]) == [0, 1] for k in (0, 2, 4)), visited
    assert after < before, (before, after)
    assert refiner.refined_poses() == []  # lr_poses 0: the poses stay


def test_each_term_of_the_loss_counts(two_view_problem):
    refiner = _refiner(two_view_problem, RefineOptions(ssim_weight=0.0, alpha_color=1.0))
    image, masks = refiner._image(0)
    T_cw = se3_inverse(refiner.T_wc(0)).to(refiner.map.dtype)
    exposure = torch.zeros(2)
    with torch.no_grad():
        color_only = float(refiner.loss(image, masks, T_cw, exposure, None))
        refiner.options = RefineOptions(ssim_weight=0.5, alpha_color=1.0)
        with_ssim = float(refiner.loss(image, masks, T_cw, exposure, None))
        refiner.options = RefineOptions(ssim_weight=0.0, alpha_color=0.0)
        depth_only = float(refiner.loss(image, masks, T_cw, exposure, None))
    assert with_ssim > color_only > 0 and depth_only > 0 and depth_only != color_only


def test_pose_refinement_moves_later_keyframes_and_never_the_first(two_view_problem):
    config, params, frames, keyframes = two_view_problem
    shifted = list(keyframes)
    T_wc = keyframes[1].T_wc.clone()
    T_wc[0, 3] += 0.01  # a 1 cm error in the second keyframe's pose
    shifted[1] = RefineKeyframe(1, 1, T_wc, keyframes[1].exposure)
    refiner = _refiner((config, params, frames, shifted), RefineOptions(lr_poses=1e-3))
    refiner.run(20)
    moved = dict(refiner.refined_poses())
    assert 0 not in moved and 1 in moved
    torch.testing.assert_close(refiner.T_wc(0), keyframes[0].T_wc, atol=1e-12, rtol=0)
    assert float((moved[1][:3, 3] - T_wc[:3, 3]).norm()) > 1e-4


def test_state_dict_resumes_exactly(two_view_problem):
    options = RefineOptions(lr_poses=1e-4)
    straight = _refiner(two_view_problem, options)
    straight.run(7)

    first = _refiner(two_view_problem, options)
    first.run(3)
    saved_map = first.map.detached()
    saved_optimizer = first.optimizer.state_dict()
    saved_refiner = first.state_dict()
    saved_generator = first.generator.get_state()

    config = two_view_problem[0]
    resumed = _refiner((config, saved_map, *two_view_problem[2:]), options)
    resumed.optimizer.load_state_dict(saved_optimizer)
    resumed.load_state_dict(saved_refiner)
    resumed.generator.set_state(saved_generator)
    resumed.run(4)
    assert resumed.steps == straight.steps == 7
    torch.testing.assert_close(resumed.map.means, straight.map.means, atol=0, rtol=0)
    torch.testing.assert_close(resumed.map.colors_raw, straight.map.colors_raw, atol=0, rtol=0)
    torch.testing.assert_close(resumed.T_wc(1), straight.T_wc(1), atol=0, rtol=0)


def test_a_state_for_other_keyframes_is_refused(two_view_problem):
    refiner = _refiner(two_view_problem, RefineOptions())
    state = refiner.state_dict()
    state["pose_deltas"] = torch.zeros(5, 6)
    with pytest.raises(ValueError, match="5 keyframe poses"):
        refiner.load_state_dict(state)


def test_options_out_of_range_are_refused():
    with pytest.raises(ValueError, match="alpha_color"):
        RefineOptions(alpha_color=1.5)


def test_a_refinement_of_known_length_decays_the_means_rate_and_restores_it(two_view_problem):
    refiner = _refiner(two_view_problem, RefineOptions(), decay_steps=5)
    base = refiner.optimizer.learning_rates
    rates = []
    for _ in range(5):
        assert refiner.step() is not None
        rates.append(refiner.optimizer.learning_rates["means"])
    # exponential from the optimizer's rate to MEANS_LR_FINAL_RATIO of it; the other groups keep theirs
    assert rates[0] == pytest.approx(base["means"]) and rates[-1] == pytest.approx(base["means"] * MEANS_LR_FINAL_RATIO)
    assert all(later < earlier for earlier, later in zip(rates, rates[1:]))
    assert {k: v for k, v in refiner.optimizer.learning_rates.items() if k != "means"} == \
        {k: v for k, v in base.items() if k != "means"}
    refiner.restore_learning_rates()
    assert refiner.optimizer.learning_rates == base
