"""``mipslam refine RUN_DIR`` on a tiny finished run (10 frames, 80x60 TUM-layout data_synth sequence with a
rolling shutter, mapped at 40x30): outputs beside the run and never over it, a lower training-view loss, resume
and Ctrl-C giving the map of an uninterrupted refinement, refined keyframe poses, native resolution, the report
and viewer, and the errors."""
from __future__ import annotations

import hashlib
import json
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import data_synth
from mipslam.mapping import MappingOptions
from mipslam import refine_run as refine_module
from mipslam.checkpoint import list_checkpoints, load_latest_checkpoint
from mipslam.cli import main
from mipslam.evaluation.run_files import read_run_config
from mipslam.io.ply import read_map_ply, write_map_ply
from mipslam.io.run_folder import RunFolder, prepare_new_run_folder
from mipslam.io.tum import read_tum_trajectory
from mipslam.pipeline import PipelineHooks, run_slam
from mipslam.refinement import KeyframeRefiner, refine_options
from mipslam.geometry import se3_inverse
from mipslam.losses.photometric import rgbd_masks
from mipslam.refine_run import RefineRequest, refine_run
from tiny_runs import tiny_config


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished, evaluated run with several keyframes and a non-keyframe among MonoGS's novel views."""
    root = tmp_path_factory.mktemp("refine")
    sequence = root / "sequence"
    data_synth.generate(sequence, layout="tum", trajectory="loop", width=80, height=60, frames=10, seed=0,
                        supersample=2, rolling_shutter=0.3)
    config = tiny_config(sequence, "dataset.downscale=2", "dataset.rolling_shutter_readout_s=0.01",
                         "keyframes.covisibility_threshold=0.94")
    run_slam(config, root / "run", hooks=PipelineHooks(constants={"keyframes.translation_ratio": 0.05}))
    return root / "run"


@pytest.fixture
def run_dir(finished_run, tmp_path) -> Path:
    """A copy of the finished run (its dataset shared, read-only)."""
    return Path(shutil.copytree(finished_run, tmp_path / "run"))


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _refine(run: Path, *args: str) -> int:
    return main(["-q", "refine", str(run), "--no-eval", *args])


def _keyframe_count(run: Path) -> int:
    return len(read_tum_trajectory(run / "keyframes.txt"))


# ----------------------------------------------------------------------------- outputs


def test_refine_writes_its_outputs_beside_the_run_and_never_changes_the_runs_own_files(run_dir, capsys):
    before = _hashes(run_dir)
    assert main(["refine", str(run_dir), "--iterations", "6"]) == 0
    out = capsys.readouterr().out
    assert "refined " in out and "6 steps" in out and "mapping resolution 40x30" in out, out
    assert "training views PSNR" in out and "full evaluation, training views" in out and "SLAM map -> refined" in out
    after = _hashes(run_dir)
    # the run's own files are untouched; its report page is rebuilt with the Refinement section
    for name, digest in before.items():
        if name != "report/report.html":
            assert after[name] == digest, name
    refined = run_dir / "refined"
    for name in ("map.ply", "traj_est.txt", "keyframes.txt", "progress.json", "metrics.json"):
        assert (refined / name).is_file(), name
    assert 1 <= len(list_checkpoints(refined / "checkpoints")) <= 2
    # keyframe poses refined (the synthetic config's refine.lr_poses): every frame keeps its timestamp and moves
    # by millimetres at most
    for name in ("traj_est.txt", "keyframes.txt"):
        moved, source = read_tum_trajectory(refined / name), read_tum_trajectory(run_dir / name)
        np.testing.assert_array_equal(moved.timestamps, source.timestamps)
        assert np.abs(moved.T_wc[:, :3, 3] - source.T_wc[:, :3, 3]).max() < 5e-3, name
    assert len(read_map_ply(refined / "map.ply")) == len(read_map_ply(run_dir / "map.ply"))
    progress = json.loads((refined / "progress.json").read_text())
    records = progress["records"]
    assert records[0]["steps"] == 0 and records[0]["seconds"] == 0.0 and records[-1]["steps"] == 6 == progress["steps"]
    assert all(r["training_psnr"] is not None and 1 <= r["training_frames"] <= 8 for r in records)
    assert progress["sessions"][0]["end"] == "budget" and progress["resolution"] == "mapping"
    metrics = json.loads((refined / "metrics.json").read_text())
    assert metrics["evaluation"]["map"] == "refined/map.ply" and metrics["map"]["file"] == "refined/map.ply"
    assert metrics["render"]["protocol"]["map"]["file"] == "refined/map.ply"
    assert metrics["render"]["protocol"]["resolution"] == "native"  # the run's own protocol
    assert metrics["refinement"]["steps"] == 6 and metrics["refinement"]["poses_refined"] is True
    run_metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["trajectory"]["ate"]["rmse"] == pytest.approx(run_metrics["trajectory"]["ate"]["rmse"], abs=2e-3)
    page = (run_dir / "report" / "report.html").read_text()
    assert "Refinement (refined/)" in page and "refinement_psnr.png" in page
    assert (run_dir / "report" / "refinement_psnr.png").stat().st_size > 5_000
    # the run folder knows refined/: not foreign, and a new run over it with --overwrite removes it
    assert RunFolder(run_dir).inspect().foreign == ()
    # mipslam eval keeps the section
    assert main(["-q", "eval", str(run_dir), "--no-render"]) == 0
    assert "Refinement (refined/)" in (run_dir / "report" / "report.html").read_text()
    (run_dir / "metrics_trajectory.json").unlink()  # (a run folder does not count these as its own)
    prepare_new_run_folder(run_dir, overwrite=True)
    assert not refined.exists()


