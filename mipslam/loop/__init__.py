"""Loop closure and spectral-aware pose-graph optimisation (SA-PGO).

Pure components (no config, no pipeline state): the pose graph and its LM solver
(:mod:`.pose_graph`, :mod:`.solver`), spectral weighting and low-frequency bases
(:mod:`.spectral`), loop-candidate descriptors (:mod:`.descriptors`) and RGB-D geometric
verification with Open3D (:mod:`.registration`, imported lazily: Open3D loads on first use).
:mod:`.from_config` maps the ``loop:`` config section to their option objects. :mod:`.closer` is
the loop-closure stage of the frame loop (:class:`LoopCloser`, built from the ``loop:`` section,
and the :class:`LoopState` that goes into the SLAM state).
docs/pgo.md defines the method and reports the benchmarks. The stage's names are imported on first
use, so that the config (which takes the options' defaults) can import the pure components.
"""
from mipslam.loop.descriptors import (
    CandidateOptions,
    DescriptorOptions,
    LoopCandidate,
    descriptor_similarity,
    global_descriptor,
    select_loop_candidates,
)
from mipslam.loop.pose_graph import PoseGraph, edge_jacobians, edge_residuals
from mipslam.loop.registration import RegistrationOptions, RegistrationResult, register_point_clouds, register_rgbd_pair
from mipslam.loop.solver import PGOOptions, PGOResult, optimize_pose_graph, optimize_pose_graph_window
from mipslam.loop.spectral import low_frequency_basis, spectral_coherence_weights

__all__ = [
    "LoopCloser", "LoopState", "LoopStep", "KeyframeView",
    "PoseGraph", "edge_residuals", "edge_jacobians",
    "PGOOptions", "PGOResult", "optimize_pose_graph", "optimize_pose_graph_window",
    "spectral_coherence_weights", "low_frequency_basis",
    "DescriptorOptions", "CandidateOptions", "LoopCandidate", "global_descriptor", "descriptor_similarity",
    "select_loop_candidates",
    "RegistrationOptions", "RegistrationResult", "register_rgbd_pair", "register_point_clouds",
]


_STAGE_NAMES = ("LoopCloser", "LoopState", "LoopStep", "KeyframeView")


def __getattr__(name: str):
    if name in _STAGE_NAMES:
        from mipslam.loop import closer

        return getattr(closer, name)
    raise AttributeError(f"module 'mipslam.loop' has no attribute {name!r}")
