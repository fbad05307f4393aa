"""Interrupted runs (docs/robustness.md): ``mipslam run`` killed with SIGKILL at chosen moments (inside tracking,
mapping and a checkpoint write) and resumed gives exactly the uninterrupted run; Ctrl-C inside
mapping too. The trials are those of the kill_resume benchmark scenario (which runs 20 and more),
with a fixed seed; the reference and the resumes run in this process to save interpreter start-ups."""
from __future__ import annotations

import random

import pytest

from mipslam.bench.scenarios import kill_resume


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    return kill_resume.prepare(tmp_path_factory.mktemp("kill_resume"), frames=10, reference_in_process=True)


@pytest.mark.slow
def test_three_sigkill_trials_resume_to_the_uninterrupted_run(setup):
    workdir = setup.reference.parent
    _, results = kill_resume.run_trials(workdir, trials=3, seed=3, setup=setup,
                                        strategies=("tracking", "mapping", "checkpoint"), in_process_resume=True)
    print(kill_resume.format_table(setup, results))
    assert [r.strategy for r in results] == ["tracking", "mapping", "checkpoint"]
    for r in results:
        assert r.ok, r
        assert r.resume_exit_code == 0 and r.pose_diff <= 1e-6 and r.map_diff <= 1e-5
        assert r.checkpoints_at_end <= 3
    # the kills landed where they were aimed (the child reports its phase through the marker file)
    assert [r.phase_at_kill for r in results] == ["tracking", "mapping", "checkpoint"]


@pytest.mark.slow
@pytest.mark.parametrize("keyframe", [1, 2], ids=["first keyframe", "second keyframe"])
def test_ctrl_c_inside_mapping_saves_a_checkpoint_that_resumes_to_the_same_run(setup, keyframe):
    """Today Ctrl-C inside mapping checkpoints a half-done frame: inside the first keyframe's mapping a
    checkpoint with an empty map (the resumed run then tracks against nothing: 3 cm off), inside a later
    one a checkpoint that cannot be resumed ("loop closure got keyframe 1 but holds 0 descriptors")."""
    assert setup.keyframes >= 2
    workdir = setup.reference.parent
    result = kill_resume.run_trial(setup, workdir, 90 + keyframe, "ctrl-c:mapping", random.Random(keyframe),
                                   in_process_resume=True, occurrence=keyframe)
    print(kill_resume.format_table(setup, [result]))
    assert not result.finished_before_kill
    assert result.ok, result


@pytest.mark.slow
def test_corrupt_newest_checkpoint_falls_back_and_the_run_still_ends_identical(setup, tmp_path, caplog, monkeypatch):
    """Checkpoints after frames 2, 4 and 5; the newest is truncated (a power cut on a file system that
    lies about fsync): --resume warns, continues from frame 4's and ends as the uninterrupted run."""
    import logging

    from mipslam.checkpoint import list_checkpoints
    from mipslam.config import load_config
    from mipslam.pipeline import run_slam

    run_dir = tmp_path / "run"
    from mipslam import run_control

    monkeypatch.setattr(run_control, "KEEP_CHECKPOINTS", 3)
    overrides = [f"dataset.path={setup.sequence}", *setup.settings]
    run_slam(load_config(setup.config, overrides=[*overrides, "dataset.max_frames=5"]), run_dir, evaluate=False)
    files = list_checkpoints(run_dir / "checkpoints")
    assert len(files) == 3
    newest = files[-1]
    newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 2])
    with caplog.at_level(logging.WARNING, logger="mipslam"):
        run_slam(load_config(setup.config, overrides=overrides), run_dir, resume=True, evaluate=False)
    messages = [r.getMessage() for r in caplog.records]
    assert any(newest.name in m and ("checksum" in m or "truncated" in m) for m in messages), messages
    assert any("resuming from older checkpoint" in m and files[-2].name in m for m in messages), messages
    diff = kill_resume.compare_runs(setup.reference, run_dir)
    assert diff["same"], diff
    assert diff["pose_diff"] == 0.0 and diff["map_diff"] == 0.0