def test_refinement_lowers_the_training_view_loss(run_dir):
    summary = refine_run(run_dir, RefineRequest(iterations=3 * _keyframe_count(run_dir), evaluate=False))
    assert summary.steps == 3 * _keyframe_count(run_dir)
    folder = RunFolder(run_dir)
    config = read_run_config(folder)
    start = refine_module._load_start(folder, config)
    sequence = refine_module._open_sequence(config, "mapping")
    load = refine_module._keyframe_loader(sequence, start.state, torch.device("cpu"), start.keyframes)

    def mean_loss(path: Path) -> float:
        gmap = read_map_ply(path)
        refiner = KeyframeRefiner(gmap, refine_module.GaussianOptimizer.from_config(gmap, MappingOptions.from_config(config.mapping)),
                                  start.keyframes, load, refine_options(config), config.render, torch.Generator())
        with torch.no_grad():
            losses = []
            for keyframe in start.keyframes:
                image = load(keyframe)
                masks = rgbd_masks(image.color, image.depth, max_depth=MappingOptions.max_depth)
                T_cw = se3_inverse(keyframe.T_wc).to(torch.float32)
                losses.append(float(refiner.loss(image, masks, T_cw, keyframe.exposure, None)))
        return sum(losses) / len(losses)

    before, after = mean_loss(run_dir / "map.ply"), mean_loss(run_dir / "refined" / "map.ply")
    assert after < before, (before, after)
    assert summary.progress[-1]["training_psnr"] > summary.progress[0]["training_psnr"]


# ----------------------------------------------------------------------------- resume and Ctrl-C


@pytest.fixture(scope="module")
def uninterrupted(finished_run, tmp_path_factory) -> Path:
    """The map of 13 steps in one session (mid-pass with the run's keyframes)."""
    run = Path(shutil.copytree(finished_run, tmp_path_factory.mktemp("uninterrupted") / "run"))
    assert _refine(run, "--iterations", "13") == 0
    return run


def _same_map(a: Path, b: Path) -> None:
    map_a, map_b = read_map_ply(a / "refined" / "map.ply"), read_map_ply(b / "refined" / "map.ply")
    for name in ("means", "log_scales", "quats_wxyz", "opacity_logits", "colors_raw"):
        torch.testing.assert_close(getattr(map_b, name), getattr(map_a, name), rtol=0, atol=0, msg=name)


def test_resume_gives_the_map_of_an_uninterrupted_refinement(run_dir, uninterrupted):
    assert _keyframe_count(run_dir) >= 2 and 13 % _keyframe_count(run_dir) != 0
    assert _refine(run_dir, "--iterations", "7") == 0
    assert _refine(run_dir, "--iterations", "6") == 0
    _same_map(uninterrupted, run_dir)
    progress = json.loads((run_dir / "refined" / "progress.json").read_text())
    assert progress["steps"] == 13 and [s["steps"] for s in progress["sessions"]] == [7, 6]
    assert [r["steps"] for r in progress["records"]] == [0, 7, 13]
    state = load_latest_checkpoint(run_dir / "refined" / "checkpoints")
    reference = load_latest_checkpoint(uninterrupted / "refined" / "checkpoints")
    assert state.tensors["refiner.pending"].tolist() == reference.tensors["refiner.pending"].tolist()
    assert state.metadata["steps"] == 13 and state.metadata["seconds"] > 0


