"""mipslam: RGB-D SLAM with an anti-aliased 3D Gaussian map (MipSLAM-style)."""
from __future__ import annotations

import os

__version__ = "0.1.0"

# OpenMP threads that finish a parallel region spin (busy-wait) for the others by default. When another
# process shares a core, the spinning thread keeps the descheduled one waiting. The renderer's two threads
# were then 3x slower than one: 40 + 74 ms against 13.6 + 20.5 ms per pose-only call, 8.7k Gaussians,
# 160x120, with one other job on the machine. Waiting passively costs microseconds per region. This only
# takes effect when mipslam is imported before torch starts its OpenMP runtime, and it never overrides a
# value the user has set.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
