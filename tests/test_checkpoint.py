"""Checkpoints: exact round trip, atomicity under crashes, corruption fallback, no unpickling,
config compatibility, RNG capture; the run folder and its atomic writes."""
from __future__ import annotations

import json
import logging
import os
import pickle
import random
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

from mipslam.checkpoint import (
    FORMAT_VERSION,
    capture_rng_state,
    check_config_compatible,
    config_differences,
    free_config_differences,
    list_checkpoints,
    load_latest_checkpoint,
    read_checkpoint,
    read_checkpoint_header,
    restore_rng_state,
    save_checkpoint,
    select_prefix,
    with_prefix,
    write_checkpoint,
)
from mipslam.config import Config, config_from_dict, config_to_dict
from mipslam.errors import CheckpointError, MipslamError
from mipslam.gaussians import GaussianMap, GaussianOptimizer, GaussianParameters
from mipslam.io.run_folder import RUN_ENTRIES, RunFolder, prepare_new_run_folder, write_json_atomic, write_text_atomic

CONFIG = config_to_dict(Config())


def sample_tensors(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "map.means": torch.randn(100, 3, generator=g),
        "poses": torch.randn(7, 4, 4, generator=g, dtype=torch.float64),
        "half": torch.randn(5, generator=g).to(torch.bfloat16),
        "fp16": torch.randn(2, 2, generator=g).half(),
        "ids": torch.randint(-5, 10**12, (9,), generator=g),
        "flags": torch.rand(6, generator=g) > 0.5,
        "bytes": torch.randint(0, 255, (11,), generator=g, dtype=torch.uint8),
        "scalar": torch.tensor(3.25),
        "empty": torch.zeros(0, 3),
        "strided": torch.arange(12.0).reshape(3, 4).T,  # not contiguous
    }


def assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert list(a) == list(b)
    for name in a:
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        assert torch.equal(a[name], b[name]), name


def test_round_trip_is_exact(tmp_path):
    tensors = sample_tensors()
    metadata = {"frame_index": 41, "keyframes": [0, 5, 9], "loss": 0.125, "flagged": [], "name": "run"}
    path = write_checkpoint(tmp_path / "checkpoint-000001.ckpt", tensors, metadata, CONFIG)
    loaded = read_checkpoint(path)
    assert_same(tensors, loaded.tensors)
    assert loaded.metadata == metadata and loaded.config == CONFIG
    assert loaded.format_version == FORMAT_VERSION and loaded.serial == 1 and loaded.created_utc
    # loaded tensors are independent, writable copies
    loaded.tensors["map.means"][0, 0] = 1e6
    assert read_checkpoint(path).tensors["map.means"][0, 0] != 1e6


def test_non_tensor_entries_and_bad_metadata_are_refused(tmp_path):
    with pytest.raises(CheckpointError, match="not a tensor"):
        write_checkpoint(tmp_path / "c.ckpt", {"x": [1, 2]}, {}, CONFIG)
    with pytest.raises(CheckpointError, match="not JSON-serialisable"):
        write_checkpoint(tmp_path / "c.ckpt", {}, {"obj": object()}, CONFIG)
    assert list(tmp_path.iterdir()) == []


def test_only_a_bounded_number_is_kept(tmp_path):
    for i in range(5):
        save_checkpoint(tmp_path, {"i": torch.tensor(i)}, {"i": i}, config=CONFIG, keep=2)
    names = [p.name for p in list_checkpoints(tmp_path)]
    assert names == ["checkpoint-000004.ckpt", "checkpoint-000005.ckpt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == names  # no temporaries left
    assert load_latest_checkpoint(tmp_path).metadata == {"i": 4}


def test_crash_before_rename_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    save_checkpoint(tmp_path, {"x": torch.ones(3)}, {"step": 1}, config=CONFIG, keep=1)

    def crash(src, dst):
        raise KeyboardInterrupt  # Ctrl-C (or a crash) after the data was written, before the rename

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, {"x": torch.zeros(3)}, {"step": 2}, config=CONFIG, keep=1)
    monkeypatch.undo()
    loaded = load_latest_checkpoint(tmp_path)
    assert loaded.metadata == {"step": 1} and torch.equal(loaded.tensors["x"], torch.ones(3))
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint-000001.ckpt"]