def test_ctrl_c_saves_a_checkpoint_that_continues_to_the_uninterrupted_map(run_dir, uninterrupted, monkeypatch,
                                                                            capsys):
    original = KeyframeRefiner.step

    def step_then_ctrl_c(self):
        loss = original(self)
        if self.steps == 4:  # the user presses Ctrl-C during step 4
            signal.raise_signal(signal.SIGINT)
        return loss

    monkeypatch.setattr(KeyframeRefiner, "step", step_then_ctrl_c)
    assert main(["refine", str(run_dir), "--iterations", "13", "--no-eval"]) == 130
    err = capsys.readouterr().err
    assert "Ctrl-C: stopping after the current step" in err
    assert f"continue with: mipslam refine {run_dir}" in err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is put back
    refined = run_dir / "refined"
    checkpoint = load_latest_checkpoint(refined / "checkpoints")
    assert checkpoint.metadata["steps"] == 4 and checkpoint.metadata["sessions"][-1]["end"] == "interrupted"
    assert (refined / "map.ply").is_file() and (refined / "traj_est.txt").is_file()
    assert json.loads((refined / "progress.json").read_text())["steps"] == 4
    monkeypatch.setattr(KeyframeRefiner, "step", original)
    assert _refine(run_dir, "--iterations", "9") == 0
    _same_map(uninterrupted, run_dir)


def test_restart_and_a_changed_slam_map(run_dir, capsys):
    assert _refine(run_dir, "--iterations", "2") == 0
    gmap = read_map_ply(run_dir / "map.ply")
    with torch.no_grad():
        gmap.means += 0.001
    write_map_ply(run_dir / "map.ply", gmap)  # as if the run were resumed and finished again
    assert _refine(run_dir, "--iterations", "2") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "another SLAM map" in err and "--restart" in err, err
    (run_dir / "refined" / "notes.txt").write_text("mine")
    assert _refine(run_dir, "--iterations", "2", "--restart") == 2
    assert "notes.txt" in capsys.readouterr().err
    (run_dir / "refined" / "notes.txt").unlink()
    assert _refine(run_dir, "--iterations", "3", "--restart") == 0
    assert json.loads((run_dir / "refined" / "progress.json").read_text())["steps"] == 3


# ----------------------------------------------------------------------------- poses, resolution, rolling shutter


def test_refined_keyframe_poses_move_their_frames_with_them(run_dir):
    config_path = run_dir / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config.setdefault("refine", {})["lr_poses"] = 0.002
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    summary = refine_run(run_dir, RefineRequest(iterations=2 * _keyframe_count(run_dir), evaluate=True,
                                                eval_every_minutes=0))
    assert summary.poses_refined
    run_est, refined_est = read_tum_trajectory(run_dir / "traj_est.txt"), read_tum_trajectory(
        run_dir / "refined" / "traj_est.txt")
    np.testing.assert_array_equal(run_est.timestamps, refined_est.timestamps)
    frames = json.loads((run_dir / "frames.json").read_text())["frames"]
    keyframe_rows = [k for k, f in enumerate(frames) if f["keyframe_id"] >= 0]
    moved = np.abs(refined_est.T_wc - run_est.T_wc).max(axis=(1, 2))
    assert moved[keyframe_rows[0]] < 1e-8  # keyframe 0 holds the gauge
    assert all(moved[k] > 1e-6 for k in keyframe_rows[1:])
    assert any(moved[k] > 1e-6 for k, f in enumerate(frames) if f["keyframe_id"] < 0)  # frames follow
    keyframes = read_tum_trajectory(run_dir / "refined" / "keyframes.txt")
    np.testing.assert_allclose(keyframes.T_wc, refined_est.T_wc[keyframe_rows], atol=1e-8)
    metrics = json.loads((run_dir / "refined" / "metrics.json").read_text())
    assert metrics["refinement"]["poses_refined"] and metrics["evaluation"]["trajectory"] == "refined/traj_est.txt"
    assert [r["steps"] for r in summary.progress] == [0, summary.steps]  # eval-every 0: before and at the end


