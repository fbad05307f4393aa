"""Loop closure and spectral-aware pose-graph optimisation (SA-PGO).

Pure components (no config, no pipeline state): the pose graph and its LM solver
(:mod:`.pose_graph`, :mod:`.solver`), spectral weighting and low-frequency bases
(:mod:`.spectral`), loop-candidate descriptors (:mod:`.descriptors`) and RGB-D geometric
verification with Open3D (:mod:`.registration`, imported lazily: Open3D loads on first use).
:mod:`.closer` is the loop-closure stage of the frame loop (``LoopCloser``, built from its ``LoopOptions``);
import it from there: the package imports only its pure components, which the data layer uses.
docs/pgo.md defines the method and reports the benchmarks.
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
    "PoseGraph", "edge_residuals", "edge_jacobians",
    "PGOOptions", "PGOResult", "optimize_pose_graph", "optimize_pose_graph_window",
    "spectral_coherence_weights", "low_frequency_basis",
    "DescriptorOptions", "CandidateOptions", "LoopCandidate", "global_descriptor", "descriptor_similarity",
    "select_loop_candidates",
    "RegistrationOptions", "RegistrationResult", "register_rgbd_pair", "register_point_clouds",
]

