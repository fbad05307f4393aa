"""Basin of convergence, measured: ATE and lost frames against the frame stride, mipslam beside its peers.

A thin scenario over ``mipslam bench``: for each sequence it runs

    mipslam bench SEQUENCE --presets PRESETS --sweep dataset.stride=1,2,4,8 --peers PEERS [--vocab FILE] ...

so every stride is a setting of mipslam and of every peer. Larger strides mean larger motion between
consecutive frames: where a system's ATE jumps or its lost frames climb, the motion has left its basin
of convergence. Each bench writes OUT/bench_<sequence>/bench.md (the sweep table: ATE cm and lost frames per
stride), bench_sweep.png (ATE and lost frames against the stride, a line per system), bench.png and
bench.json (machine, every run).

Sequences: TUM fr1_rpy (``--tum``, default ../shared/data/tum_fr1_rpy_300; skipped with a message
when absent) and a data_synth loop generated into OUT/synth_loop (``--synth-frames`` frames at
``--synth-size``).

    .venv/bin/python benchmarks/bench_basin.py --out bench_out/basin --vocab orbvoc.txt
    .venv/bin/python benchmarks/bench_basin.py --out bench_out/basin_small --max-frames 60 --peers open3d
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
STRIDES = "1,2,4,8"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="a new folder; one bench folder per sequence in it")
    parser.add_argument("--presets", default="fast", help="mipslam presets (default fast)")
    parser.add_argument("--peers", default="open3d,orbslam3", help="peers (default open3d,orbslam3; '' for none)")
    parser.add_argument("--vocab", type=Path, default=None, help="ORB vocabulary for orbslam3 (mipslam bench --train-vocab)")
    parser.add_argument("--strides", default=STRIDES, help=f"dataset.stride values (default {STRIDES})")
    parser.add_argument("--max-frames", type=int, default=None, help="frames per run after the stride (default all)")
    parser.add_argument("--repeat", type=int, default=1, help="runs per mipslam setting (default 1)")
    parser.add_argument("--tum", type=Path, default=REPO.parent / "shared" / "data" / "tum_fr1_rpy_300")
    parser.add_argument("--synth-frames", type=int, default=120)
    parser.add_argument("--synth-size", default="320x240", help="WIDTHxHEIGHT of the data_synth loop")
    parser.add_argument("--bench-arg", dest="bench_args", action="append", default=[],
                        help="passed on to every mipslam bench (repeatable), e.g. --bench-arg=--threads=1")
    args = parser.parse_args(argv)
    if args.out.exists() and any(args.out.iterdir()):
        parser.error(f"{args.out} exists and is not empty; choose another --out")
    import data_synth
    from mipslam.cli import main as mipslam_main

    width, height = (int(v) for v in args.synth_size.lower().split("x"))
    synth = args.out / "synth_loop"
    data_synth.generate(synth, layout="replica", trajectory="loop", width=width, height=height,
                        frames=args.synth_frames, seed=0, supersample=2)
    sequences = [synth]
    if args.tum.is_dir():
        sequences.insert(0, args.tum)
    else:
        print(f"{args.tum} not found: TUM part skipped", file=sys.stderr)
    code = 0
    for sequence in sequences:
        bench = ["bench", str(sequence), "--presets", args.presets, "--sweep", f"dataset.stride={args.strides}",
                 "--repeat", str(args.repeat), "--out", str(args.out / f"bench_{sequence.name}"), *args.bench_args]
        if args.peers:
            bench += ["--peers", args.peers]
        if args.vocab is not None:
            bench += ["--vocab", str(args.vocab)]
        if args.max_frames is not None:
            bench += ["--max-frames", str(args.max_frames)]
        code = max(code, mipslam_main(bench))
    return code


if __name__ == "__main__":
    sys.exit(main())
