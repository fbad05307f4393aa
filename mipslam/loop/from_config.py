"""Map the ``loop:`` config section to the option objects of the pure loop components.

The only module of ``mipslam.loop`` that knows the config; everything else takes options.
"""
from __future__ import annotations

from dataclasses import replace

from mipslam.config import LoopConfig
from mipslam.loop.descriptors import CandidateOptions
from mipslam.loop.registration import RegistrationOptions
from mipslam.loop.solver import PGOOptions


def pgo_options(config: LoopConfig, base: PGOOptions = PGOOptions()) -> PGOOptions:
    """SA-PGO switches from the config; the remaining solver settings come from ``base``."""
    return replace(
        base,
        spectral_edge_weighting=config.spectral_edge_weighting,
        low_frequency_correction=config.low_frequency_correction,
        num_eigenvectors=config.num_eigenvectors,
        full_iterations=config.full_iterations,
    )


def candidate_options(config: LoopConfig, base: CandidateOptions = CandidateOptions()) -> CandidateOptions:
    """Loop-candidate rules: the minimum keyframe gap comes from the config."""
    return replace(base, min_gap=config.min_keyframe_gap)


def registration_options(config: LoopConfig, base: RegistrationOptions = RegistrationOptions()) -> RegistrationOptions:
    """Verification method, acceptance thresholds, voxel sizes (finest and 2x) and pixel stride from the config."""
    return replace(base, method=config.registration, fitness_threshold=config.icp_fitness_threshold,
                   rmse_threshold=config.icp_rmse_threshold, voxel_sizes=(2 * config.icp_voxel_m, config.icp_voxel_m),
                   pixel_stride=config.icp_pixel_stride)
