"""Pure geometry on tensors: SE(3)/SO(3), the pinhole camera and image resampling."""
from mipslam.geometry.camera import pixel_grid, project, sampling_rate, unproject, unproject_depth
from mipslam.geometry.se3 import (
    hat,
    interpolate_pose,
    nearest_rigid,
    quat_wxyz_to_rotmat,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rigidity_error,
    rotation_angle,
    rotmat_to_quat_wxyz,
    se3_compose,
    se3_exp,
    se3_exp_times,
    se3_exp_times_vjp,
    se3_from_rt,
    se3_inverse,
    se3_log,
    relative_motion,
    so3_exp,
    so3_log,
    transform_points,
    vee,
)
from mipslam.geometry.resample import resize_area

__all__ = [
    "hat", "vee", "so3_exp", "so3_log", "se3_exp", "se3_exp_times", "se3_exp_times_vjp", "se3_log", "se3_inverse",
    "se3_compose", "se3_from_rt", "interpolate_pose",
    "quat_wxyz_to_rotmat", "rotmat_to_quat_wxyz", "quat_xyzw_to_wxyz", "quat_wxyz_to_xyzw",
    "transform_points", "rigidity_error", "rotation_angle", "relative_motion", "nearest_rigid",
    "pixel_grid", "project", "sampling_rate", "unproject", "unproject_depth", "resize_area",
]
