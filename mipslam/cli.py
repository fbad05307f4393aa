"""Command-line interface: the only place that parses arguments, configures logging and turns
errors into exit codes (0 success, 1 unexpected failure, 2 usage/config/data error, 130 Ctrl-C).

    mipslam run CONFIG [--preset P] [--set k=v]... [--out DIR] [--resume RUN_DIR]
    mipslam eval RUN_DIR | --gt GT.txt --est EST.txt
    mipslam synth --out DIR --format replica|tum --trajectory loop ...
    mipslam config CONFIG [--preset P] [--set k=v]...
"""
from __future__ import annotations

import argparse
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


def _build_parser() -> argparse.ArgumentParser:
    parser = _ArgumentParser(prog="mipslam", description="RGB-D SLAM with an anti-aliased 3D Gaussian map.")
    parser.add_argument("--version", action="version", version=f"mipslam {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_ArgumentParser)

    run = sub.add_parser("run", help="run SLAM on a sequence described by a config file")
    run.add_argument("config", type=Path, help="YAML config (e.g. configs/replica.yaml)")
    _add_config_args(run)
    run.add_argument("--out", type=Path, help="run folder (default: runs/<config name>-<time>)")
    run.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue the run in RUN_DIR from its last good checkpoint")
    run.add_argument("--no-eval", action="store_true", help="skip the evaluation at the end")

    ev = sub.add_parser("eval", help="evaluate a run folder, or a pair of TUM trajectory files")
    ev.add_argument("run_dir", nargs="?", type=Path, help="run folder written by 'mipslam run'")
    ev.add_argument("--gt", type=Path, help="ground-truth trajectory (TUM format)")
    ev.add_argument("--est", type=Path, help="estimated trajectory (TUM format)")
    ev.add_argument("--alignment", choices=["se3", "sim3", "none"], default=None, help="trajectory alignment (default se3)")
    ev.add_argument("--association", choices=["timestamp", "index"], default=None,
                    help="pose association (default: timestamp; index for Replica-style runs)")
    ev.add_argument("--max-diff", type=float, default=None, help="timestamp association tolerance in seconds (default 0.02)")
    ev.add_argument("--out", type=Path, help="where to write metrics.json (default: RUN_DIR/metrics.json, or print only)")

    sy = sub.add_parser("synth", help="generate a synthetic RGB-D sequence with exact ground truth")
    sy.add_argument("--out", type=Path, required=True, help="output folder (must not exist or be empty)")
    sy.add_argument("--format", choices=["replica", "tum"], default="replica", help="folder layout")
    sy.add_argument("--trajectory", default="loop", help="camera trajectory name (loop, zoom, line, static)")
    sy.add_argument("--width", type=int, default=160)
    sy.add_argument("--height", type=int, default=120)
    sy.add_argument("--frames", type=int, default=60)
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--supersample", type=int, default=4, help="samples per pixel side for the footprint average")
    sy.add_argument("--laps", type=int, default=1, help="laps of the loop trajectory")
    sy.add_argument("--depth-noise", type=float, default=0.0, help="depth noise at 1 m (metres, grows with z^2)")
    sy.add_argument("--depth-holes", type=float, default=0.0, help="fraction of depth pixels dropped")
    sy.add_argument("--exposure-jitter", type=float, default=0.0, help="per-frame gain/bias jitter")

    cf = sub.add_parser("config", help="print the resolved config (file + preset + overrides)")
    cf.add_argument("config", type=Path)
    _add_config_args(cf)
    return parser


# ----------------------------------------------------------------------------- commands

def _cmd_config(args) -> int:
    from mipslam.config import config_to_yaml, load_config

    sys.stdout.write(config_to_yaml(load_config(args.config, preset=args.preset, overrides=args.overrides)))
    return EXIT_OK


def _cmd_run(args) -> int:
    from mipslam.config import load_config
    from mipslam.pipeline import run_slam

    config = load_config(args.config, preset=args.preset, overrides=args.overrides)
    if args.resume is not None and args.out is not None and args.out.resolve() != args.resume.resolve():
        raise _UsageError("mipslam run: --resume RUN_DIR continues in RUN_DIR; drop --out or give the same folder")
    run_dir = args.resume or args.out or Path("runs") / f"{args.config.stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    summary = run_slam(config, run_dir, resume=args.resume is not None, evaluate=not args.no_eval)
    print(summary.describe())
    return EXIT_OK


def _cmd_eval(args) -> int:
    if args.run_dir is not None and (args.gt or args.est):
        raise _UsageError("mipslam eval: give either RUN_DIR or --gt and --est, not both")
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

        metrics = evaluate_run(args.run_dir, alignment=args.alignment, association=args.association, max_diff=args.max_diff)
        out = args.out or args.run_dir / "metrics.json"
    if out is not None:
        from mipslam.io.run_folder import write_json_atomic

        write_json_atomic(out, metrics)
    print(_format_metrics(metrics))
    if out is not None:
        print(f"metrics written to {out}")
    return EXIT_OK


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
    render = metrics.get("render")
    if render:
        for row in render.get("rows", []):
            lines.append(f"{row['mode']:>6} x{row['scale']:<5g} PSNR {row['psnr']:.2f} dB  SSIM {row['ssim']:.4f}")
    return "\n".join(lines) if lines else json.dumps(metrics, indent=2)


def _cmd_synth(args) -> int:
    import data_synth

    out = data_synth.generate(
        args.out, layout=args.format, trajectory=args.trajectory, width=args.width, height=args.height,
        frames=args.frames, seed=args.seed, supersample=args.supersample, laps=args.laps,
        depth_noise=args.depth_noise, depth_holes=args.depth_holes, exposure_jitter=args.exposure_jitter,
    )
    print(f"synthetic {args.format} sequence written to {out}")
    return EXIT_OK


_COMMANDS = {"run": _cmd_run, "eval": _cmd_eval, "synth": _cmd_synth, "config": _cmd_config}


def _configure_logging(debug: bool, quiet: bool) -> None:
    level = logging.DEBUG if debug else logging.WARNING if quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s" if debug else "mipslam: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    logging.getLogger("mipslam").setLevel(level)
    logging.getLogger("data_synth").setLevel(level)


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
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # the last line of defence: one line, traceback only with --debug
        if debug:
            raise
        print(f"error: unexpected {type(exc).__name__}: {exc} (rerun with --debug for the traceback)", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
