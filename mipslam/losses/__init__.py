"""Losses of tracking and mapping (docs/design.md, "Losses"): pure functions on tensors, any device.

- :mod:`mipslam.losses.photometric`: colour + depth L1 with masks and the affine exposure model.
- :mod:`mipslam.losses.regularizers`: isotropy and scale-cap regularisers on activated scales.
- :mod:`mipslam.losses.frequency`: local frequency-domain (Hann-windowed patch FFT) perceptual loss.
"""
from mipslam.losses.frequency import frequency_loss, hann_window_2d, image_to_patches
from mipslam.losses.photometric import (
    AffineExposure,
    RGBDLoss,
    RGBDMasks,
    apply_affine_exposure,
    image_gradient_magnitude,
    image_gradient_mask,
    masked_l1,
    normalised_depth,
    rgbd_l1_loss,
    rgbd_masks,
)
from mipslam.losses.regularizers import isotropy_loss, scale_cap_loss

__all__ = [
    "AffineExposure",
    "RGBDLoss",
    "RGBDMasks",
    "apply_affine_exposure",
    "frequency_loss",
    "hann_window_2d",
    "image_gradient_magnitude",
    "image_gradient_mask",
    "image_to_patches",
    "isotropy_loss",
    "masked_l1",
    "normalised_depth",
    "rgbd_l1_loss",
    "rgbd_masks",
    "scale_cap_loss",
]
