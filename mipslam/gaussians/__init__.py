"""The map: parameters, activations, add/remove (optimizer state resized with them), densify/prune policy."""
from mipslam.gaussians.initialization import fill_depth_holes, gaussians_from_rgbd
from mipslam.gaussians.model import (
    BUFFER_NAMES,
    PARAMETER_NAMES,
    ActivatedGaussians,
    GaussianMap,
    GaussianParameters,
    color_logit,
    quat_multiply_wxyz,
)
from mipslam.gaussians.optimizer import GaussianOptimizer
from mipslam.gaussians.policy import (
    cap_count_mask,
    cap_pixel_mask,
    densify_pixel_mask,
    distances_to_camera,
    far_from_existing,
    prune_mask,
)

__all__ = [
    "PARAMETER_NAMES", "BUFFER_NAMES", "ActivatedGaussians", "GaussianParameters", "GaussianMap",
    "GaussianOptimizer", "gaussians_from_rgbd", "fill_depth_holes", "far_from_existing", "color_logit", "quat_multiply_wxyz",
    "densify_pixel_mask", "cap_pixel_mask", "prune_mask", "cap_count_mask", "distances_to_camera",
]