def test_partial_temporary_from_a_killed_writer_is_ignored(tmp_path):
    first = save_checkpoint(tmp_path, {"x": torch.ones(1000)}, {"step": 1}, config=CONFIG)
    second = write_checkpoint(tmp_path / "scratch.ckpt", {"x": torch.zeros(1000)}, {"step": 2}, CONFIG)
    # what a power cut mid-write leaves: half a file under a temporary name
    (tmp_path / ".checkpoint-000002.ckpt.x1y2.tmp").write_bytes(second.read_bytes()[:2000])
    second.unlink()
    assert load_latest_checkpoint(tmp_path).path == first
    assert list_checkpoints(tmp_path) == [first]


KILL_WRITER = textwrap.dedent(
    """
    import sys, torch
    from mipslam.checkpoint import save_checkpoint
    for i in range(1, 100000):
        values = torch.full((1_000_000,), float(i))  # 4 MB per checkpoint
        save_checkpoint(sys.argv[1], {"values": values}, {"i": i}, config={"seed": 0}, keep=2)
        if i == 1:
            print("ready", flush=True)
    """
)


@pytest.mark.slow
def test_kill_9_during_checkpoint_writes_leaves_a_loadable_checkpoint(tmp_path):
    rng = random.Random(7)
    for trial in range(2):
        folder = tmp_path / f"trial{trial}"
        process = subprocess.Popen([sys.executable, "-c", KILL_WRITER, str(folder)], stdout=subprocess.PIPE, text=True)
        try:
            assert process.stdout.readline().strip() == "ready"
            time.sleep(rng.uniform(0.05, 0.6))
        finally:
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=30)
        loaded = load_latest_checkpoint(folder)
        i = loaded.metadata["i"]
        assert i >= 1 and torch.equal(loaded.tensors["values"], torch.full((1_000_000,), float(i)))
        assert len(list_checkpoints(folder)) <= 3  # keep=2, plus one if killed between rename and pruning


@pytest.mark.parametrize("damage", ["flip_byte", "truncate", "empty"])
def test_corrupt_latest_checkpoint_is_reported_and_the_previous_used(tmp_path, caplog, damage):
    save_checkpoint(tmp_path, sample_tensors(1), {"step": 1}, config=CONFIG, keep=3)
    latest = save_checkpoint(tmp_path, sample_tensors(2), {"step": 2}, config=CONFIG, keep=3)
    data = bytearray(latest.read_bytes())
    if damage == "flip_byte":
        data[len(data) // 2] ^= 0x40
    elif damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data = bytearray()
    latest.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=str(latest.name)):
        read_checkpoint(latest)
    with caplog.at_level(logging.WARNING, logger="mipslam.checkpoint"):
        loaded = load_latest_checkpoint(tmp_path)
    assert loaded.metadata == {"step": 1}
    assert_same(loaded.tensors, sample_tensors(1))
    assert any(latest.name in record.getMessage() and record.levelno == logging.WARNING for record in caplog.records)


