"""File formats at the boundary of mipslam (trajectories, maps, run folders)."""
from mipslam.io.tum import Trajectory, read_tum_trajectory, write_tum_trajectory

__all__ = ["Trajectory", "read_tum_trajectory", "write_tum_trajectory"]
