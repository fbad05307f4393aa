"""Command-line interface: the only place that parses arguments, configures logging and turns
errors into exit codes (0 success, 1 unexpected failure, 2 usage/config/data error, 130 Ctrl-C).

    mipslam run CONFIG [--preset P] [--set k=v]... [--out DIR [--overwrite]]
                [--viewer [--viewer-host H] [--viewer-port P]]
    mipslam run --resume RUN_DIR [CONFIG] [--set k=v]...
    mipslam refine RUN_DIR [--minutes M] [--iterations N] [--resolution mapping|native] [--restart]
                   [--eval-every-minutes E] [--no-eval]
    mipslam view RUN_DIR [--host H] [--port P] [--follow] [--map-only] [--slam-map] [--screenshot PNG [--size WxH]]
    mipslam eval RUN_DIR [--frames split|all|keyframes|non_keyframes] [--resolution native|mapping]
                 [--scales 0.25,1] [--modes point,eaa] [--every K]
                 | --gt GT.txt --est EST.txt
    mipslam export RUN_DIR --mesh mesh.ply [--voxel-size M] [--overwrite]
    mipslam synth --out DIR --format replica|tum --trajectory loop ... [--overwrite]
    mipslam config CONFIG [--preset P] [--set k=v]...  |  mipslam config --list
    mipslam bench SEQUENCE_OR_CONFIG [--presets fast,balanced,accurate] [--sweep KEY=V1,V2]... [--repeat 3]
                  [--threads 2] [--max-frames N] [--set k=v]... [--out DIR] [--jobs N | --ray [ADDRESS]]
                  [--peers open3d,orbslam3 [--vocab FILE] [--peers-only] [--peer-repeat N] [--peer-set k=v]...]
    mipslam bench --train-vocab FILE --vocab-images DIR [DIR...] [--vocab-k 10] [--vocab-levels 5]
    mipslam bench --scenario NAME [--out DIR] [--smoke] [--threads N] [--set NAME.KEY=VALUE]... [--set k=v]...
    mipslam bench --list-scenarios

CONFIG is a YAML file or a built-in config's name (base, replica, synthetic, tum: ``mipslam config --list``).
"""
from __future__ import annotations

import argparse
import gc
import json
import logging
import sys
import time
from pathlib import Path

from mipslam import __version__
from mipslam.errors import MipslamError

log = logging.getLogger("mipslam")

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class _ArgumentParser(argparse.ArgumentParser):
    """argparse that raises instead of exiting, so every usage error takes the same path."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise _UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


class _UsageError(Exception):
    pass


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=["fast", "balanced", "accurate"], help="speed/accuracy preset overlay")
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config value, e.g. --set tracking.iterations=30 (repeatable)",
    )


def _float_list(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None
    if not values or not all(v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive numbers separated by commas, got {text!r}")
    return values


def _mode_list(text: str) -> tuple[str, ...]:
    from mipslam.render import MODES

    values = tuple(v.strip() for v in text.split(",") if v.strip())
    unknown = [v for v in values if v not in MODES]
    if not values or unknown:
        raise argparse.ArgumentTypeError(f"expected modes from {', '.join(MODES)} separated by commas, got {text!r}")
    return values


def _finite_float(text: str, *, zero_allowed: bool) -> float:
    """A finite number > 0 (>= 0 with ``zero_allowed``) from an argument, or the argparse error that says so."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not ((value >= 0 if zero_allowed else value > 0) and value != float("inf")):
        raise argparse.ArgumentTypeError(f"expected {'a number >= 0' if zero_allowed else 'a positive number'}, "
                                         f"got {text!r}")
    return value


def _positive_float(text: str) -> float:
    return _finite_float(text, zero_allowed=False)


def _non_negative_float(text: str) -> float:
    return _finite_float(text, zero_allowed=True)


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port in 0..65535, got {value}")
    return value


def _add_viewer_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--viewer", action="store_true",
                   help="show the run live in the browser (needs pip install 'mipslam[viewer]')")
    p.add_argument("--viewer-host", default="127.0.0.1",
                   help="viewer address (default 127.0.0.1, this machine only; 0.0.0.0 = every interface)")
    p.add_argument("--viewer-port", type=_port, default=8080,
                   help="viewer port (default 8080; the next free one when busy)")