def test_no_usable_checkpoint_is_an_error(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint found"):
        load_latest_checkpoint(tmp_path)
    (tmp_path / "checkpoint-000001.ckpt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="no usable checkpoint"):
        load_latest_checkpoint(tmp_path)


class _Payload:
    """Unpickling this creates the file ``marker`` (stands in for arbitrary code execution)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_planted_pickle_payload_is_never_executed(tmp_path):
    # the payload is live: a plain unpickler would run it
    probe = tmp_path / "probe_marker"
    pickle.loads(pickle.dumps(_Payload(probe))).close()
    assert probe.exists()

    folder = tmp_path / "checkpoints"
    good = save_checkpoint(folder, {"x": torch.arange(3)}, {"step": 1}, config=CONFIG)
    marker = tmp_path / "pwned"
    (folder / "checkpoint-000002.ckpt").write_bytes(pickle.dumps({"state": _Payload(marker)}))
    torch.save({"state": _Payload(marker)}, folder / "checkpoint-000003.ckpt")
    with pytest.raises(CheckpointError, match="pickle"):
        read_checkpoint(folder / "checkpoint-000002.ckpt")
    with pytest.raises(CheckpointError, match="torch.save"):
        read_checkpoint(folder / "checkpoint-000003.ckpt")
    assert load_latest_checkpoint(folder).path == good
    assert not marker.exists()


def test_other_format_version_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr("mipslam.checkpoint.FORMAT_VERSION", FORMAT_VERSION + 1)
    path = write_checkpoint(tmp_path / "checkpoint-000001.ckpt", {"x": torch.ones(1)}, {}, CONFIG)
    monkeypatch.undo()
    with pytest.raises(CheckpointError, match=f"format version {FORMAT_VERSION + 1}"):
        read_checkpoint(path)


def test_incompatible_config_is_refused_naming_the_keys(tmp_path):
    save_checkpoint(tmp_path, {"x": torch.ones(1)}, {}, config=CONFIG)
    changed = config_to_dict(config_from_dict({"render": {"mode": "point"}, "dataset": {"stride": 2}}))
    with pytest.raises(CheckpointError) as info:
        load_latest_checkpoint(tmp_path, current_config=changed)
    message = str(info.value)
    assert "render.mode: checkpoint 'eaa', now 'point'" in message and "dataset.stride" in message
    assert "checkpoint-000001.ckpt" in message
    # settings that do not change the result may differ
    free = config_to_dict(config_from_dict({"run": {"checkpoint_every": 7, "diagnostics": True, "threads": 1},
                                            "eval": {"alignment": "sim3"}, "dataset": {"max_frames": 99}}))
    assert load_latest_checkpoint(tmp_path, current_config=free).tensors["x"].item() == 1.0
    # a key missing on one side (a config from another version) counts as a difference
    assert config_differences({"a": {"b": 1}}, {"a": {"b": 1, "c": (1, 2)}}) == ["a.c: checkpoint <absent>, now [1, 2]"]
    assert config_differences({"a": {"b": [1, 2]}}, {"a": {"b": (1, 2)}}) == []
    check_config_compatible(CONFIG, dict(CONFIG))


def test_config_comparison_takes_one_folder_written_two_ways_as_one_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seq").mkdir()
    saved = {"dataset": {"path": str(tmp_path / "seq")}, "run": {"threads": 0}}
    for same in ("seq", "./seq/", str(tmp_path / "seq") + "/", str(tmp_path / "x" / ".." / "seq")):
        assert config_differences(saved, {"dataset": {"path": same}, "run": {"threads": 0}}) == [], same
    assert config_differences(saved, {"dataset": {"path": "other"}, "run": {"threads": 0}}) == [
        f"dataset.path: checkpoint {str(tmp_path / 'seq')!r}, now {str(tmp_path / 'other')!r}"]
    # keys that cannot change results may differ; they are reported, not refused
    changed = {"dataset": {"path": "seq"}, "run": {"threads": 2}}
    assert config_differences(saved, changed) == []
    assert free_config_differences(saved, changed) == ["run.threads: 0 -> 2"]


def test_changed_free_settings_are_logged_on_resume(tmp_path, caplog):
    save_checkpoint(tmp_path, {"x": torch.ones(1)}, {}, config=CONFIG)
    current = config_to_dict(config_from_dict({"run": {"threads": 1, "checkpoint_every": 0}}))
    with caplog.at_level(logging.INFO, logger="mipslam.checkpoint"):
        load_latest_checkpoint(tmp_path, current_config=current)
    assert "run.threads: 0 -> 1" in caplog.text and "run.checkpoint_every: 50 -> 0" in caplog.text


def test_the_header_is_read_without_the_payload(tmp_path):
    path = save_checkpoint(tmp_path, sample_tensors(), {"next_frame": 7}, config=CONFIG)
    header = read_checkpoint_header(path)
    assert header["metadata"] == {"next_frame": 7} and header["config"] == CONFIG
    with path.open("r+b") as handle:  # damage in the payload does not hide the header (the full read refuses it)
        handle.seek(-40, os.SEEK_END)
        handle.write(b"\xff" * 8)
    assert read_checkpoint_header(path)["metadata"]["next_frame"] == 7
    with pytest.raises(CheckpointError, match="checksum"):
        read_checkpoint(path)
    (tmp_path / "other.ckpt").write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(CheckpointError, match="pickle"):
        read_checkpoint_header(tmp_path / "other.ckpt")


def test_rng_states_are_restored_exactly_through_a_checkpoint(tmp_path):
    generator = torch.Generator().manual_seed(123)
    torch.manual_seed(1), np.random.seed(2), random.seed(3)
    random.gauss(0, 1)  # leaves a cached gaussian in Python's state
    tensors, meta = capture_rng_state({"keyframes": generator})

    def draw():
        return (torch.rand(4).tolist(), np.random.rand(4).tolist(), np.random.randn(), [random.random() for _ in range(4)],
                random.gauss(0, 1), torch.randperm(10, generator=generator).tolist())

    expected = draw()
    path = write_checkpoint(tmp_path / "checkpoint-000001.ckpt", tensors, {"rng": meta}, CONFIG)
    draw()  # advance everything
    loaded = read_checkpoint(path)
    restore_rng_state(loaded.tensors, loaded.metadata["rng"], {"keyframes": generator})
    assert draw() == expected
    with pytest.raises(CheckpointError, match="random state"):
        restore_rng_state({}, loaded.metadata["rng"])


def test_map_and_optimizer_resume_through_a_checkpoint(tmp_path):
    g = torch.Generator().manual_seed(0)
    n = 30
    gmap = GaussianMap(GaussianParameters(
        means=torch.randn(n, 3, generator=g), quats_wxyz=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 2, opacity_logits=torch.randn(n, generator=g),
        colors_raw=torch.randn(n, 3, generator=g), anchor_keyframe=torch.arange(n) % 4, created_frame=torch.arange(n),
    ))
    lrs = {"means": 1e-2, "quats_wxyz": 1e-2, "log_scales": 1e-2, "opacity_logits": 1e-1, "colors_raw": 1e-2}
    opt = GaussianOptimizer(gmap, lrs)

    def train(m: GaussianMap, o: GaussianOptimizer, steps: int) -> None:
        for _ in range(steps):
            o.zero_grad()
            a = m.activated()
            ((a.means - 0.5) ** 2).sum().add((a.colors - a.opacities[:, None]).pow(2).sum()).add(a.scales.sum()).backward()
            o.step()

    train(gmap, opt, 3)
    gmap.remove(torch.arange(n) % 5 == 0, optimizer=opt)
    tensors = {**with_prefix("map", gmap.state_dict()), **with_prefix("optim", opt.state_dict())}
    save_checkpoint(tmp_path, tensors, {"frame_index": 3}, config=CONFIG)

    loaded = load_latest_checkpoint(tmp_path, current_config=CONFIG)
    resumed = GaussianMap.from_state_dict(select_prefix("map", loaded.tensors))
    resumed_opt = GaussianOptimizer(resumed, {k: 0.0 for k in lrs})
    resumed_opt.load_state_dict(select_prefix("optim", loaded.tensors))
    train(gmap, opt, 5)
    train(resumed, resumed_opt, 5)
    assert_same(gmap.state_dict(), resumed.state_dict())


# ----------------------------------------------------------------------------- run folder


def test_run_folder_layout_and_creation(tmp_path):
    run = RunFolder(tmp_path / "runs" / "a").create()
    assert run.root.is_dir() and run.checkpoints.is_dir() and run.report.is_dir()
    names = {p.name for p in (run.config_yaml, run.traj_est, run.traj_gt, run.keyframes, run.map_ply, run.metrics,
                              run.timings, run.loops)}
    assert names == {"config.yaml", "traj_est.txt", "traj_gt.txt", "keyframes.txt", "map.ply", "metrics.json",
                     "timings.json", "loops.json"}
    assert all(p.parent == run.root for p in (run.config_yaml, run.map_ply, run.checkpoints, run.report))
    assert list(run.root.glob(".write_probe*")) == []


def test_run_folder_that_cannot_be_written_gives_a_clear_error(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(MipslamError, match="not a folder"):
        RunFolder(blocker).create()
    with pytest.raises(MipslamError, match="cannot create the run folder"):
        RunFolder(blocker / "sub").create()

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    run = RunFolder(tmp_path / "ok").create()
    monkeypatch.setattr("tempfile.mkstemp", denied)
    with pytest.raises(MipslamError, match="not writable .Permission denied") as info:
        run.check_writable()
    assert str(run.root) in str(info.value)


def test_atomic_json_and_text_writes(tmp_path, monkeypatch):
    path = write_json_atomic(tmp_path / "metrics.json", {"ate": np.float64(0.5), "per_frame": torch.tensor([1.0, 2.0])})
    assert json.loads(path.read_text()) == {"ate": 0.5, "per_frame": [1.0, 2.0]}
    assert oct(path.stat().st_mode & 0o777) == oct(0o644)
    with pytest.raises(MipslamError, match="'frames\\[1\\].psnr' is not finite"):
        write_json_atomic(tmp_path / "metrics.json", {"frames": [{"psnr": 1.0}, {"psnr": float("nan")}]})
    assert json.loads(path.read_text())["ate"] == 0.5

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(MipslamError, match="No space left on device") as info:
        write_text_atomic(path, "partial")
    assert str(path) in str(info.value)
    monkeypatch.undo()
    assert json.loads(path.read_text())["ate"] == 0.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]


def test_stale_temporaries_are_cleaned(tmp_path):
    run = RunFolder(tmp_path).create()
    stale = [run.root / ".map.ply.abc.tmp", run.checkpoints / ".checkpoint-000003.ckpt.k.tmp"]
    for p in stale:
        p.write_bytes(b"partial")
    keep = run.root / "map.ply"
    keep.write_bytes(b"complete")
    assert sorted(run.remove_stale_temporaries()) == sorted(stale)
    assert keep.exists() and not any(p.exists() for p in stale)


def _finished_run(root) -> RunFolder:
    run = RunFolder(root).create()
    save_checkpoint(run.checkpoints, {"x": torch.ones(1)}, {"next_frame": 3}, config=CONFIG)
    for name in sorted(RUN_ENTRIES - {"checkpoints", "report"}):
        (run.root / name).write_text(name)
    (run.report / "trajectory.png").write_bytes(b"png")
    return run


def test_a_new_run_goes_only_where_nothing_would_be_lost(tmp_path):
    assert prepare_new_run_folder(tmp_path / "new") is False and not (tmp_path / "new").exists()
    (tmp_path / "empty").mkdir()
    assert prepare_new_run_folder(tmp_path / "empty") is True
    (tmp_path / "file").write_text("x")
    with pytest.raises(MipslamError, match="not a folder"):
        prepare_new_run_folder(tmp_path / "file", overwrite=True)
    run = _finished_run(tmp_path / "run")
    with pytest.raises(MipslamError, match=r"holds a finished run \(1 checkpoint.*--resume .*--overwrite.*--out"):
        prepare_new_run_folder(run.root)
    assert RunFolder(run.root).inspect().foreign == ()
    # foreign files: refused even with overwrite, and nothing is deleted
    for foreign in (run.root / "mesh.ply", run.checkpoints / "notes.txt", run.report / "sub"):
        foreign.mkdir() if foreign.name == "sub" else foreign.write_text("mine")
        with pytest.raises(MipslamError, match="did not make"):
            prepare_new_run_folder(run.root, overwrite=True)
        assert foreign.exists() and len(list_checkpoints(run.checkpoints)) == 1
        foreign.rmdir() if foreign.is_dir() else foreign.unlink()
    (run.root / ".map.ply.abc.tmp").write_text("partial")
    assert prepare_new_run_folder(run.root, overwrite=True) is True
    assert run.root.is_dir() and list(run.root.iterdir()) == []
    # a config.yaml in a folder without checkpoints/ is the user's own file
    own = tmp_path / "own"
    own.mkdir()
    (own / "config.yaml").write_text("mine")
    with pytest.raises(MipslamError, match="holds no mipslam run"):
        prepare_new_run_folder(own, overwrite=True)
    # the remains of a run that stopped before its first checkpoint are not a run
    remains = RunFolder(tmp_path / "remains").create()
    remains.config_yaml.write_text("run: {}")
    assert prepare_new_run_folder(remains.root) is True and list(remains.root.iterdir()) == []


def test_an_unstarted_run_removes_only_what_it_created(tmp_path):
    run = RunFolder(tmp_path / "run").create()
    run.config_yaml.write_text("run: {}")
    assert run.remove_if_unstarted(remove_root=True) and not run.root.exists()
    run = RunFolder(tmp_path / "kept").create()
    (run.report / "mine.txt").write_text("x")
    assert not run.remove_if_unstarted(remove_root=True)
    assert (run.report / "mine.txt").exists() and not run.checkpoints.exists()
    started = _finished_run(tmp_path / "started")
    assert not started.remove_if_unstarted(remove_root=True) and started.config_yaml.exists()


def test_a_key_newer_than_the_checkpoint_is_no_difference_at_its_default():
    """A checkpoint written before a config key existed resumes while the key holds its default (the older
    code behaved as the default); any other value of the new key is a difference that changes results."""
    current = config_to_dict(Config())
    saved = json.loads(json.dumps(current))
    del saved["tracking"]["coarse_mode_iterations"]
    assert config_differences(saved, current) == []
    current["tracking"]["coarse_mode_iterations"] = 4
    assert config_differences(saved, current) == ["tracking.coarse_mode_iterations: checkpoint <absent>, now 4"]
