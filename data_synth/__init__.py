"""Procedural indoor RGB-D sequences with exact ground truth, written as Replica or TUM folders.

Public API:

- :func:`generate` writes a folder (see :mod:`data_synth.writer` for the file contract).
- :data:`TRAJECTORIES` and :func:`trajectory_poses` give the named camera paths.
- :func:`load_scene` rebuilds the scene of a generated folder (or its ``synth.json``) and
  :func:`render_view` renders it at any pose and intrinsics (ground truth at other resolutions).
- :func:`make_scene` builds the scene of a seed directly; :func:`read_synth_json`,
  :func:`synth_intrinsics` and :func:`ground_truth_poses` read a folder's description.
"""
from data_synth.io import ground_truth_poses, load_scene, read_synth_json, synth_intrinsics
from data_synth.render import render_view
from data_synth.scene import Scene, make_scene
from data_synth.sensor import SensorOptions
from data_synth.trajectories import TRAJECTORIES, trajectory_poses
from data_synth.writer import DEPTH_SCALE, LAYOUTS, default_intrinsics, generate

__all__ = [
    "generate", "TRAJECTORIES", "LAYOUTS", "DEPTH_SCALE", "trajectory_poses", "load_scene", "render_view",
    "make_scene", "Scene", "SensorOptions", "read_synth_json", "synth_intrinsics", "ground_truth_poses",
    "default_intrinsics",
]