def test_native_resolution_and_the_recorded_images(run_dir, capsys):
    summary = refine_run(run_dir, RefineRequest(iterations=2, resolution="native", evaluate=False))
    assert summary.image_size == (80, 60) and summary.resolution == "native"
    # continuing keeps the refinement's resolution; asking for another one says what to type
    assert _refine(run_dir, "--iterations", "1") == 0
    assert json.loads((run_dir / "refined" / "progress.json").read_text())["resolution"] == "native"
    assert _refine(run_dir, "--iterations", "1", "--resolution", "mapping") == 2
    err = capsys.readouterr().err
    assert "--resolution native" in err and "--restart" in err
    # the keyframes are read as the camera recorded them, though the run moved their rolling shutter's rows to one
    # instant for tracking: the evaluation compares views of the map with the recorded images
    folder = RunFolder(run_dir)
    config = read_run_config(folder)
    start = refine_module._load_start(folder, config)
    assert config.dataset.rolling_shutter_readout_s > 0
    for resolution, size in (("mapping", (30, 40)), ("native", (60, 80))):
        sequence = refine_module._open_sequence(config, resolution)
        load = refine_module._keyframe_loader(sequence, start.state, torch.device("cpu"), start.keyframes)
        keyframe = start.keyframes[-1]
        image = load(keyframe)
        raw = sequence[keyframe.frame_index]
        assert tuple(image.color.shape[:2]) == size and (image.intrinsics.width, image.intrinsics.height) == size[::-1]
        torch.testing.assert_close(image.color, raw.color, atol=0, rtol=0)
        torch.testing.assert_close(image.depth, raw.depth)


# ----------------------------------------------------------------------------- report and viewer


def test_viewer_shows_the_refined_map_unless_asked_for_the_slam_map(run_dir):
    from mipslam.viewer.snapshot import snapshot_from_run_dir

    before = snapshot_from_run_dir(run_dir)
    assert not before.refined and before.map_file == run_dir / "map.ply"
    assert _refine(run_dir, "--iterations", "2") == 0
    shown = snapshot_from_run_dir(run_dir)
    assert shown.refined and shown.map_file == run_dir / "refined" / "map.ply"
    assert "refined map" in shown.describe_map() and "--slam-map" in shown.describe_map()
    refined_map = read_map_ply(run_dir / "refined" / "map.ply").activated()
    np.testing.assert_allclose(shown.snapshot.splats.means, refined_map.means.detach().numpy(), atol=1e-6)
    slam = snapshot_from_run_dir(run_dir, refined=False)
    assert not slam.refined and slam.map_file == run_dir / "map.ply" and "--slam-map" in slam.describe_map()


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("args, message", [
    (["--minutes", "0"], "expected a positive number"),
    (["--minutes", "x"], "expected a number"),
    (["--iterations", "-1"], "expected a whole number >= 0"),
    (["--eval-every-minutes", "-1"], "expected a number >= 0"),
    (["--resolution", "full"], "invalid choice"),
])
def test_bad_flag_values_are_one_line_with_exit_code_2(finished_run, args, message, capsys):
    assert main(["refine", str(finished_run), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and message in err, err


def test_folders_that_are_not_finished_runs_and_a_missing_dataset(run_dir, tmp_path, capsys):
    def error(path: Path) -> str:
        assert main(["refine", str(path), "--iterations", "1"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("error: "), err
        return err

    assert "no such run folder" in error(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    assert "config.yaml: missing" in error(tmp_path / "empty")
    no_checkpoint = Path(shutil.copytree(run_dir, tmp_path / "no_checkpoint"))
    shutil.rmtree(no_checkpoint / "checkpoints")
    assert "no checkpoint" in error(no_checkpoint)
    unfinished = Path(shutil.copytree(run_dir, tmp_path / "unfinished"))
    (unfinished / "map.ply").unlink()
    message = error(unfinished)
    assert "map.ply: missing" in message and "mipslam run --resume" in message
    moved = tmp_path / "moved_dataset"
    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    config["dataset"]["path"] = str(moved)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    message = error(run_dir)
    assert str(moved) in message and "dataset folder" in message
    assert not (run_dir / "refined").exists()
