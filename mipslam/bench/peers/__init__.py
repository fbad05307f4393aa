"""Peers: established RGB-D systems run by ``mipslam bench --peers`` on the same frames, evaluated alike.

* ``open3d`` = ``open3d-dense`` (Open3D's dense RGB-D SLAM, ``open3d.t.pipelines.slam``: frame-to-model
  ICP + TSDF, on the CPU) and ``open3d-odometry`` (Open3D's frame-to-frame RGB-D odometry);
* ``orbslam3``: ORB-SLAM3 RGB-D through the optional package ``pyorbslam3`` (GPL-3.0,
  ``pip install 'mipslam[peers]'``), with a DBoW2 vocabulary trained by :mod:`~mipslam.bench.peers.vocabulary`.

Each peer job is a child process (:mod:`~mipslam.bench.peers.worker`) that writes ``traj_est.txt``,
``traj_gt.txt`` and ``peer.json``; :func:`evaluate_peer_run` evaluates it here with mipslam's own
trajectory evaluation (same association tolerance, same alignment as a ``mipslam run`` of the
same config). A lost frame is a frame the peer gave no pose.
"""
from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

from mipslam.bench.peers.options import PeerOptions, parse_peer_sets
from mipslam.errors import ConfigError, EvaluationError, MipslamError

__all__ = ["PEERS", "PEER_GROUPS", "PeerOptions", "check_peers_available", "default_peer_repeats",
           "evaluate_peer_run", "parse_peer_sets", "parse_peers"]

# name -> (what it is, default repeats: Open3D once (its runs differ only in the 4th digit), ORB-SLAM3 three times)
PEERS: dict[str, tuple[str, int]] = {
    "open3d-dense": ("Open3D dense RGB-D SLAM (t.pipelines.slam, frame-to-model ICP + TSDF, CPU)", 1),
    "open3d-odometry": ("Open3D RGB-D odometry, frame to frame (hybrid photometric + geometric term)", 1),
    "orbslam3": ("ORB-SLAM3 RGB-D (pyorbslam3, GPL-3.0; not deterministic: repeated)", 3),
}
PEER_GROUPS: dict[str, tuple[str, ...]] = {"open3d": ("open3d-dense", "open3d-odometry")}
EVAL_FILE = "bench_eval.json"


def parse_peers(text: str | None) -> tuple[str, ...]:
    """``"open3d,orbslam3"`` -> ``("open3d-dense", "open3d-odometry", "orbslam3")`` (groups expanded, order kept)."""
    if not text:
        return ()
    out: list[str] = []
    for name in (n.strip().lower() for n in text.split(",")):
        if not name:
            continue
        members = PEER_GROUPS.get(name, (name,))
        for member in members:
            if member not in PEERS:
                known = ", ".join([*PEER_GROUPS, *PEERS])
                raise ConfigError(f"--peers '{text}': unknown peer '{name}'; choose from {known}")
            if member not in out:
                out.append(member)
    return tuple(out)


def default_peer_repeats(peer: str) -> int:
    return PEERS[peer][1]


def check_peers_available(peers: tuple[str, ...], options: PeerOptions, python: str) -> None:
    """ConfigError before anything runs when a requested peer cannot run: no vocabulary for ORB-SLAM3, or
    (with the bench's own interpreter) a package missing."""
    if "orbslam3" in peers:
        vocabulary = options.orbslam3.vocabulary
        if not vocabulary:
            raise ConfigError("--peers orbslam3 needs an ORB vocabulary: give --vocab FILE (train one with "
                              "'mipslam bench --train-vocab FILE --vocab-images DIR...')")
        if not Path(vocabulary).expanduser().is_file():
            raise ConfigError(f"--vocab {vocabulary}: file not found")
        if python == sys.executable and importlib.util.find_spec("pyorbslam3") is None:
            raise ConfigError("--peers orbslam3 needs the optional package pyorbslam3 (GPL-3.0): pip install "
                              "'mipslam[peers]', or give --peer-python an interpreter that has it")
    if any(p.startswith("open3d") for p in peers) and python == sys.executable \
            and importlib.util.find_spec("open3d") is None:
        raise ConfigError("--peers open3d needs the package open3d (a mipslam dependency); reinstall mipslam")


def evaluate_peer_run(run_dir: Path) -> dict[str, Any]:
    """ATE/RPE of a finished peer run folder with mipslam's evaluation; writes ``RUN/bench_eval.json``.

    Protocol from peer.json (the config's ``eval.alignment`` and association tolerance, 0.5 for frame
    numbers), as ``mipslam eval`` applies them to a run: ground truth at the frames' timestamps against
    the peer's poses, nearest timestamp, Umeyama alignment. -> dict with the metrics and the peer summary.
    """
    from mipslam.evaluation.trajectory import evaluate_trajectory
    from mipslam.io.run_folder import write_json_atomic
    from mipslam.io.tum import read_tum_trajectory

    run_dir = Path(run_dir)
    try:
        info = json.loads((run_dir / "peer.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise MipslamError(f"{run_dir / 'peer.json'}: missing or unreadable ({exc})") from None
    if not info.get("poses"):
        detail = "; ORB-SLAM3 never initialised (too few ORB features?)" if info.get("initialised") is False else ""
        raise EvaluationError(f"{info.get('peer')} gave no pose: all {info.get('frames')} frames lost{detail}")
    gt_path = run_dir / "traj_gt.txt"
    if not gt_path.is_file():
        raise EvaluationError(f"{gt_path}: the sequence has no ground truth; nothing to compare with")
    gt = read_tum_trajectory(gt_path, allow_duplicate_timestamps=True)
    est = read_tum_trajectory(run_dir / "traj_est.txt")
    protocol = info["evaluation"]
    metrics = evaluate_trajectory(gt, est, alignment=protocol["alignment"], association="timestamp",
                                  max_diff=protocol["max_diff_s"]).to_dict()
    data = {"peer": info, "trajectory": metrics,
            "lost_frames": {"count": info["lost_frames"], "positions": info["lost_positions"],
                            "note": "frames the peer gave no pose; they are not in the ATE"}}
    write_json_atomic(run_dir / EVAL_FILE, data)
    return data
