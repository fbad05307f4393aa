"""Bad input (docs/robustness.md): the dataset cases not covered by test_datasets_errors.py, and the CLI's
nonexistent paths, unwritable run folders and a disk that fills up while outputs are written.

Every case ends in a DatasetError naming the file (and line), or in exit code 2 with one line on
stderr naming the file, and never leaves a partial file under a final name.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import data_synth
import mipslam.io.run_folder as run_folder
from mipslam.checkpoint import list_checkpoints, load_latest_checkpoint
from mipslam.cli import main
from mipslam.config import DatasetConfig
from mipslam.datasets import ReplicaSequence, TUMSequence, make_sequence
from mipslam.errors import DatasetError
from test_datasets import H, W, tum_cfg, write_replica, write_tum

TINY = ["mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
        "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1"]


def expect_dataset_error(fn, path: Path, *, line: int | None = None, match: str) -> None:
    with pytest.raises(DatasetError) as info:
        fn()
    assert info.value.path == path, str(info.value)
    assert info.value.line == line, str(info.value)
    assert str(info.value).startswith(f"{path}:{line}: " if line is not None else f"{path}: ")
    assert match in str(info.value), str(info.value)


def replace_line(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")


def field_of_line(path: Path, line: int, index: int) -> str:
    return path.read_text().splitlines()[line - 1].split()[index]


# ----------------------------------------------------------------------------- datasets: the rest of the bad-input cases

def _tum_case(case: str, root: Path):
    """Damage a fresh 4-frame TUM folder; returns (how to trigger the error, file, line, message)."""
    write_tum(root, n=4)
    open_tum = lambda: TUMSequence(root, tum_cfg(root))  # noqa: E731
    gt, rgb, depth = root / "groundtruth.txt", root / "rgb.txt", root / "depth.txt"
    if case == "ground truth with NaN position":
        replace_line(gt, 5, f"{field_of_line(gt, 5, 0)} 1 nan 3 0 0 0 1")
        return open_tum, gt, 5, "'ty' is not finite"
    if case == "ground truth with NaN quaternion":
        replace_line(gt, 5, f"{field_of_line(gt, 5, 0)} 1 2 3 0 0 nan 1")
        return open_tum, gt, 5, "'qz' is not finite"
    if case == "ground truth short line":
        replace_line(gt, 5, f"{field_of_line(gt, 5, 0)} 1 2")
        return open_tum, gt, 5, "expected 8 numbers"
    if case == "ground truth without poses":
        gt.write_text("# timestamp tx ty tz qx qy qz qw\n")
        return open_tum, gt, None, "no poses"
    if case == "duplicate colour timestamp":
        replace_line(rgb, 4, rgb.read_text().splitlines()[2])
        return open_tum, rgb, 4, "duplicate timestamp"
    if case == "unsorted depth timestamps":
        replace_line(depth, 4, "999.0 " + field_of_line(depth, 4, 1))
        return open_tum, depth, 4, "not sorted"
    if case == "binary list file":
        rgb.write_bytes(b"\xff\xfe\x00 not text")
        return open_tum, rgb, None, "not a text file"
    second_depth = sorted((root / "depth").iterdir())[1]
    if case == "depth listed but missing":
        second_depth.unlink()
        return open_tum, second_depth, None, "missing on disk"
    if case == "8-bit depth":
        cv2.imwrite(str(second_depth), np.full((H, W), 100, np.uint8))
        return lambda: open_tum()[1], second_depth, None, "must be 16-bit"
    if case == "depth larger than colour":
        cv2.imwrite(str(second_depth), np.full((H + 2, W), 1000, np.uint16))
        return lambda: open_tum()[1], second_depth, None, "colour and depth must be registered at the same size"
    raise AssertionError(case)


TUM_CASES = ["ground truth with NaN position", "ground truth with NaN quaternion", "ground truth short line",
             "ground truth without poses", "duplicate colour timestamp", "unsorted depth timestamps",
             "binary list file", "depth listed but missing", "8-bit depth", "depth larger than colour"]


@pytest.mark.parametrize("case", TUM_CASES)
def test_tum_bad_input_is_a_dataset_error_naming_file_and_line(tmp_path, case):
    trigger, path, line, match = _tum_case(case, tmp_path / "tum")
    expect_dataset_error(trigger, path, line=line, match=match)


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("fx", 0.0, "camera.fx must be positive"),  # would divide by zero in every projection
        ("fy", -21.0, "camera.fy must be positive"),
        ("scale", 0, "camera.scale must be positive"),  # was reported against the first depth image
        ("w", 16.5, "camera.w must be a whole number of pixels"),  # was silently truncated to 16
        ("h", 0, "camera.h must be a whole number of pixels"),
    ],
)
def test_replica_camera_parameters_out_of_range(tmp_path, key, value, match):
    root = tmp_path / "rep"
    write_replica(root, n=2)
    params = json.loads((root / "cam_params.json").read_text())
    params["camera"][key] = value
    (root / "cam_params.json").write_text(json.dumps(params))
    expect_dataset_error(lambda: ReplicaSequence(root, DatasetConfig(kind="replica", path=str(root))),
                         root / "cam_params.json", match=match)


@pytest.fixture(scope="module")
def synthetic_folder(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth") / "seq"
    data_synth.generate(root, width=16, height=12, frames=2, supersample=1)
    return root


@pytest.mark.parametrize(
    "change, match",
    [
        ({"intrinsics": {"fx": -5.0}}, "intrinsics.fx must be positive"),  # was a ConfigError blaming dataset.fx
        ({"intrinsics": {"width": 0}}, "intrinsics.width must be a whole number"),
        ({"intrinsics": {"width": 17}}, "intrinsics say 17x12 but the images are 16x12"),  # was blamed on dataset.width
        ({"intrinsics": {"fy": float("nan")}}, "intrinsics.fy must be a finite number"),
        ({"depth_scale": 0}, "depth_scale must be a positive number"),
        ({"format_version": 7}, "format_version 7 is not supported"),
    ],
)
def test_synth_json_out_of_range_names_synth_json(tmp_path, synthetic_folder, change, match):
    root = tmp_path / "seq"
    shutil.copytree(synthetic_folder, root)
    meta = json.loads((root / "synth.json").read_text())
    for key, value in change.items():
        meta[key] = {**meta[key], **value} if isinstance(value, dict) else value
    (root / "synth.json").write_text(json.dumps(meta))
    expect_dataset_error(lambda: make_sequence(DatasetConfig(kind="synthetic", path=str(root))),
                         root / "synth.json", match=match)


def test_truncated_synth_json_names_the_line(tmp_path, synthetic_folder):
    root = tmp_path / "seq"
    shutil.copytree(synthetic_folder, root)
    (root / "synth.json").write_text('{"format_version": 1,\n "layout": "replica",\n')
    expect_dataset_error(lambda: make_sequence(DatasetConfig(kind="synthetic", path=str(root))),
                         root / "synth.json", line=3, match="invalid JSON")


# ----------------------------------------------------------------------------- the CLI: one line, exit code 2

@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "seq"
    data_synth.generate(out, layout="replica", trajectory="loop", width=40, height=30, frames=4, seed=0, supersample=2)
    return out


def run_argv(sequence: Path, *extra: str, out: Path | None = None, resume: Path | None = None) -> list[str]:
    argv = ["-q", "run", "synthetic", "--no-eval"]  # -q: warnings and errors only
    argv += ["--out", str(out)] if out is not None else []
    argv += ["--resume", str(resume)] if resume is not None else []
    for item in (f"dataset.path={sequence}", *TINY, *extra):
        argv += ["--set", item]
    return argv


def one_line_error(capsys) -> str:
    """The one ``error:`` line on stderr (the last line; warnings logged before it start with ``mipslam:``)."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines and lines[-1].startswith("error: "), lines
    assert all(line.startswith("mipslam: ") for line in lines[:-1]), lines  # log lines only, no traceback
    return lines[-1]


