"""Settings of the peer systems (frozen, one dataclass per peer) and ``--peer-set PEER.KEY=VALUE``.

The defaults are those of each system's own example for TUM RGB-D at 640x480, so the peers run as
their authors run them: Open3D's ``t_reconstruction_system/default_config.yml`` (dense SLAM) and
``reconstruction_system`` odometry options, ORB-SLAM3's ``Examples/RGB-D/TUM1.yaml``.
"""
from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field
from typing import Any

import yaml

from mipslam.errors import ConfigError

__all__ = ["Open3DDenseOptions", "Open3DOdometryOptions", "ORBSLAM3Options", "PeerOptions", "parse_peer_sets"]


@dataclass(frozen=True)
class Open3DDenseOptions:
    """``open3d.t.pipelines.slam``: frame-to-model point-to-plane ICP against the raycast TSDF, then integration."""

    voxel_size_m: float = 3.0 / 512  # TSDF voxel edge (Open3D example: 3 m / 512)
    block_resolution: int = 16  # voxels per block edge
    block_count: int = 40000  # hash-map capacity in blocks
    depth_min_m: float = 0.1  # raycast near limit
    depth_max_m: float = 3.0  # depth beyond this is ignored (tracking, integration, raycast)
    distance_threshold_m: float = 0.07  # ICP correspondence distance (odometry_distance_thr)
    trunc_voxel_multiplier: float = 8.0  # TSDF truncation = this * voxel size
    device: str = "CPU:0"  # Open3D device; the bench compares CPU systems


@dataclass(frozen=True)
class Open3DOdometryOptions:
    """``open3d.pipelines.odometry.compute_rgbd_odometry`` frame to frame (hybrid photometric + geometric term)."""

    depth_max_m: float = 3.0  # OdometryOption.depth_max
    depth_diff_max_m: float = 0.07  # OdometryOption.depth_diff_max: correspondence depth gate


@dataclass(frozen=True)
class ORBSLAM3Options:
    """ORB-SLAM3 RGB-D (``pyorbslam3``); ORB extractor and depth thresholds as in TUM1.yaml.

    vocabulary: a DBoW2 text vocabulary (``mipslam bench --train-vocab``); required to run.
    realtime: pace the frames to the recording's timestamps, as ORB-SLAM3's TUM example does (its
    local-mapping thread gets the time a live camera would give it). Index-timestamped sequences
    (Replica) are never paced.
    """

    vocabulary: str = ""
    realtime: bool = True
    features: int = 1000  # ORBextractor.nFeatures
    scale_factor: float = 1.2  # ORBextractor.scaleFactor
    levels: int = 8  # ORBextractor.nLevels
    fast_threshold: int = 20  # ORBextractor.iniThFAST
    fast_threshold_min: int = 7  # ORBextractor.minThFAST
    baseline_m: float = 0.07732  # Stereo.b: the virtual baseline of the RGB-D camera (Kinect, TUM1.yaml)
    close_depth_baselines: float = 40.0  # Stereo.ThDepth: points closer than this many baselines are "close"
    fps: int = 30  # Camera.fps (an integer; ORB-SLAM3 uses it for keyframe and relocalisation timing)


@dataclass(frozen=True)
class PeerOptions:
    """Options of every peer; the bench passes the whole object to the peer worker (JSON)."""

    open3d_dense: Open3DDenseOptions = field(default_factory=Open3DDenseOptions)
    open3d_odometry: Open3DOdometryOptions = field(default_factory=Open3DOdometryOptions)
    orbslam3: ORBSLAM3Options = field(default_factory=ORBSLAM3Options)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PeerOptions":
        sections = {f.name: f.type for f in dataclasses.fields(cls)}
        kinds = {"open3d_dense": Open3DDenseOptions, "open3d_odometry": Open3DOdometryOptions,
                 "orbslam3": ORBSLAM3Options}
        values = {}
        for name in sections:
            section = data.get(name, {})
            known = {f.name for f in dataclasses.fields(kinds[name])}
            unknown = sorted(set(section) - known)
            if unknown:
                raise ConfigError(f"peer options: unknown key '{name}.{unknown[0]}'")
            values[name] = kinds[name](**section)
        return cls(**values)


def parse_peer_sets(items: list[str] | tuple[str, ...], base: PeerOptions | None = None) -> PeerOptions:
    """Apply ``--peer-set SECTION.KEY=VALUE`` (YAML value) to ``base``; ConfigError names a bad key or value.

    Sections: open3d_dense, open3d_odometry, orbslam3 (e.g. ``orbslam3.realtime=false``).
    """
    options = base or PeerOptions()
    data = options.to_dict()
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--peer-set '{item}': expected SECTION.KEY=VALUE, e.g. orbslam3.realtime=false")
        key, text = (s.strip() for s in item.split("=", 1))
        every = [f"{s}.{k}" for s, values in data.items() for k in values]
        if key not in every:
            near = difflib.get_close_matches(key, every, n=1, cutoff=0.5)
            hint = f"; did you mean '{near[0]}'?" if near else f"; known keys: {', '.join(every)}"
            raise ConfigError(f"--peer-set {key}: unknown peer option{hint}")
        section, name = key.split(".", 1)
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            value = text
        current = data[section][name]
        if isinstance(current, bool):
            ok = isinstance(value, bool)
        elif isinstance(current, float):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        elif isinstance(current, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = True
            value = "" if value is None else str(value)
        if not ok:
            raise ConfigError(f"--peer-set {key}={text}: expected a {type(current).__name__}")
        data[section][name] = value
    return PeerOptions.from_dict(data)