def _build_parser() -> argparse.ArgumentParser:
    parser = _ArgumentParser(prog="mipslam", description="RGB-D SLAM with an anti-aliased 3D Gaussian map.")
    parser.add_argument("--version", action="version", version=f"mipslam {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_ArgumentParser)

    run = sub.add_parser("run", help="run SLAM on a sequence described by a config file")
    run.add_argument("config", type=Path, nargs="?",
                     help="a built-in config's name (replica, tum, synthetic: mipslam config --list) or a YAML file; "
                          "with --resume, default the run's own config.yaml")
    _add_config_args(run)
    run.add_argument("--out", type=Path, metavar="DIR",
                     help="run folder, new or empty (default: runs/<config name>-<time>)")
    run.add_argument("--overwrite", action="store_true",
                     help="replace the run already in --out (deletes only the files a run writes)")
    run.add_argument("--resume", type=Path, metavar="RUN_DIR",
                     help="continue the run in RUN_DIR from its last good checkpoint, with its own config")
    run.add_argument("--no-eval", action="store_true", help="skip the evaluation at the end")
    _add_viewer_args(run)

    ev = sub.add_parser("eval", help="evaluate a run folder, or a pair of TUM trajectory files")
    ev.add_argument("run_dir", nargs="?", type=Path, help="run folder written by 'mipslam run'")
    ev.add_argument("--gt", type=Path, help="ground-truth trajectory (TUM format)")
    ev.add_argument("--est", type=Path, help="estimated trajectory (TUM format)")
    ev.add_argument("--alignment", choices=["se3", "sim3", "none"], default=None, help="trajectory alignment (default se3)")
    ev.add_argument("--association", choices=["timestamp", "index"], default=None,
                    help="pose association (default: timestamp; index for Replica-style runs)")
    ev.add_argument("--max-diff", type=float, default=None, help="timestamp association tolerance in seconds (default 0.02)")
    ev.add_argument("--out", type=Path,
                    help="metrics file to write (default: RUN_DIR/metrics.json for the run's own evaluation, "
                         "RUN_DIR/metrics_<label>.json beside it when scales, modes or other options differ; "
                         "--gt/--est: print only)")
    ev.add_argument("--frames", choices=["split", "all", "keyframes", "non_keyframes"], default=None,
                    help="render metrics on novel and training views as two rows (split: every 5th frame that is not "
                         "a keyframe, as MonoGS, and the keyframes), or on one set: all frames, keyframes (training "
                         "views) or non-keyframes (novel views); default: the run's eval.frames")
    ev.add_argument("--resolution", choices=["native", "mapping"], default=None,
                    help="what scale 1 is: native = the camera's own images (before dataset.downscale), mapping = "
                         "the frames the run mapped; default: the run's eval.resolution")
    ev.add_argument("--scales", type=_float_list, default=None, metavar="S1,S2,...",
                    help="render at these scales of the --resolution reference, e.g. 0.125,0.25,0.5,1,2 "
                         "(default: eval.scales)")
    ev.add_argument("--modes", type=_mode_list, default=None, metavar="M1,M2,...",
                    help="footprint modes to compare, e.g. point,mip,ewa,eaa (default: eval.modes, else the run's mode)")
    ev.add_argument("--every", type=int, default=None, metavar="K",
                    help="split: novel views at every K-th frames.json position (default 5); one set: every K-th "
                         "frame of it (default: at most 50 frames, 8 for multi-scale tables)")
    ev.add_argument("--ground-truth", choices=["auto", "exact", "resampled"], default="auto",
                    help="ground truth at other scales: exact data_synth renders or area-resampled images (default auto)")
    ev.add_argument("--lpips", action=argparse.BooleanOptionalAction, default=True,
                    help="compute LPIPS-alex where its weights are installed (default on)")
    ev.add_argument("--no-render", action="store_true", help="trajectory metrics only (no rendering)")
    ev.add_argument("--no-report", action="store_true", help="do not write RUN_DIR/report/")

    ex = sub.add_parser("export", help="export a run's map as a triangle mesh (TSDF fusion of rendered keyframes)")
    ex.add_argument("run_dir", type=Path, help="run folder written by 'mipslam run'")
    ex.add_argument("--mesh", type=Path, required=True, help="output mesh file (.ply, .obj, ...)")
    ex.add_argument("--voxel-size", type=float, default=None,
                    help="TSDF voxel size in metres (default: half a rendered pixel at the median depth, in [0.005, 0.1])")
    ex.add_argument("--overwrite", action="store_true", help="replace an existing mesh file")
    ex.add_argument("--sdf-trunc", type=float, default=None, help="TSDF truncation in metres (default 4 voxels)")
    ex.add_argument("--depth-max", type=float, default=None, help="ignore rendered depth beyond this (metres)")
    ex.add_argument("--scale", type=float, default=1.0, help="render at this scale of the mapping resolution")
    ex.add_argument("--mode", default=None, help="footprint mode of the renders (default: the run's mode)")
    ex.add_argument("--tsdf", choices=["voxel_block_grid", "scalable"], default="voxel_block_grid",
                    help="Open3D TSDF: VoxelBlockGrid (default) or the legacy ScalableTSDFVolume")
    ex.add_argument("--memory-limit", type=float, default=2048.0, metavar="MB",
                    help="stop with an error when the TSDF fusion (voxels, block table, meshing) would need more "
                         "than this (default 2048 MB; VoxelBlockGrid only)")

    sy = sub.add_parser("synth", help="generate a synthetic RGB-D sequence with exact ground truth")
    sy.add_argument("--out", type=Path, required=True, help="output folder (must not exist or be empty)")
    sy.add_argument("--overwrite", action="store_true", help="replace an earlier synthetic sequence in --out")
    sy.add_argument("--format", choices=["replica", "tum"], default="replica", help="folder layout")
    sy.add_argument("--trajectory", default="loop",
                    help="camera trajectory name (loop, zoom, line, static, spin), or a TUM trajectory file to replay "
                         "at 30 frames/s (e.g. a TUM RGB-D groundtruth.txt; --frames 0: all of it)")
    sy.add_argument("--trajectory-start", type=float, default=0.0, metavar="S",
                    help="replayed file: seconds after its first pose of the first frame")
    sy.add_argument("--width", type=int, default=160)
    sy.add_argument("--height", type=int, default=120)
    sy.add_argument("--frames", type=int, default=60)
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--supersample", type=int, default=4, help="samples per pixel side for the footprint average")
    sy.add_argument("--laps", type=int, default=1, help="laps of the loop trajectory")
    sy.add_argument("--depth-noise", type=float, default=0.0, help="depth noise at 1 m (metres, grows with z^2)")
    sy.add_argument("--depth-holes", type=float, default=0.0, help="fraction of depth pixels dropped")
    sy.add_argument("--exposure-jitter", type=float, default=0.0, help="per-frame gain/bias jitter")
    sy.add_argument("--motion-blur", type=float, default=0.0, metavar="F",
                    help="exposure as a fraction of the frame interval: colour averaged over the motion (0 = off)")
    sy.add_argument("--depth-radial-bias", type=float, default=0.0, metavar="B",
                    help="depth too far by B (relative) at the image's edges, 2B at its corners, 0 at its centre")
    sy.add_argument("--rolling-shutter", type=float, default=0.0, metavar="F",
                    help="colour rows read out top to bottom over F frame intervals (0 = a global shutter)")
    sy.add_argument("--depth-baseline", type=float, default=0.0, metavar="M",
                    help="depth from a second camera M metres along the colour camera's x axis, not registered to "
                         "the colour image (a raw Kinect's depth; 0 = registered)")
    sy.add_argument("--depth-focal-ratio", type=float, default=1.0, metavar="R",
                    help="that depth camera's focal length over the colour camera's (1 = the same)")
    sy.add_argument("--depth-delay", type=float, default=0.0, metavar="F",
                    help="depth taken F (< 0.5) frame intervals after the colour, as unsynchronised streams; the TUM "
                         "layout's depth.txt gives the later time (0 = together)")

    be = sub.add_parser("bench", help="run presets/sweeps on a sequence, repeated, and tabulate speed against accuracy")
    be.add_argument("target", type=Path, metavar="SEQUENCE_OR_CONFIG", nargs="?",
                    help="a YAML config or a built-in config's name, or a Replica / TUM / data_synth sequence folder "
                         "(the built-in config of its kind is used)")
    be.add_argument("--presets", default=None, metavar="P1,P2,...",
                    help="presets to compare, e.g. fast,balanced,accurate ('none' = the config as it is; default none)")
    be.add_argument("--sweep", dest="sweeps", action="append", default=[], metavar="KEY=V1,V2,...",
                    help="config values to sweep, e.g. render.eaa_max_nodes=1,2,4 (repeatable: cartesian product)")
    be.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config value in every setting (repeatable; wins over --threads and --max-frames)")
    be.add_argument("--repeat", type=int, default=3, help="runs per setting (default 3; medians and spread over them)")
    be.add_argument("--threads", type=int, default=None,
                    help="torch threads per run (run.threads, default 2); with --scenario: the scenario's threads")
    be.add_argument("--seed", type=int, default=0, help="run.seed of every run (default 0)")
    be.add_argument("--max-frames", type=int, default=None, help="process at most N frames of the sequence")
    be.add_argument("--timeout", type=float, default=3600.0, metavar="S",
                    help="seconds before a job's run is killed and recorded as failed (default 3600)")
    be.add_argument("--out", type=Path, help="output folder, new or empty (default: runs/bench-<name>-<time>)")
    where = be.add_mutually_exclusive_group()
    where.add_argument("--jobs", type=int, default=1, metavar="N",
                       help="local jobs at once (default 1: runs sharing a machine time each other; recorded)")
    where.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                       help="run the jobs as Ray tasks: a local Ray instance, or the cluster at ADDRESS "
                            "(needs pip install 'mipslam[ray]')")
    peers = be.add_argument_group("peers (docs/peers.md)")
    peers.add_argument("--peers", default=None, metavar="P1,P2",
                       help="also run established systems on the same frames: open3d (dense SLAM and odometry), "
                            "orbslam3 (needs pip install 'mipslam[peers]', GPL-3.0, and --vocab)")
    peers.add_argument("--peers-only", action="store_true", help="run the peers only, no mipslam settings")
    peers.add_argument("--peer-repeat", type=int, default=None, metavar="N",
                       help="runs per peer setting (default: 3 for orbslam3, 1 for the open3d peers)")
    peers.add_argument("--peer-python", default=None, metavar="PYTHON",
                       help="interpreter of the peer processes (default: this one), e.g. a venv holding pyorbslam3")
    peers.add_argument("--vocab", type=Path, default=None, metavar="FILE",
                       help="DBoW2 ORB vocabulary for orbslam3 (make one with --train-vocab)")
    peers.add_argument("--peer-set", dest="peer_sets", action="append", default=[], metavar="PEER.KEY=VALUE",
                       help="a peer option, e.g. orbslam3.realtime=false or open3d_dense.voxel_size_m=0.01 (repeatable)")
    scenarios = be.add_argument_group("benchmark scenarios (docs/bench.md; no SEQUENCE_OR_CONFIG)")
    scenarios.add_argument("--scenario", default=None, metavar="NAME",
                           help="run one benchmark scenario into --out (see --list-scenarios); --set NAME.KEY=VALUE "
                                "sets one of its options, --set KEY=VALUE a config value of the runs it makes")
    scenarios.add_argument("--list-scenarios", action="store_true", help="list the scenarios, one line each, and exit")
    scenarios.add_argument("--smoke", action="store_true",
                           help="run the scenario at its smallest size (checks that it runs; the numbers mean nothing)")
    vocab = be.add_argument_group("ORB vocabulary training (no SEQUENCE_OR_CONFIG)")
    vocab.add_argument("--train-vocab", type=Path, default=None, metavar="FILE",
                       help="train a DBoW2 ORB vocabulary (ORBvoc.txt format) into FILE and exit")
    vocab.add_argument("--vocab-images", nargs="+", type=Path, default=[], metavar="DIR",
                       help="folders of training images, none of them from a sequence the vocabulary will be "
                            "evaluated on (depth maps are skipped)")
    vocab.add_argument("--vocab-k", type=int, default=10, help="branching factor (default 10)")
    vocab.add_argument("--vocab-levels", type=int, default=5, help="depth of the tree (default 5)")
    vocab.add_argument("--vocab-max-images", type=int, default=0, metavar="N",
                       help="use at most N training images, evenly spaced (default 0: all)")

    rf = sub.add_parser("refine", help="keep optimising a finished run's map over all its keyframes; the refined "
                                       "map goes to RUN_DIR/refined/ (Ctrl-C-safe, run again to continue)")
    rf.add_argument("run_dir", type=Path, help="run folder written by 'mipslam run' (finished)")
    rf.add_argument("--minutes", type=_positive_float, default=None, metavar="M",
                    help="refinement time of this session in minutes (the steps' own time, evaluations excluded; "
                         "default 10 when --iterations is not given either)")
    rf.add_argument("--iterations", type=_non_negative_int, default=None, metavar="N",
                    help="steps of this session (one keyframe per step); with --minutes, whichever comes first; 0 = "
                         "no step: write and evaluate the map as it is")
    rf.add_argument("--resolution", choices=["mapping", "native"], default=None,
                    help="train on the keyframes at the run's mapping resolution (default; the dataset read as the "
                         "run read it) or the camera's own (dataset.downscale 1); continuing keeps the refinement's")
    rf.add_argument("--restart", action="store_true",
                    help="start over from the SLAM map, replacing RUN_DIR/refined/ (default: continue it)")
    rf.add_argument("--eval-every-minutes", type=_non_negative_float, default=1.0, metavar="E",
                    help="refinement minutes between progress evaluations (novel and training views, at most 8 "
                         "frames each, native resolution, no LPIPS; default 1; 0 = only before and at the end)")
    rf.add_argument("--no-eval", action="store_true",
                    help="skip the full evaluation at the end (refined/metrics.json)")

    vw = sub.add_parser("view", help="show a run folder in the browser (map, trajectories, keyframes, loops)")
    vw.add_argument("run_dir", type=Path, help="run folder written by 'mipslam run'")
    vw.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (default 127.0.0.1, this machine only; 0.0.0.0 = every interface)")
    vw.add_argument("--port", type=_port, default=8080, help="port (default 8080; the next free one when busy)")
    vw.add_argument("--follow", action="store_true", help="move the view with the frame chosen on the slider")
    vw.add_argument("--map-only", action="store_true", help="draw the Gaussians alone (no trajectories or cameras)")
    vw.add_argument("--slam-map", action="store_true",
                    help="show the SLAM map (map.ply, traj_est.txt) where 'mipslam refine' wrote a refined one "
                         "(shown by default)")
    vw.add_argument("--screenshot", type=Path, metavar="PNG",
                    help="save a screenshot of the page (headless Chromium) to PNG and exit instead of serving")
    vw.add_argument("--size", default="960x640", metavar="WxH", help="screenshot size in pixels (default 960x640)")

    cf = sub.add_parser("config", help="print the resolved config (file + preset + overrides), or list the built-in "
                                       "configs")
    cf.add_argument("config", type=Path, nargs="?",
                    help="a built-in config's name (base, replica, synthetic, tum) or a YAML file")
    cf.add_argument("--list", action="store_true", help="list the built-in configs and presets, and where they are")
    _add_config_args(cf)
    return parser


