"""mipslam: RGB-D SLAM with an anti-aliased 3D Gaussian map (MipSLAM-style)."""
from __future__ import annotations

import os

__version__ = "0.1.0"

# OpenMP threads that finish a parallel region spin (busy-wait) for the next one, by default for about 300k
# iterations. When another process shares a core, the spinning thread keeps the descheduled one waiting: two
# 2-thread runs on 2 cores ran at 0.45 frames/s each (fr1_rpy, fast, 60 frames). Waiting passively instead
# (threads sleep at once) makes every one of a frame's thousands of small parallel regions wake its threads:
# alone, the same run ran at 3.1 frames/s against 4.8 with the default spin. A short spin keeps most of both:
# 5000 iterations gave 4.4 frames/s alone and 2.4 each for the pair (passive: 3.0). This only takes effect
# when mipslam is imported before torch starts its OpenMP runtime (libgomp, as torch's and the CPU renderer's),
# and never overrides a value the user has set (OMP_WAIT_POLICY=ACTIVE for a machine of one's own).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("GOMP_SPINCOUNT", "5000")