def test_nonexistent_dataset_path(tmp_path, capsys):
    missing = tmp_path / "no_such_sequence"
    assert main(run_argv(missing, out=tmp_path / "run")) == 2
    assert str(missing) in one_line_error(capsys)


def test_resume_of_a_folder_without_checkpoints(tmp_path, tiny_sequence, capsys):
    empty = tmp_path / "empty_run"
    empty.mkdir()
    assert main(run_argv(tiny_sequence, resume=empty)) == 2
    err = one_line_error(capsys)
    assert str(empty) in err and "checkpoint" in err


def test_resume_of_a_nonexistent_folder_creates_nothing(tmp_path, tiny_sequence, capsys):
    typo = tmp_path / "runs" / "typo"
    assert main(run_argv(tiny_sequence, resume=typo)) == 2
    err = one_line_error(capsys)
    assert str(typo) in err
    assert not (tmp_path / "runs").exists(), "--resume of a mistyped folder created it"


def test_eval_and_export_of_nonexistent_run_folders(tmp_path, capsys):
    missing = tmp_path / "missing_run"
    assert main(["eval", str(missing)]) == 2
    assert str(missing) in one_line_error(capsys)
    assert main(["export", str(missing), "--mesh", str(tmp_path / "mesh.ply")]) == 2
    assert str(missing) in one_line_error(capsys)
    assert not (tmp_path / "mesh.ply").exists()