# ----------------------------------------------------------------------------- commands

def _cmd_config(args) -> int:
    from mipslam.config import config_to_yaml, load_config

    if args.list:
        if args.config is not None or args.preset or args.overrides:
            raise _UsageError("mipslam config: --list takes no CONFIG, --preset or --set")
        return _list_configs()
    if args.config is None:
        raise _UsageError("mipslam config: give a CONFIG (a built-in config's name or a YAML file), or --list")
    sys.stdout.write(config_to_yaml(load_config(args.config, preset=args.preset, overrides=args.overrides)))
    return EXIT_OK


def _list_configs() -> int:
    from mipslam.config import CONFIG_DIR, builtin_configs

    configs = builtin_configs()
    if not configs:
        raise MipslamError(f"{CONFIG_DIR}: no built-in configs; the installed package is incomplete, reinstall mipslam")
    width = max(len(c.name) for c in configs)
    print("built-in configs (mipslam run NAME --set dataset.path=DIR; inherit_from: NAME):")
    for c in configs:
        if not c.preset:
            print(f"  {c.name:<{width}}  {c.description}")
    print("presets (--preset NAME, laid over the config):")
    for c in configs:
        if c.preset:
            print(f"  {c.name:<{width}}  {c.description}")
    print(f"files: {CONFIG_DIR}")
    return EXIT_OK


