"""Smoke test over every CLI command and its error path: one line on stderr, exit code 2, no traceback."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import data_synth
from mipslam import __version__
from mipslam.cli import main
from mipslam.io.run_folder import RunFolder

REPO = Path(__file__).resolve().parent.parent


def test_help_and_version(capsys):
    assert main(["--help"]) == 0
    assert "run" in capsys.readouterr().out
    assert main(["--version"]) == 0
    assert __version__ in capsys.readouterr().out
    for command in ("run", "eval", "synth", "config"):
        assert main([command, "--help"]) == 0
    assert main([]) == 2


def test_config_prints_the_resolved_config(capsys):
    assert main(["config", "tum", "--preset", "fast", "--set", "tracking.iterations=7"]) == 0
    out = capsys.readouterr().out
    assert "iterations: 7" in out and "kind: tum" in out


def test_config_list_shows_the_built_in_configs_and_presets(capsys):
    from mipslam.config import CONFIG_DIR

    assert main(["config", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in lines if line.startswith("  ")}
    assert list(rows) == ["base", "replica", "synthetic", "tum", "fast", "balanced", "accurate"]
    assert "TUM RGB-D" in rows["tum"] and "data_synth" in rows["synthetic"]
    presets = lines.index(next(line for line in lines if line.startswith("presets")))
    assert all(lines.index(rows[name]) > presets for name in ("fast", "balanced", "accurate"))
    assert all(lines.index(rows[name]) < presets for name in ("base", "replica", "synthetic", "tum"))
    assert lines[-1] == f"files: {CONFIG_DIR}"


def test_config_by_name_with_a_preset_from_any_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["config", "tum", "--preset", "fast"]) == 0
    by_name = capsys.readouterr().out
    assert main(["config", str(REPO / "mipslam" / "configs" / "tum.yaml"), "--preset", "fast"]) == 0
    assert capsys.readouterr().out == by_name and "kind: tum" in by_name


@pytest.mark.parametrize(
    "argv, message",
    [
        (["config", "nope.yaml"], "config file not found"),
        (["config", "base", "--set", "mapping.iteratoins=3"], "did you mean 'mapping.iterations'"),
        (["run"], "give a CONFIG file to start a run, or --resume RUN_DIR"),
        (["config", "tmu"], "unknown config 'tmu' (did you mean 'tum'?); built-in configs: base, replica, synthetic, "
                            "tum (presets: fast, balanced, accurate); or give a YAML file"),
        (["run", "tmu"], "unknown config 'tmu'"),
        (["config"], "give a CONFIG (a built-in config's name or a YAML file), or --list"),
        (["config", "--list", "tum"], "--list takes no CONFIG"),
        (["run", "tum", "--out", "/nonexistent/never"], "dataset.path is empty; point it at a tum folder with --set "
                                                        "dataset.path=DIR"),
        (["eval"], "give a RUN_DIR, or both --gt"),
        (["synth", "--out", "/tmp/x", "--format", "kitti"], "invalid choice"),
        (["frobnicate"], "invalid choice"),
    ],
)
def test_errors_are_one_line_with_exit_code_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_eval_of_two_trajectory_files(tmp_path, capsys):
    from mipslam.io.tum import write_tum_trajectory
    import numpy as np

    times = np.arange(10, dtype=np.float64)
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = np.linspace(0, 1, 10)
    poses[:, 1, 3] = np.linspace(0, 1, 10) ** 2
    write_tum_trajectory(tmp_path / "gt.txt", times, poses)
    shifted = poses.copy()
    shifted[:, 2, 3] += 0.01  # a constant offset: removed by SE(3) alignment, 1 cm without it
    write_tum_trajectory(tmp_path / "est.txt", times, shifted)
    out = tmp_path / "metrics.json"
    assert main(["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["ate"]["rmse"] < 1e-9
    assert main(["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"), "--alignment", "none",
                 "--out", str(out)]) == 0
    assert json.loads(out.read_text())["ate"]["rmse"] == pytest.approx(0.01, abs=1e-6)
    capsys.readouterr()
    assert main(["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "missing.txt")]) == 2
    assert "missing.txt" in capsys.readouterr().err


def test_console_script_runs_as_a_process(tmp_path):
    """The installed entry point, as a user calls it: errors give exit code 2 and one line, --debug a traceback."""
    exe = Path(sys.executable).with_name("mipslam")
    if not exe.exists():
        pytest.skip(f"console script not installed next to {sys.executable}")
    result = subprocess.run([str(exe), "config", str(tmp_path / "none.yaml")], capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.strip().startswith("error:") and "Traceback" not in result.stderr
    debug = subprocess.run([str(exe), "--debug", "config", str(tmp_path / "none.yaml")], capture_output=True, text=True)
    assert debug.returncode == 2 and "Traceback" in debug.stderr


# ----------------------------------------------------------------------------- run folders: refuse, resume, replace

# A few seconds per run on 2 cores: 6 frames of 40 x 30, few iterations, no final refinement.
TINY = ["mapping.first_frame_iterations=20", "mapping.iterations=5", "refine.passes=0",
        "mapping.densify_pixel_stride=2", "tracking.iterations=10", "keyframes.window_size=3",
        "keyframes.random_past=1", "run.threads=1"]


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "seq"
    data_synth.generate(out, layout="replica", trajectory="loop", width=40, height=30, frames=6, seed=0, supersample=2)
    return out


def run_argv(sequence: Path | str, out: Path, *extra: str) -> list[str]:
    argv = ["-q", "run", "synthetic", "--no-eval", "--out", str(out)]
    for item in (f"dataset.path={sequence}", *TINY, *extra):
        argv += ["--set", item]
    return argv


def error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines and lines[-1].startswith("error: ") and "Traceback" not in "".join(lines), lines
    return lines[-1]


def checkpoint_frames(run_dir: Path) -> list[int]:
    from mipslam.checkpoint import list_checkpoints, read_checkpoint_header

    return [read_checkpoint_header(p)["metadata"]["next_frame"] for p in list_checkpoints(run_dir / "checkpoints")]


@pytest.fixture(scope="module")
def partial_run(tiny_sequence, tmp_path_factory) -> Path:
    """A run stopped after 3 of the 6 frames (as Ctrl-C or a kill leaves it, minus the outputs)."""
    run_dir = tmp_path_factory.mktemp("runs") / "partial"
    assert main(run_argv(tiny_sequence, run_dir, "dataset.max_frames=3")) == 0
    return run_dir


def copy_run(run_dir: Path, to: Path) -> Path:
    import shutil

    return Path(shutil.copytree(run_dir, to))


def test_a_run_by_name_from_another_folder_lands_in_runs_there(tiny_sequence, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["-q", "run", "synthetic", "--preset", "fast", "--no-eval"]
    for item in (f"dataset.path={tiny_sequence}", *TINY, "dataset.max_frames=2", "mapping.first_frame_iterations=5"):
        argv += ["--set", item]
    assert main(argv) == 0
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert run_dir.name.startswith("synthetic-") and (run_dir / "traj_est.txt").is_file()
    assert "kind: synthetic" in (run_dir / "config.yaml").read_text()


def test_a_run_folder_holds_only_what_a_run_writes(partial_run):
    contents = RunFolder(partial_run).inspect()
    assert contents.holds_run and contents.foreign == (), contents
    assert (partial_run / "traj_est.txt").is_file() and contents.checkpoints


def test_run_refuses_a_folder_holding_a_run(partial_run, tiny_sequence, tmp_path, capsys):
    run_dir = copy_run(partial_run, tmp_path / "run")
    before = {p.relative_to(run_dir): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert main(run_argv(tiny_sequence, run_dir)) == 2
    err = error_line(capsys)
    assert str(run_dir) in err and f"--resume {run_dir}" in err and "--overwrite" in err and "another --out" in err
    assert {p.relative_to(run_dir): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before


def test_overwrite_replaces_a_run_but_never_foreign_files(partial_run, tiny_sequence, tmp_path, capsys):
    run_dir = copy_run(partial_run, tmp_path / "run")
    (run_dir / "notes.txt").write_text("mine")
    assert main(run_argv(tiny_sequence, run_dir, "dataset.max_frames=4") + ["--overwrite"]) == 2
    err = error_line(capsys)
    assert "notes.txt" in err and "another --out" in err
    assert (run_dir / "notes.txt").read_text() == "mine" and checkpoint_frames(run_dir) == [3]
    (run_dir / "notes.txt").unlink()
    assert main(run_argv(tiny_sequence, run_dir, "dataset.max_frames=4") + ["--overwrite"]) == 0
    assert checkpoint_frames(run_dir) == [4]  # the old run's checkpoint is gone, not resumed from
    assert len([line for line in (run_dir / "traj_est.txt").read_text().splitlines() if line[:1] != "#"]) == 4
    # a folder that holds no run at all is never a run folder, with or without --overwrite
    other = tmp_path / "photos"
    other.mkdir()
    (other / "config.yaml").write_text("my own file")
    assert main(run_argv(tiny_sequence, other) + ["--overwrite"]) == 2
    assert "holds no mipslam run" in error_line(capsys)
    assert (other / "config.yaml").read_text() == "my own file"
    assert main(["run", "--resume", str(run_dir), "--overwrite"]) == 2
    assert "give one of them" in error_line(capsys)


def test_a_run_that_fails_before_its_first_frame_leaves_no_folder(tiny_sequence, tmp_path, capsys, monkeypatch):
    missing = tmp_path / "no_such_sequence"
    assert main(run_argv(missing, tmp_path / "runs" / "a")) == 2
    assert str(missing) in error_line(capsys)
    assert not (tmp_path / "runs").exists()
    if not torch.cuda.is_available():
        assert main(run_argv(tiny_sequence, tmp_path / "b", "run.device=cuda")) == 2
        assert "cuda" in error_line(capsys) and not (tmp_path / "b").exists()
    # A failure after the run made its folder (injected where the run opens its sequence) removes what the
    # run created, and only that: a folder that existed before stays.
    from mipslam import run_control
    from mipslam.errors import MipslamError

    def fail(*args, **kwargs):
        raise MipslamError("injected failure before the first frame")

    monkeypatch.setattr(run_control, "make_sequence", fail)
    assert main(run_argv(tiny_sequence, tmp_path / "c")) == 2
    assert "injected" in error_line(capsys) and not (tmp_path / "c").exists()
    (tmp_path / "empty").mkdir()
    assert main(run_argv(tiny_sequence, tmp_path / "empty")) == 2
    assert (tmp_path / "empty").is_dir() and not any((tmp_path / "empty").iterdir())


def test_resume_from_the_run_folder_alone(partial_run, tiny_sequence, tmp_path, capsys):
    run_dir = copy_run(partial_run, tmp_path / "run")
    saved = (run_dir / "config.yaml").read_text()
    assert f"path: {tiny_sequence.resolve()}" in saved  # absolute: the file means the same read from anywhere
    # The run's own config (max_frames 3) is complete: said so, exit 0, nothing written.
    assert main(["run", "--resume", str(run_dir)]) == 0
    out = capsys.readouterr().out
    assert "already complete (3 of 3 frames)" in out and "nan" not in out
    assert checkpoint_frames(run_dir) == [3]
    # Going further is a key that cannot change results (as is the thread count): allowed and logged.
    assert main(["run", "--resume", str(run_dir), "--no-eval", "--set", "dataset.max_frames=0",
                 "--set", "run.threads=2"]) == 0
    err = capsys.readouterr().err
    assert "dataset.max_frames: 3 -> 0" in err and "run.threads: 1 -> 2" in err
    assert checkpoint_frames(run_dir)[-1] == 6
    assert "threads: 2" in (run_dir / "config.yaml").read_text()
    assert main(["run", "--resume", str(run_dir), "--set", "dataset.max_frames=0"]) == 0
    assert "already complete (6 of 6 frames)" in capsys.readouterr().out


def test_resume_with_the_runs_config_file_from_another_directory(partial_run, tmp_path, monkeypatch, capsys):
    """The advice of the resume error, typed from another working directory, names the same sequence."""
    run_dir = copy_run(partial_run, tmp_path / "run")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["-q", "run", str(run_dir / "config.yaml"), "--resume", str(run_dir), "--no-eval",
                 "--set", "dataset.max_frames=4"]) == 0
    assert checkpoint_frames(run_dir)[-1] == 4


def test_resume_with_the_same_folder_written_relative_and_with_a_changed_result_key(
        partial_run, tiny_sequence, tmp_path, monkeypatch, capsys):
    run_dir = copy_run(partial_run, tmp_path / "run")
    monkeypatch.chdir(tiny_sequence.parent)
    relative = ["--set", "dataset.path=./seq/", "--set", "dataset.max_frames=4"]
    assert main(["-q", "run", "--resume", str(run_dir), "--no-eval", *relative]) == 0
    assert checkpoint_frames(run_dir)[-1] == 4
    assert main(["run", "--resume", str(run_dir), "--set", "render.mode=point", "--set", "tracking.iterations=3"]) == 2
    err = error_line(capsys)
    assert "render.mode: checkpoint 'eaa', now 'point'" in err and "tracking.iterations" in err
    assert f"mipslam run --resume {run_dir}" in err
    other = tmp_path / "other_seq"
    other.symlink_to(tiny_sequence, target_is_directory=True)  # same files: a link resolves to the same folder
    assert main(["-q", "run", "--resume", str(run_dir), "--no-eval", "--set", f"dataset.path={other}"]) == 0


def test_resume_errors_say_what_to_type(partial_run, tmp_path, capsys):
    assert main(["run", str(partial_run)]) == 2  # the run folder given as the config
    assert f"continue it with mipslam run --resume {partial_run}" in error_line(capsys)
    assert main(["run", "--resume", str(tmp_path / "typo")]) == 2
    assert "no such run folder" in error_line(capsys) and not (tmp_path / "typo").exists()
    (tmp_path / "bare").mkdir()
    assert main(["run", "--resume", str(tmp_path / "bare")]) == 2
    assert "no checkpoint to resume from" in (err := error_line(capsys)) and f"--out {tmp_path / 'bare'}" in err


# ----------------------------------------------------------------------------- config files: one line, exit 2

def test_config_file_mistakes_are_one_line_with_exit_code_2(tmp_path, capsys):
    png = tmp_path / "photo.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    assert main(["config", str(png)]) == 2
    assert "not a YAML text file" in error_line(capsys)
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracking:\n  iterations: 3\n   alpha_color: [1\n")
    assert main(["config", str(bad)]) == 2
    assert f"{bad}:3:" in error_line(capsys)
    assert main(["config", str(REPO / "mipslam" / "configs" / "replca.yaml")]) == 2
    assert "did you mean" in (err := error_line(capsys)) and str(REPO / "mipslam" / "configs" / "replica.yaml") in err
    assert main(["run", str(tmp_path)]) == 2
    assert "is a folder" in error_line(capsys)


# ----------------------------------------------------------------------------- other commands keep earlier results

def test_eval_out_never_replaces_a_file_that_is_not_metrics(tmp_path, capsys):
    from mipslam.io.tum import write_tum_trajectory
    import numpy as np

    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = np.arange(5) * 0.1
    write_tum_trajectory(tmp_path / "gt.txt", np.arange(5.0), poses)
    write_tum_trajectory(tmp_path / "est.txt", np.arange(5.0), poses)
    before = (tmp_path / "est.txt").read_text()
    argv = ["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"), "--out"]
    assert main(argv + [str(tmp_path / "est.txt")]) == 2
    assert "not a metrics file" in error_line(capsys)
    assert (tmp_path / "est.txt").read_text() == before


def test_export_never_writes_over_the_runs_files_or_an_existing_mesh(partial_run, tmp_path, capsys):
    map_before = (partial_run / "map.ply").read_bytes()
    assert main(["export", str(partial_run), "--mesh", str(partial_run / "map.ply")]) == 2
    assert "one of the run's own files" in error_line(capsys)
    assert (partial_run / "map.ply").read_bytes() == map_before
    mesh = tmp_path / "mesh.ply"
    mesh.write_text("an earlier mesh")
    assert main(["export", str(partial_run), "--mesh", str(mesh)]) == 2
    assert "--overwrite" in error_line(capsys) and mesh.read_text() == "an earlier mesh"


def test_synth_into_a_folder_that_is_not_empty(tmp_path, capsys):
    out = tmp_path / "seq"
    argv = ["-q", "synth", "--out", str(out), "--width", "16", "--height", "12", "--frames", "2", "--supersample", "1"]
    assert main(argv) == 0
    assert main(argv) == 2
    assert "--overwrite" in error_line(capsys)
    assert main(argv + ["--overwrite"]) == 0
    (out / "notes.txt").write_text("mine")
    assert main(argv + ["--overwrite"]) == 0  # only what synth writes is replaced
    assert (out / "notes.txt").read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert main(argv[:3] + [str(other)] + argv[4:] + ["--overwrite"]) == 2
    assert (other / "notes.txt").read_text() == "mine"
