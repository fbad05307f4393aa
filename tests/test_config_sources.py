"""One source of truth per setting: the config sections take the stage options' defaults and checks, and the
constants that change results are config keys that the stages read."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from mipslam.config import LoopConfig, MappingConfig, RenderConfig, TrackingConfig, load_config
from mipslam.errors import ConfigError
from mipslam.loop.descriptors import CandidateOptions
from mipslam.loop.from_config import CANDIDATE_KEYS, PGO_KEYS, REGISTRATION_KEYS, registration_options
from mipslam.loop.registration import RegistrationOptions
from mipslam.loop.solver import PGOOptions
from mipslam.render import RenderOptions
from mipslam.rendering import render_options
from mipslam.state import FrameRecord, SLAMState
from mipslam.tracking import TrackingResult


def test_render_config_defaults_and_checks_are_the_renderers():
    defaults = RenderOptions()
    for option, value in render_options(RenderConfig()).items():
        expected = None if option == "filter_3d_scale" else getattr(defaults, option)  # the 3D filter is off
        assert value == expected, option
    # the renderer's rule, reported under the config key
    with pytest.raises(ConfigError, match=r"'render.eaa_k_sigma': must be positive"):
        load_config("synthetic", overrides=["render.eaa_k_sigma=0"])
    with pytest.raises(ConfigError, match=r"'render.eaa_max_nodes': must be an integer >= 1"):
        RenderConfig(eaa_max_nodes=0)


def test_loop_config_maps_every_option_it_mirrors_and_takes_their_defaults():
    loop_keys = {f.name for f in dataclasses.fields(LoopConfig)}
    for table, options in ((PGO_KEYS, PGOOptions), (CANDIDATE_KEYS, CandidateOptions),
                           (REGISTRATION_KEYS, RegistrationOptions)):
        option_fields = {f.name for f in dataclasses.fields(options)}
        assert set(table) <= loop_keys and set(table.values()) <= option_fields, table
    config = LoopConfig()
    assert config.num_eigenvectors == PGOOptions.num_eigenvectors
    assert config.full_iterations == PGOOptions.full_iterations
    assert config.min_keyframe_gap == CandidateOptions.min_gap
    assert config.icp_voxel_m == RegistrationOptions.voxel_sizes[-1]
    assert registration_options(config).voxel_sizes == RegistrationOptions.voxel_sizes


def _result(loss: float) -> TrackingResult:
    return TrackingResult(torch.eye(4, dtype=torch.float64), torch.zeros(2), loss, 1, 1.0, True, "ok")


def test_the_running_loss_momentum_is_the_tracking_configs():
    state = SLAMState.initial(MappingConfig(), 0, torch.device("cpu"))
    for momentum, expected in ((TrackingConfig().running_loss_momentum, 0.9 * 1.0 + 0.1 * 2.0), (0.5, 1.5)):
        state.running_loss = 1.0
        state.frames.append(FrameRecord(0, 0.0, torch.eye(4), torch.zeros(2), "ok", 2.0, 1, -1, -1, torch.eye(4)))
        state.end_frame(_result(2.0), momentum)
        assert state.running_loss == pytest.approx(expected)


@pytest.mark.parametrize("key,value", [("coarse_share", 1.0), ("relocalise_max_m", 0.0),
                                       ("running_loss_momentum", 1.0)])
def test_tracking_constants_are_checked(key, value):
    with pytest.raises(ConfigError, match=f"tracking.{key.split('_max')[0]}"):
        TrackingConfig(**{key: value})