def _cmd_run(args) -> int:
    from mipslam.config import load_config, resolve_config_source
    from mipslam.datasets import make_sequence
    from mipslam.io.run_folder import RunFolder, prepare_new_run_folder
    from mipslam.pipeline import resolve_device, run_slam

    if args.resume is not None:
        if args.out is not None and not _same_path(args.out, args.resume):
            raise _UsageError("mipslam run: --resume RUN_DIR continues in RUN_DIR; drop --out or give the same folder")
        if args.overwrite:
            raise _UsageError("mipslam run: --overwrite starts a run over, --resume continues it; give one of them")
        folder = RunFolder(args.resume)
        _check_resumable(folder, config_given=args.config is not None)
        config = load_config(args.config or folder.config_yaml, preset=args.preset, overrides=args.overrides)
        finished = None if _is_stream(config) else _finished_run_message(folder, config,
                                                                           len(make_sequence(config.dataset)))
        if finished:
            print(finished)
            return EXIT_OK
        existed = True
    else:
        if args.config is None:
            raise _UsageError("mipslam run: give a CONFIG file to start a run, or --resume RUN_DIR to continue one")
        source = resolve_config_source(args.config)  # a file, or a built-in config's name
        if source.is_dir() and (source / RunFolder.CHECKPOINTS).is_dir():
            raise _UsageError(f"{args.config}: is a run folder, not a config file; continue it with "
                              f"mipslam run --resume {args.config}")
        config = load_config(source, preset=args.preset, overrides=args.overrides)
        folder = RunFolder(args.out or _default_run_dir(args.config))
        # What can be checked before a folder is made or an earlier run replaced: the dataset opens, the device exists.
        if not _is_stream(config):  # a camera is opened once, by the run
            make_sequence(config.dataset)
        resolve_device(config.run.device)
        existed = prepare_new_run_folder(folder.root, overwrite=args.overwrite)
    viewer = _start_live_viewer(args, config) if args.viewer else None
    # What is alive now (modules, the config) lives for the whole run: keep it out of the cyclic collector's
    # full passes, each of which would rescan ~200k objects (0.15-0.2 s; 0.4 s of GC in 20 frames -> 0.1 s).
    gc.freeze()
    try:
        observed = {"observer": viewer} if viewer is not None else {}  # else the run's own Observer
        summary = run_slam(config, folder.root, resume=args.resume is not None, evaluate=not args.no_eval, **observed)
    except BaseException:
        if viewer is not None:
            viewer.close()
        if args.resume is None and folder.remove_if_unstarted(remove_root=not existed):
            log.debug("removed %s: the run stopped before its first checkpoint", folder.root)
        raise
    print(summary.describe())
    if viewer is not None:
        viewer.finish(summary.run_dir)
        _serve_until_interrupted(viewer.url, viewer.close)
    return EXIT_OK


