"""mipslam: RGB-D SLAM with an anti-aliased 3D Gaussian map (MipSLAM-style)."""
from __future__ import annotations

__version__ = "0.1.0"