def test_run_folder_under_a_file(tmp_path, tiny_sequence, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert main(run_argv(tiny_sequence, out=blocker / "run")) == 2
    err = one_line_error(capsys)
    assert str(blocker / "run") in err and "cannot create the run folder" in err
    assert blocker.read_text() == "not a folder"


def test_run_folder_not_writable(tmp_path, tiny_sequence, capsys, monkeypatch):
    """A read-only folder (simulated: root ignores permission bits, so the first file creation is refused)."""
    real_mkstemp = run_folder.tempfile.mkstemp
    run_dir = tmp_path / "readonly_run"

    def refuse(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve().is_relative_to(run_dir.resolve()):
            raise PermissionError(errno.EACCES, "Permission denied")
        return real_mkstemp(*args, dir=dir, **kwargs)

    monkeypatch.setattr(run_folder.tempfile, "mkstemp", refuse)
    assert main(run_argv(tiny_sequence, out=run_dir)) == 2
    err = one_line_error(capsys)
    assert str(run_dir) in err and "not writable" in err and "Permission denied" in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders; the simulated test above covers it")
def test_run_folder_read_only_for_real(tmp_path, tiny_sequence, capsys):
    run_dir = tmp_path / "ro"
    run_dir.mkdir()
    run_dir.chmod(0o555)
    try:
        assert main(run_argv(tiny_sequence, out=run_dir)) == 2
        assert "not writable" in one_line_error(capsys) or "cannot create" in capsys.readouterr().err
    finally:
        run_dir.chmod(0o755)


# ----------------------------------------------------------------------------- disk full while writing outputs

class _DiskFullAfter:
    """A file object that accepts ``budget`` bytes and then fails like a full disk (ENOSPC)."""

    def __init__(self, handle, budget: int):
        self._handle, self._budget = handle, budget

    def write(self, data) -> int:
        data = bytes(data)
        if len(data) > self._budget:
            self._handle.write(data[: self._budget])  # a partial file really is on disk
            self._handle.flush()
            self._budget = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self._budget -= len(data)
        return self._handle.write(data)

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self._handle.__exit__(*exc)


class _OsWithFullDisk:
    """``os`` for mipslam.io.run_folder, whose ``fdopen`` fills the disk while writing files named ``victim``."""

    def __init__(self, victim: str, budget: int):
        self._victim, self._budget = victim, budget
        self.hits: list[str] = []

    def fdopen(self, fd, *args, **kwargs):
        handle = os.fdopen(fd, *args, **kwargs)
        name = os.readlink(f"/proc/self/fd/{fd}")
        if Path(name).name.startswith(f".{self._victim}."):
            self.hits.append(name)
            return _DiskFullAfter(handle, self._budget)
        return handle

    def __getattr__(self, name):
        return getattr(os, name)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, tiny_sequence) -> Path:
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    assert main(run_argv(tiny_sequence, "run.checkpoint_every=2", out=run_dir)) == 0
    return run_dir


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd to tell which file is written")
@pytest.mark.parametrize("victim", [
    "config.yaml", "checkpoint", "frames.json", "map.ply", "timings.json", "run.json",
    "traj_est.txt",
])
def test_disk_full_while_writing_outputs(tmp_path, finished_run, tiny_sequence, capsys, monkeypatch, victim):
    """``--resume`` of a run killed while writing its outputs (after its final checkpoint) rewrites its
    checkpoint and outputs; the disk fills up while one of them is written: exit 2, one line naming that
    file, its previous complete version byte-identical, no temporary file left behind, and the run still
    resumable."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    (run_dir / "keyframes.txt").unlink()  # an output missing: the run is not complete, so --resume has work to do
    before = snapshot(run_dir)
    checkpoints = list_checkpoints(run_dir / "checkpoints")
    if victim == "checkpoint":
        serial = int(checkpoints[-1].name.split("-")[1].split(".")[0]) + 1
        victim = f"checkpoint-{serial:06d}.ckpt"
        target = run_dir / "checkpoints" / victim
    else:
        target = run_dir / victim
    full_disk = _OsWithFullDisk(victim, budget=100)
    monkeypatch.setattr(run_folder, "os", full_disk)
    assert main(run_argv(tiny_sequence, resume=run_dir)) == 2
    err = one_line_error(capsys)
    monkeypatch.undo()
    assert len(full_disk.hits) == 1, f"{victim} was written {len(full_disk.hits)} times"
    assert err.startswith(f"error: {target}: write failed (No space left on device)"), err
    after = snapshot(run_dir)
    assert not [name for name in after if name.endswith(".tmp")], "a temporary file was left behind"
    relative = str(target.relative_to(run_dir))
    assert after.get(relative) == before.get(relative), f"{relative} is not its previous complete version"
    assert set(before) - {str(p.relative_to(run_dir)) for p in checkpoints} <= set(after), "a complete output vanished"
    # the run is still resumable from its last complete checkpoint, and then writes everything
    assert load_latest_checkpoint(run_dir / "checkpoints").metadata["next_frame"] == 4
    assert main(run_argv(tiny_sequence, resume=run_dir)) == 0
    assert snapshot(run_dir)["map.ply"] == before["map.ply"]


# ----------------------------------------------------------------------------- a frame that cannot be read mid-run

@pytest.fixture
def sequence_with_broken_frame(tmp_path, tiny_sequence) -> tuple[Path, Path, bytes]:
    root = tmp_path / "seq"
    shutil.copytree(tiny_sequence, root)
    broken = root / "results" / "frame000002.png"
    original = broken.read_bytes()
    broken.write_bytes(original[: len(original) // 2])  # a truncated copy
    return root, broken, original


def test_unreadable_frame_mid_run_is_one_line_naming_the_file(tmp_path, sequence_with_broken_frame, capsys):
    root, broken, _ = sequence_with_broken_frame
    assert main(run_argv(root, "run.checkpoint_every=0", out=tmp_path / "run")) == 2
    err = one_line_error(capsys)
    assert err.startswith(f"error: {broken}: ") and "truncated" in err, err
    assert not (tmp_path / "run" / "map.ply").exists() and not (tmp_path / "run" / "traj_est.txt").exists()


def test_unreadable_frame_mid_run_keeps_the_finished_frames(tmp_path, sequence_with_broken_frame, finished_run, capsys):
    """Frames 0 and 1 were done when frame 2 turned out unreadable: they are checkpointed, so after the
    file is fixed ``--resume`` continues at frame 2 and ends where an uninterrupted run ends."""
    root, broken, original = sequence_with_broken_frame
    run_dir = tmp_path / "run"
    assert main(run_argv(root, "run.checkpoint_every=0", out=run_dir)) == 2
    capsys.readouterr()
    assert load_latest_checkpoint(run_dir / "checkpoints").metadata["next_frame"] == 2
    broken.write_bytes(original)
    assert main(run_argv(root, resume=run_dir)) == 0
    assert (run_dir / "map.ply").read_bytes() == (finished_run / "map.ply").read_bytes()
    assert (run_dir / "traj_est.txt").read_bytes() == (finished_run / "traj_est.txt").read_bytes()