def _is_stream(config) -> bool:
    """A camera or a recording played as one: opened once, by the run, and of no fixed length."""
    return config.dataset.kind in ("realsense", "realsense_bag")


def _same_path(a: Path, b: Path) -> bool:
    return a.expanduser().resolve() == b.expanduser().resolve()


def _default_run_dir(config: Path) -> Path:
    """``runs/<config name>-<time>``, with ``-2``, ``-3`` ... when runs start within the same second."""
    base = Path("runs") / f"{config.stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    candidate, n = base, 1
    while candidate.exists():
        n += 1
        candidate = base.with_name(f"{base.name}-{n}")
    return candidate


def _check_resumable(folder, *, config_given: bool) -> None:
    """A folder that --resume can continue: it exists and holds a checkpoint (and its config.yaml when no
    config is given); else a one-line error saying what to type instead."""
    contents = folder.inspect()
    if not contents.exists:
        raise _UsageError(f"{folder.root}: no such run folder to resume; check the path, or start a new run with "
                          f"mipslam run CONFIG --out {folder.root}")
    if not contents.is_folder:
        raise _UsageError(f"{folder.root}: is not a run folder (not a folder at all); --resume takes the folder a "
                          "run wrote")
    if not contents.checkpoints:
        raise _UsageError(f"{folder.root}: no checkpoint to resume from (the run stopped before its first one, or "
                          f"this is not a run folder); start it again with mipslam run CONFIG --out {folder.root}")
    if not config_given and not folder.config_yaml.is_file():
        raise _UsageError(f"{folder.config_yaml}: missing; give the run's config: mipslam run CONFIG --resume "
                          f"{folder.root}")


def _finished_run_message(folder, config, total_frames: int) -> str | None:
    """A line saying the run is already complete (every frame of the sequence checkpointed and the final
    outputs written after that checkpoint), or None when resuming has work to do. The config must still be
    compatible: resuming a finished run with changed settings is the same error as resuming any run."""
    from mipslam.checkpoint import check_config_compatible, read_checkpoint_header
    from mipslam.config import config_to_dict
    from mipslam.errors import CheckpointError

    latest = folder.inspect().checkpoints[-1]
    try:
        header = read_checkpoint_header(latest)
        done = int((header.get("metadata") or {}).get("next_frame", -1))
    except (CheckpointError, TypeError, ValueError):
        return None  # the resume reads the checkpoints properly and reports what is wrong
    check_config_compatible(header.get("config") or {}, config_to_dict(config), source=latest)
    outputs = (folder.traj_est, folder.keyframes, folder.map_ply)
    written = all(p.is_file() and p.stat().st_mtime >= latest.stat().st_mtime for p in outputs)
    if done < total_frames or not written:
        return None
    return (f"{folder.root}: the run is already complete ({done} of {total_frames} frames); nothing to do. "
            f"Evaluate it again with: mipslam eval {folder.root}; or start a new run with --out")


def _start_live_viewer(args, config):
    from mipslam.viewer.live import LiveViewer
    from mipslam.viewer.server import ViewerOptions

    viewer = LiveViewer(config.render, ViewerOptions(host=args.viewer_host, port=args.viewer_port),
                        diagnostics=config.run.diagnostics)
    log.info("viewer: %s (open it in a browser)", viewer.url)
    return viewer


