"""The child process of a peer job: ``PYTHON -m mipslam.bench.peers.worker JOB.json``.

A peer runs in a process of its own (a crash or a hang of a third-party system costs one row, the
bench kills it at its time limit, and GPL code never loads into the bench's process); the
interpreter can be another one than the bench's (``--peer-python``). JOB.json (written by the bench):

    {"peer": "open3d-dense" | "open3d-odometry" | "orbslam3", "config": CONFIG.yaml,
     "preset": null, "overrides": ["dataset.path=...", ...], "out": RUN_DIR, "options": PeerOptions dict}

The worker resolves the config as ``mipslam run`` would (so the dataset section, with ``stride``,
``max_frames`` and the association tolerance, is the same), reads the sequence at the resolution on
disk and writes into RUN_DIR: ``traj_est.txt`` (the peer's poses, TUM), ``traj_gt.txt`` (ground truth
at the frames' timestamps, as a run writes it) and ``peer.json`` (frames, lost frames, timings and
the evaluation protocol the bench must apply). Exit codes: 0 done, 2 a MipslamError (one line on
stderr), 1 anything else.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from mipslam.bench.peers.options import PeerOptions
from mipslam.errors import MipslamError
from mipslam.evaluation.run_eval import TRAJECTORY_ASSOCIATION_S

PEER_FILE = "peer.json"


def run_peer_job(job: dict) -> dict:
    """Run the job described by ``job`` (see the module docstring); -> the content of peer.json."""
    from mipslam.config import load_config
    from mipslam.datasets import make_sequence
    from mipslam.io.run_folder import write_json_atomic
    from mipslam.io.tum import write_tum_trajectory

    peer = job["peer"]
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    options = PeerOptions.from_dict(job.get("options") or {})
    config = load_config(job["config"], preset=job.get("preset"),
                         overrides=[*job.get("overrides", []), "dataset.downscale=1"])
    sequence = make_sequence(config.dataset)
    if peer == "open3d-dense":
        from mipslam.bench.peers.open3d_peers import run_open3d_dense

        result = run_open3d_dense(sequence, options.open3d_dense)
    elif peer == "open3d-odometry":
        from mipslam.bench.peers.open3d_peers import run_open3d_odometry

        result = run_open3d_odometry(sequence, options.open3d_odometry)
    elif peer == "orbslam3":
        from mipslam.bench.peers.orbslam3_peer import run_orbslam3

        result = run_orbslam3(sequence, options.orbslam3, out)
    else:
        raise MipslamError(f"unknown peer '{peer}'")
    write_tum_trajectory(out / "traj_est.txt", result.timestamps, result.T_wc)
    if sequence.gt_T_wc is not None:
        valid = [i for i in range(len(sequence)) if bool(sequence.gt_valid[i])]
        write_tum_trajectory(out / "traj_gt.txt", sequence.timestamps[valid], sequence.gt_T_wc[valid])
    by_index = sequence.timestamp_kind == "index"
    info = {
        "peer": peer, "sequence": str(sequence.root), "timestamp_kind": sequence.timestamp_kind,
        "width": sequence.intrinsics.width, "height": sequence.intrinsics.height,
        "dataset": {"stride": config.dataset.stride, "first_frame": config.dataset.first_frame,
                    "max_frames": config.dataset.max_frames},
        "evaluation": {"alignment": config.eval.alignment,
                       "max_diff_s": 0.5 if by_index else TRAJECTORY_ASSOCIATION_S},
        "options": options.to_dict()[peer.replace("-", "_")],
        **result.summary(),
    }
    write_json_atomic(out / PEER_FILE, info)
    return info


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m mipslam.bench.peers.worker JOB.json", file=sys.stderr)
        return 2
    try:
        job = json.loads(Path(argv[0]).read_text(encoding="utf-8"))
        run_peer_job(job)
    except MipslamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (OSError, json.JSONDecodeError) as exc:
        print(f"error: {argv[0]}: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
