"""One source of truth per setting: the config holds the user-facing keys, each stage's options dataclass beside
its code holds its constants, and one adapter (``section_options``) builds the options from the section."""
from __future__ import annotations

import ast
import math
import dataclasses
from dataclasses import replace
from pathlib import Path

import pytest
import torch

import mipslam.config as config_module
from mipslam.config import INTERNAL_KEYS, Config, LoopConfig, RenderConfig, TrackingConfig, load_config
from mipslam.errors import ConfigError
from mipslam.keyframes import KeyframeOptions
from mipslam.loop.closer import LoopOptions
from mipslam.loop.descriptors import CandidateOptions
from mipslam.loop.registration import RegistrationOptions
from mipslam.loop.solver import PGOOptions
from mipslam.mapping import MappingOptions
from mipslam.render import RenderOptions
from mipslam.rendering import render_options
from mipslam.state import FrameRecord, SLAMState
from mipslam.tracking import TrackingOptions, TrackingResult


def test_the_config_imports_no_stage():
    tree = ast.parse(Path(config_module.__file__).read_text(encoding="utf-8"))
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert {name for name in imported if name and name.startswith("mipslam")} == {"mipslam.errors"}


@pytest.mark.parametrize("options_type,section", [(TrackingOptions, "tracking"), (MappingOptions, "mapping"),
                                                  (KeyframeOptions, "keyframes"), (LoopOptions, "loop")])
def test_every_key_of_a_section_reaches_its_stage_with_the_sections_default(options_type, section):
    config = Config()
    options = options_type.from_config(getattr(config, section))
    for f in dataclasses.fields(getattr(config, section)):
        assert getattr(options, f.name) == getattr(getattr(config, section), f.name), f.name
        assert getattr(options_type, f.name) == f.default, f.name  # the options' default is the config's


def test_the_sensors_depth_noise_reaches_tracking_and_loop_verification():
    config = load_config("tum")
    assert config.dataset.depth_noise_power == 2
    tracking = TrackingOptions.from_config(config.tracking, depth_noise_power=config.dataset.depth_noise_power)
    loop = LoopOptions.from_config(config.loop, depth_noise_power=config.dataset.depth_noise_power)
    assert tracking.direct_depth_noise_power == 2 and loop.registration_options().direct_depth_noise_power == 2
    assert loop.registration_options().fitness_threshold == 0.75


def test_render_options_are_the_renderers_constants():
    defaults = RenderOptions()
    for option, value in render_options(RenderConfig()).items():
        expected = None if option == "filter_3d_scale" else getattr(defaults, option)  # the 3D filter is off
        assert value == expected, option
    with pytest.raises(ConfigError, match=r"'render.eaa_max_nodes': must be an integer >= 1"):
        RenderConfig(eaa_max_nodes=0)


def test_loop_options_make_the_components_options():
    options = LoopOptions()
    assert options.num_eigenvectors == PGOOptions.num_eigenvectors
    assert options.full_iterations == PGOOptions.full_iterations
    assert options.min_keyframe_gap == CandidateOptions.min_gap
    assert options.registration_options().voxel_sizes == RegistrationOptions.voxel_sizes
    assert options.registration_options().method == "direct"
    assert options.registration_options().fitness_threshold == LoopConfig.fitness_threshold
    pgo = options.pgo_options()
    assert pgo.spectral_edge_weighting and pgo.low_frequency_correction


@pytest.mark.parametrize("section", sorted(INTERNAL_KEYS))
def test_an_internal_constant_set_as_a_config_key_is_a_clear_error(section):
    module, _, names = INTERNAL_KEYS[section]
    for name in names:
        with pytest.raises(ConfigError, match=rf"'{section}\.{name}': no longer a config key: it is an internal "
                                              rf"constant of {module.split(' ')[0]}"):
            load_config("synthetic", overrides=[f"{section}.{name}=1"])


@pytest.mark.parametrize("old,new", [("loop.icp_fitness_threshold=0.5", "loop.fitness_threshold"),
                                     ("tracking.direct_depth_noise_power=2", "dataset.depth_noise_power"),
                                     ("loop.registration_depth_noise_power=2", "dataset.depth_noise_power")])
def test_a_renamed_key_names_the_new_one(old, new):
    with pytest.raises(ConfigError, match=rf"'{old.split('=')[0]}'.*'{new}'"):
        load_config("synthetic", overrides=[old])


def _result(loss: float) -> TrackingResult:
    return TrackingResult(torch.eye(4, dtype=torch.float64), torch.zeros(2), loss, 1, 1.0, True, "ok")


def test_the_running_loss_momentum_is_trackings():
    state = SLAMState.initial(MappingOptions(), 0, torch.device("cpu"))
    for momentum, expected in ((TrackingOptions().running_loss_momentum, 0.9 * 1.0 + 0.1 * 2.0), (0.5, 1.5)):
        state.running_loss = 1.0
        state.frames.append(FrameRecord(0, 0.0, torch.eye(4), torch.zeros(2), "ok", 2.0, 1, -1, -1, torch.eye(4)))
        state.end_frame(_result(2.0), momentum)
        assert state.running_loss == pytest.approx(expected)


def test_the_running_depth_disagreement_follows_tracked_frames_and_survives_a_checkpoint():
    # ok and disagreement-flagged frames move the level (a scene whose depth agrees less everywhere must not stay
    # flagged for good); other failures and unmeasured frames do not
    state = SLAMState.initial(MappingOptions(), 0, torch.device("cpu"))
    momentum = TrackingOptions().running_loss_momentum
    for status, disagreement, expected in (("ok", 0.02, 0.02), ("depth_disagreement", 0.12, 0.9 * 0.02 + 0.1 * 0.12),
                                           ("loss_jump", 0.5, 0.03), ("ok", math.nan, 0.03)):
        state.frames.append(FrameRecord(0, 0.0, torch.eye(4), torch.zeros(2), status, 1.0, 1, -1, -1, torch.eye(4)))
        state.end_frame(replace(_result(1.0), status=status, ok=status == "ok", depth_disagreement=disagreement),
                        momentum)
        assert state.running_disagreement == pytest.approx(expected)
    tensors, metadata = state.to_checkpoint()
    back = SLAMState.from_checkpoint(tensors, metadata, MappingOptions(), torch.device("cpu"))
    assert back.running_disagreement == state.running_disagreement
    del metadata["running_disagreement"]  # a checkpoint written before the level existed
    assert SLAMState.from_checkpoint(tensors, metadata, MappingOptions(), torch.device("cpu")).running_disagreement is None


@pytest.mark.parametrize("key,value", [("iterations", 0), ("resolution_scale", 0.0),
                                       ("relocalise_loss_ratio", 0.5)])
def test_tracking_keys_are_checked(key, value):
    with pytest.raises(ConfigError, match=f"tracking.{key}"):
        TrackingConfig(**{key: value})