def _serve_until_interrupted(url: str, close) -> None:
    """Keep the viewer open until Ctrl-C when someone can press it (stdin a terminal); else close it now."""
    if not sys.stdin.isatty():
        close()
        return
    print(f"viewer: {url} (Ctrl-C to close)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        close()


def _cmd_view(args) -> int:
    from mipslam.viewer.recorded import RecordedViewer
    from mipslam.viewer.server import ViewerOptions

    if args.screenshot is not None:
        from mipslam.viewer.browser import screenshot

        try:
            width, height = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise _UsageError(f"mipslam view: --size expects WIDTHxHEIGHT, e.g. 960x640, got {args.size!r}") from None
        viewer = RecordedViewer(args.run_dir, ViewerOptions(host="127.0.0.1", port=0, follow=args.follow,
                                                            map_only=args.map_only), refined=not args.slam_map)
        log.info("viewer: showing %s", viewer.describe_map())
        try:
            out = screenshot(viewer.url, args.screenshot, width=width, height=height,
                             ready=lambda: viewer.server.clients > 0)
        finally:
            viewer.close()
        print(f"screenshot of {args.run_dir} written to {out}")
        return EXIT_OK
    viewer = RecordedViewer(args.run_dir, ViewerOptions(host=args.host, port=args.port, follow=args.follow,
                                                        map_only=args.map_only), refined=not args.slam_map)
    print(f"viewer: {viewer.url} (Ctrl-C to close)", flush=True)
    log.info("viewer: showing %s", viewer.describe_map())
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return EXIT_OK
    finally:
        viewer.close()


def _cmd_refine(args) -> int:
    from mipslam.refine_run import RefineRequest, refine_run

    request = RefineRequest(minutes=args.minutes, iterations=args.iterations, resolution=args.resolution,
                            restart=args.restart, eval_every_minutes=args.eval_every_minutes,
                            evaluate=not args.no_eval)
    summary = refine_run(args.run_dir, request)
    print(summary.describe())
    return EXIT_OK


def _cmd_eval(args) -> int:
    if args.run_dir is not None and (args.gt or args.est):
        raise _UsageError("mipslam eval: give either RUN_DIR or --gt and --est, not both")
    if args.out is not None:  # (the run's own metrics.json is derived: evaluating again replaces it)
        _check_replaceable_metrics(args.out)
    if args.run_dir is None:
        if not (args.gt and args.est):
            raise _UsageError("mipslam eval: give a RUN_DIR, or both --gt GT.txt and --est EST.txt")
        from mipslam.evaluation.trajectory import evaluate_trajectory
        from mipslam.io.tum import read_tum_trajectory

        metrics = evaluate_trajectory(
            # Ground-truth files of the TUM benchmark contain repeated timestamps (fr2_desk); evo keeps them.
            read_tum_trajectory(args.gt, allow_duplicate_timestamps=True), read_tum_trajectory(args.est),
            alignment=args.alignment or "se3", association=args.association or "timestamp",
            max_diff=0.02 if args.max_diff is None else args.max_diff,
        ).to_dict()
        out = args.out
    else:
        from mipslam.evaluation.run_eval import evaluate_run

        metrics = evaluate_run(args.run_dir, alignment=args.alignment, association=args.association,
                               max_diff=args.max_diff, render=not args.no_render,
                               render_options=_render_options(args), report=not args.no_report)
        # another request than the run's own evaluation goes beside metrics.json, never over it
        out = args.out or args.run_dir / metrics["evaluation"]["metrics_file"]
    if out is not None:
        from mipslam.io.run_folder import write_json_atomic

        write_json_atomic(out, metrics)
    print(_format_metrics(metrics))
    if out is not None:
        label = metrics.get("evaluation", {}).get("label")
        kept = f" (evaluation '{label}'; the run's own metrics.json is unchanged)" if label and args.out is None else ""
        print(f"metrics written to {out}{kept}")
    return EXIT_OK


def _check_replaceable_metrics(path: Path) -> None:
    """Metrics are written over an earlier metrics file (re-evaluating is the point), never over anything else
    (a trajectory or a config given to --out by mistake)."""
    if not path.exists():
        return
    if path.is_dir():
        raise _UsageError(f"{path}: is a folder; give --out a file name such as {path / 'metrics.json'}")
    try:
        earlier = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        earlier = None
    if not (isinstance(earlier, dict) and ("trajectory" in earlier or "ate" in earlier)):
        raise _UsageError(f"{path}: exists and is not a metrics file written by mipslam eval; it is left as it is: "
                          "choose another --out")


def _render_options(args):
    """Render-evaluation options: the run's eval config, overridden by the flags that were given."""
    from mipslam.config import config_from_dict
    from mipslam.evaluation.render_eval import RenderEvalOptions

    import yaml

    config_path = args.run_dir / "config.yaml"
    try:
        eval_cfg = config_from_dict(yaml.safe_load(config_path.read_text(encoding="utf-8")) or {}).eval
    except FileNotFoundError:
        return None  # evaluate_run reports the missing file
    return RenderEvalOptions(
        frames=args.frames or eval_cfg.frames,
        resolution=args.resolution or eval_cfg.resolution,
        scales=args.scales or tuple(eval_cfg.scales),
        modes=args.modes or tuple(eval_cfg.modes),
        every=args.every,
        lpips=args.lpips,
        ground_truth=args.ground_truth,
    )


def _format_metrics(metrics: dict) -> str:
    lines = []
    trajectory = metrics.get("trajectory", metrics)
    ate = trajectory.get("ate")
    if ate:
        lines.append(f"ATE RMSE {ate['rmse'] * 100:.3f} cm over {ate['count']} matched poses"
                     f" ({trajectory['protocol']['alignment']['method']} alignment)")
    rpe_t, rpe_r = trajectory.get("rpe_translation"), trajectory.get("rpe_rotation")
    if rpe_t and rpe_r:
        lines.append(f"RPE {rpe_t['rmse'] * 100:.3f} cm, {rpe_r['rmse']:.3f} deg per step")
    path = trajectory.get("path_length")
    if path and path.get("ratio") is not None:
        lines.append(f"path length {path['estimate'] * 100:.1f} cm against {path['ground_truth'] * 100:.1f} cm "
                     f"of ground truth (x{path['ratio']:.2f})")
    loop_edges = metrics.get("loop_edges")
    if loop_edges:
        from mipslam.evaluation.loop_edges import summary_lines

        first, by_fitness = summary_lines(loop_edges)
        lines.extend([f"loop edges against ground truth (medians): {first}", f"  {by_fitness}"])
    size = metrics.get("map")
    if size and "gaussians" in size:
        lines.append(f"map: {size['gaussians']} Gaussians, {size['ply_mb']:.2f} MB ({size['file']})")
    render = metrics.get("render")
    if render:
        if "unavailable" in render:
            lines.append(f"render metrics unavailable: {render['unavailable']}")
        protocol = render.get("protocol", {})
        reference = protocol.get("scale_reference", {})
        if reference:
            lines.append(f"render metrics at scales of the {reference['resolution']} resolution "
                         f"{'x'.join(map(str, reference['size']))}, estimated poses, no exposure compensation")
        from mipslam.evaluation.report import selection_text

        for selection in protocol.get("frames", {}).get("views", []):
            lines.append(selection_text(selection))
        for row in render.get("rows", []):
            psnr = "inf" if row["psnr"] is None else f"{row['psnr']:.2f}"
            text = (f"{row['views']:>13} {row['mode']:>6} x{row['scale']:<6g} {row['width']}x{row['height']} "
                    f"PSNR {psnr:>6} dB  SSIM {row['ssim']:.4f}")
            if row.get("depth_l1") is not None:
                text += f"  depth L1 {row['depth_l1'] * 100:.2f} cm"
            if row.get("lpips") is not None:
                text += f"  LPIPS {row['lpips']:.4f}"
            lines.append(text)
        if isinstance(render.get("lpips"), str) and render["lpips"].startswith("unavailable"):
            lines.append(f"LPIPS {render['lpips']}")
    if metrics.get("report"):
        lines.append(f"report: {Path(metrics.get('run_dir', '.')) / metrics['report']}")
    return "\n".join(lines) if lines else json.dumps(metrics, indent=2)


def _cmd_synth(args) -> int:
    import data_synth

    if not args.overwrite and args.out.is_dir() and any(args.out.iterdir()):
        earlier = (args.out / "synth.json").is_file()
        raise _UsageError(f"{args.out}: output folder is not empty; choose another --out"
                          + (" or replace the synthetic sequence there with --overwrite" if earlier else ""))
    out = data_synth.generate(
        args.out, layout=args.format, trajectory=args.trajectory, width=args.width, height=args.height,
        frames=args.frames, seed=args.seed, supersample=args.supersample, laps=args.laps,
        depth_noise=args.depth_noise, depth_holes=args.depth_holes, exposure_jitter=args.exposure_jitter,
        trajectory_start_s=args.trajectory_start, motion_blur=args.motion_blur, depth_delay=args.depth_delay,
        rolling_shutter=args.rolling_shutter, depth_radial_bias=args.depth_radial_bias,
        depth_baseline=args.depth_baseline, depth_focal_ratio=args.depth_focal_ratio, overwrite=args.overwrite,
    )
    print(f"synthetic {args.format} sequence written to {out}")
    return EXIT_OK


def _cmd_export(args) -> int:
    from mipslam.export import export_mesh

    _check_mesh_target(args.mesh, args.run_dir, overwrite=args.overwrite)
    result = export_mesh(args.run_dir, args.mesh, voxel_size=args.voxel_size, sdf_trunc=args.sdf_trunc,
                         depth_max=args.depth_max, scale=args.scale, mode=args.mode, method=args.tsdf,
                         memory_limit_mb=args.memory_limit)
    print(result.describe())
    return EXIT_OK


def _check_mesh_target(mesh: Path, run_dir: Path, *, overwrite: bool) -> None:
    """A mesh never replaces a file of the run it comes from (its map.ply), a folder, or, without
    ``--overwrite``, any existing file."""
    from mipslam.io.run_folder import RUN_ENTRIES

    if not run_dir.is_dir():
        return  # export_mesh names the missing run folder
    if _same_path(mesh.parent, run_dir) and mesh.name in RUN_ENTRIES:
        raise _UsageError(f"{mesh}: is one of the run's own files; give the mesh another name, e.g. "
                          f"{mesh.with_name('mesh.ply')}")
    if mesh.is_dir():
        raise _UsageError(f"{mesh}: is a folder; give --mesh a file name such as {mesh / 'mesh.ply'}")
    if mesh.exists() and not overwrite:
        raise _UsageError(f"{mesh}: exists; replace it with --overwrite or choose another --mesh")


def _cmd_bench_vocab(args) -> int:
    from mipslam.bench.peers.vocabulary import train_vocabulary_file

    if args.target is not None:
        raise _UsageError("mipslam bench: --train-vocab takes no SEQUENCE_OR_CONFIG (see 'mipslam bench --help')")
    if not args.vocab_images:
        raise _UsageError("mipslam bench: --train-vocab needs --vocab-images DIR [DIR...] (see 'mipslam bench --help')")
    if args.train_vocab.exists():
        raise MipslamError(f"{args.train_vocab}: exists; choose another file for --train-vocab or remove it")
    report = train_vocabulary_file(args.vocab_images, args.train_vocab, k=args.vocab_k, levels=args.vocab_levels,
                                   max_images=args.vocab_max_images, seed=args.seed)
    print(report.describe())
    return EXIT_OK


_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def _scenario_value(name: str, key: str, text: str, kind: str):
    """``text`` as a value of the scenario option ``key`` whose declared type is ``kind`` (int, float, bool, str
    or tuple[T, ...] of them, comma-separated)."""
    def one(item: str, item_kind: str):
        try:
            if item_kind == "bool":
                if item.lower() not in _TRUE + _FALSE:
                    raise ValueError
                return item.lower() in _TRUE
            return {"int": int, "float": float}.get(item_kind, str)(item)
        except ValueError:
            raise _UsageError(f"mipslam bench: --set {name}.{key}={text}: expected {kind}") from None

    kind = kind.replace(" ", "")
    if kind.startswith("tuple[") and kind.endswith(",...]"):
        return tuple(one(item.strip(), kind[6:-5]) for item in text.split(",") if item.strip())
    return one(text.strip(), kind)


def _scenario_request(args):
    """(scenario name, its Options) from the parsed ``mipslam bench --scenario`` arguments, without running it.

    ``--set NAME.KEY=VALUE`` sets an option (``--smoke`` starts from the smallest size); any other ``--set KEY=VALUE``
    is a config override of the runs the scenario makes (its ``config_overrides``)."""
    import difflib
    from dataclasses import fields

    from mipslam.bench.scenarios import SCENARIOS, load_scenario

    name = args.scenario
    if name not in SCENARIOS:
        close = difflib.get_close_matches(name, SCENARIOS, n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise _UsageError(f"mipslam bench: --scenario {name}: unknown; {hint}choose one of {', '.join(SCENARIOS)} "
                          "(mipslam bench --list-scenarios)")
    given = [flag for flag, value in (("SEQUENCE_OR_CONFIG", args.target), ("--presets", args.presets),
                                      ("--sweep", args.sweeps), ("--peers", args.peers),
                                      ("--train-vocab", args.train_vocab), ("--ray", args.ray)) if value]
    if given:
        raise _UsageError(f"mipslam bench: --scenario takes no {', '.join(given)} (see 'mipslam bench --help')")
    module = load_scenario(name)
    kinds = {f.name: str(f.type) for f in fields(module.Options)}
    values = dict(module.SMOKE) if args.smoke else {}
    if args.threads is not None and "threads" in kinds:
        values["threads"] = args.threads
    config_overrides = []
    for item in args.overrides:
        key, sep, text = item.partition("=")
        if not sep:
            raise _UsageError(f"mipslam bench: --set {item}: expected KEY=VALUE")
        if not key.startswith(f"{name}."):
            if "config_overrides" not in kinds:
                raise _UsageError(f"mipslam bench: --set {item}: scenario {name} takes no config values; its options "
                                  f"are {', '.join(f'{name}.{k}' for k in kinds)}")
            config_overrides.append(item)
            continue
        option = key[len(name) + 1:]
        if option not in kinds:
            close = difflib.get_close_matches(option, kinds, n=1)
            hint = f"did you mean '{name}.{close[0]}'? " if close else ""
            raise _UsageError(f"mipslam bench: --set {item}: {name} has no option {option!r}; {hint}its options are "
                              f"{', '.join(kinds)}")
        values[option] = _scenario_value(name, option, text, kinds[option])
    if config_overrides:
        values["config_overrides"] = (*values.get("config_overrides", ()), *config_overrides)
    return name, module.Options(**values)


def _cmd_bench_scenario(args) -> int:
    from mipslam.bench.scenarios import default_scenario_out_dir, run_scenario

    name, options = _scenario_request(args)
    if args.threads is not None and not hasattr(options, "threads"):
        import torch

        torch.set_num_threads(args.threads)
    result = run_scenario(name, options, args.out or default_scenario_out_dir(name))
    print(result.summary)
    written = [result.files.json, *([result.files.markdown] if result.files.markdown else []), *result.plots]
    print(f"results: {', '.join(str(p) for p in written)}")
    if not result.passed:
        print(f"error: scenario {name}: a check failed (see {result.files.markdown})", file=sys.stderr)
        return EXIT_FAILURE
    return EXIT_OK


def _list_scenarios() -> int:
    from mipslam.bench.scenarios import SCENARIOS

    width = max(len(name) for name in SCENARIOS)
    for info in SCENARIOS.values():
        print(f"{info.name:<{width}}  {info.summary}{' (source checkout)' if info.needs_checkout else ''}")
    return EXIT_OK


def _cmd_bench(args) -> int:
    if args.list_scenarios:
        return _list_scenarios()
    if args.scenario is not None:  # before torch loads: a scenario may set the thread environment first
        return _cmd_bench_scenario(args)
    from mipslam.bench import (BenchSpec, LocalExecutor, RayExecutor, default_out_dir, parse_presets, parse_sweep,
                               resolve_target, run_bench)
    from mipslam.bench.peers import parse_peer_sets, parse_peers

    if args.smoke:
        raise _UsageError("mipslam bench: --smoke goes with --scenario NAME (see 'mipslam bench --help')")
    if args.train_vocab is not None:
        return _cmd_bench_vocab(args)
    if args.target is None:
        raise _UsageError("mipslam bench: give SEQUENCE_OR_CONFIG, --scenario NAME (--list-scenarios) or "
                          "--train-vocab FILE (see 'mipslam bench --help')")
    target = resolve_target(args.target)
    options = parse_peer_sets(args.peer_sets)
    if args.vocab is not None:
        options = parse_peer_sets([f"orbslam3.vocabulary={args.vocab.expanduser().resolve()}"], options)
    spec = BenchSpec(target=target, out_dir=args.out or default_out_dir(target), presets=parse_presets(args.presets),
                     sweeps=tuple(parse_sweep(s) for s in args.sweeps), overrides=tuple(args.overrides),
                     repeat=args.repeat, threads=2 if args.threads is None else args.threads, seed=args.seed,
                     max_frames=args.max_frames,
                     timeout_s=args.timeout, peers=parse_peers(args.peers), peer_repeat=args.peer_repeat,
                     peer_python=args.peer_python or sys.executable, peer_options=options,
                     run_mipslam=not args.peers_only)
    executor = RayExecutor(args.ray or None) if args.ray is not None else LocalExecutor(args.jobs)
    outcome = run_bench(spec, executor)
    print(outcome.describe())
    if outcome.failed:
        print(f"warning: {outcome.failed} of {len(outcome.rows)} jobs failed; their errors are rows of "
              f"{outcome.files.markdown}", file=sys.stderr)
    return EXIT_OK


_COMMANDS = {"bench": _cmd_bench, "run": _cmd_run, "eval": _cmd_eval, "synth": _cmd_synth, "config": _cmd_config,
             "export": _cmd_export, "view": _cmd_view, "refine": _cmd_refine}


def _configure_logging(debug: bool, quiet: bool) -> None:
    level = logging.DEBUG if debug else logging.WARNING if quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s" if debug else "mipslam: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    logging.getLogger("mipslam").setLevel(level)
    logging.getLogger("data_synth").setLevel(level)


def _one_line(exc: BaseException) -> str:
    """The message on one line (a library message quoting a user's text with a line break in it, say)."""
    return " | ".join(line.strip() for line in str(exc).splitlines() if line.strip())


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    try:
        parser = _build_parser()
        args = parser.parse_args(argv)
        _configure_logging(args.debug, args.quiet)
        if args.command is None:
            parser.print_help()
            return EXIT_USAGE
        return _COMMANDS[args.command](args)
    except SystemExit as exc:  # --help / --version exit through argparse
        return int(exc.code or 0)
    except _UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except MipslamError as exc:
        if debug:
            log.exception("failed")
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # the last line of defence: one line, traceback only with --debug
        if debug:
            raise
        print(f"error: unexpected {type(exc).__name__}: {_one_line(exc)} (rerun with --debug for the traceback)",
              file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
