"""Map the ``loop:`` config section to the option objects of the pure loop components.

The only module of ``mipslam.loop`` that knows the config; everything else takes options. Each mapped
setting is defined once: the config's defaults are the options' (``mipslam.config.LoopConfig``), and the
tables below say which config key sets which option.
"""
from __future__ import annotations

from dataclasses import replace

from mipslam.config import LoopConfig
from mipslam.loop.descriptors import CandidateOptions
from mipslam.loop.registration import RegistrationOptions
from mipslam.loop.solver import PGOOptions

# loop config key -> option field
PGO_KEYS = {"spectral_edge_weighting": "spectral_edge_weighting", "low_frequency_correction": "low_frequency_correction",
            "num_eigenvectors": "num_eigenvectors", "full_iterations": "full_iterations"}
CANDIDATE_KEYS = {"min_keyframe_gap": "min_gap"}
REGISTRATION_KEYS = {"registration": "method", "icp_fitness_threshold": "fitness_threshold",
                     "icp_rmse_threshold": "rmse_threshold", "icp_pixel_stride": "pixel_stride",
                     "registration_depth_noise_power": "direct_depth_noise_power"}


def _settings(config: LoopConfig, keys: dict[str, str]) -> dict:
    return {option: getattr(config, key) for key, option in keys.items()}


def pgo_options(config: LoopConfig, base: PGOOptions = PGOOptions()) -> PGOOptions:
    """SA-PGO switches from the config; the remaining solver settings come from ``base``."""
    return replace(base, **_settings(config, PGO_KEYS))


def candidate_options(config: LoopConfig, base: CandidateOptions = CandidateOptions()) -> CandidateOptions:
    """Loop-candidate rules: the minimum keyframe gap comes from the config."""
    return replace(base, **_settings(config, CANDIDATE_KEYS))


def registration_options(config: LoopConfig, base: RegistrationOptions = RegistrationOptions()) -> RegistrationOptions:
    """Verification method, acceptance thresholds, voxel sizes (finest and 2x), pixel stride and the direct
    alignment's depth units (z^p) from the config."""
    return replace(base, **_settings(config, REGISTRATION_KEYS), voxel_sizes=(2 * config.icp_voxel_m, config.icp_voxel_m))
