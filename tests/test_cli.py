"""Smoke test over every CLI command and its error path: one line on stderr, exit code 2, no traceback."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mipslam import __version__
from mipslam.cli import main

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
    assert main(["config", str(REPO / "configs" / "tum.yaml"), "--preset", "fast", "--set", "tracking.iterations=7"]) == 0
    out = capsys.readouterr().out
    assert "iterations: 7" in out and "kind: tum" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["config", "nope.yaml"], "config file not found"),
        (["config", str(REPO / "configs" / "base.yaml"), "--set", "mapping.iteratoins=3"], "did you mean 'mapping.iterations'"),
        (["run"], "required: config"),
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
