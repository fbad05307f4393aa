"""Value objects passed between stages (frozen dataclasses; tensors carry shape comments)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, OpenCV convention.

    Pixel (u, v) is the unit square [u-0.5, u+0.5] x [v-0.5, v+0.5]; its centre has integer
    coordinates, so the image spans [-0.5, width-0.5] horizontally.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the same camera rendered at ``factor`` times the resolution.

        With pixel centres at integers the image edge sits at -0.5, so a continuous coordinate
        x maps to ``factor * (x + 0.5) - 0.5``; focal lengths scale by ``factor``. Width and
        height are rounded to the nearest integer (at least 1).
        """
        if not factor > 0:
            raise ValueError(f"scale factor must be positive, got {factor}")
        return Intrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=factor * (self.cx + 0.5) - 0.5,
            cy=factor * (self.cy + 0.5) - 0.5,
            width=max(1, int(round(self.width * factor))),
            height=max(1, int(round(self.height * factor))),
        )

    def with_size(self, width: int, height: int) -> "Intrinsics":
        return replace(self, width=int(width), height=int(height))

    def matrix(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
        """K as a tensor.  # [3, 3]"""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device
        )


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame as a dataset delivers it (CPU tensors).

    color: float32 in [0, 1]                        # [H, W, 3]
    depth: float32 metres, 0 = no measurement       # [H, W]
    T_wc_gt: camera-to-world ground truth or None   # [4, 4] float64
    depth_time_offset: seconds from the colour image's instant to the depth image's (unsynchronised
        streams, e.g. a Kinect's; 0 where the dataset does not say)
    """

    index: int
    timestamp: float
    color: torch.Tensor
    depth: torch.Tensor
    intrinsics: Intrinsics
    T_wc_gt: torch.Tensor | None = None
    depth_time_offset: float = 0.0
