"""The visual run report: every plot is written as a readable, non-trivial PNG and report.html ties them together;
loops.json is read; the top view uses the two axes of largest extent; the CLI writes it all with the new flags."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mipslam.cli import main
from mipslam.config import config_from_dict, load_config
from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render
from mipslam.evaluation.report import MODE_COLORS, loop_closures, loop_text, plot_psnr_vs_scale, top_view_axes, write_report
from mipslam.evaluation.run_eval import evaluation_label, evaluate_run
from test_render_eval import FRAMES, make_tiny_run

PLOTS = ("trajectory", "translation_error", "psnr_vs_scale", "timing", "gaussians", "crops")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    return make_tiny_run(tmp_path_factory.mktemp("report"), trajectory="loop")


def _assert_real_png(path: Path, min_width: int = 300, min_height: int = 200) -> np.ndarray:
    assert path.is_file() and path.stat().st_size > 5_000, path
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None, f"{path} does not decode as an image"
    height, width = image.shape[:2]
    assert width >= min_width and height >= min_height, (path, image.shape)
    # a plot, not a blank canvas: many distinct colours and real contrast
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 50, path
    assert image.std() > 10, path
    return image


def test_report_writes_every_plot_and_the_page(tiny_run):
    (tiny_run / "loops.json").write_text(json.dumps({"loops": [{"i": 0, "j": 1, "accepted": True, "fitness": 0.8}]}))
    evaluation = evaluate_render(tiny_run, RenderEvalOptions(scales=(0.25, 1.0), modes=("point", "eaa"), every=3,
                                                             lpips=False))
    metrics = evaluate_run(tiny_run, render=False, report=False)
    metrics["render"] = evaluation.to_dict()
    assert evaluation.view_sets == ("training",)  # no frame at positions 0, 3, ... is a novel view
    files = write_report(tiny_run, metrics, evaluation)
    assert set(files.images) == set(PLOTS)
    for name in PLOTS:
        assert files.images[name] == tiny_run / "report" / f"{name}.png"
        _assert_real_png(files.images[name])
    crops = cv2.imread(str(files.images["crops"]))
    assert crops.shape[1] > crops.shape[0] * 1.3  # two scale rows of four columns (ground truth, point, mip, eaa)
    page = files.html.read_text(encoding="utf-8")
    for name in PLOTS:
        assert f"src='{name}.png'" in page
    assert "ATE RMSE" in page and "1 accepted, 0 rejected" in page
    for scale in ("0.25", "1"):
        assert f"<td>{scale}</td>" in page
    assert "<th>views</th>" in page and page.count("<td class='l'>training</td>") == 4
    # one view set: the headline names it; the map's size is there
    assert "render x1 48x36 (eaa, training views)" in page
    size = metrics["map"]
    assert f"{size['gaussians']} Gaussians, {size['ply_mb']:.2f} MB (map.ply)" in page
    # the protocol in words, not raw JSON dumps
    assert "<h2>Protocol</h2>" in page and "<pre>" not in page and "&quot;" not in page
    assert "3 of 3 estimated poses matched" in page
    (tiny_run / "loops.json").unlink()


def test_loop_closure_line_says_zero_when_loops_json_lists_none():
    assert loop_text({"enabled": True, "loops": []}) == "0 loop closures"
    assert loop_text({"enabled": False, "loops": []}) == "0 loop closures (loop closure off)"
    assert loop_text({"loops": [{"keyframe_i": 0, "keyframe_j": 4, "accepted": True},
                                {"keyframe_i": 1, "keyframe_j": 5, "accepted": False}]}) == "1 accepted, 1 rejected"
    assert loop_text(None) == "not recorded (no loops.json)"


def test_coinciding_curves_stay_visible(tmp_path):
    same = [(0.25, 20.0), (0.5, 25.0), (1.0, 30.0)]
    image = cv2.imread(str(plot_psnr_vs_scale(tmp_path / "psnr.png", {"point": same, "mip": same, "eaa": same}, "")))
    rgb = image[..., ::-1].reshape(-1, 3).astype(int)
    for mode in ("point", "mip", "eaa"):  # every curve, though drawn on the same points, has pixels of its colour
        colour = np.array([int(MODE_COLORS[mode][i:i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(rgb - colour).sum(axis=1) < 30).sum() > 200, mode


def test_single_scale_evaluation_plots_psnr_against_scale_from_the_showcase_frame(tiny_run, tmp_path):
    from mipslam.evaluation.report import _psnr_points, plot_psnr_vs_scale

    evaluation = evaluate_render(tiny_run, RenderEvalOptions(frames="all", every=3, lpips=False,
                                                             showcase_scales=(0.5, 1.0)))
    assert evaluation.showcase.scales == (0.5, 1.0)
    assert set(evaluation.showcase.renders) == {(s, m) for s in (0.5, 1.0) for m in ("point", "mip", "eaa")}
    points, subtitle = _psnr_points(evaluation.to_dict(), evaluation.showcase)
    assert set(points) == {"point", "mip", "eaa"} and "frame 0 only" in subtitle
    assert all(len(values) == 2 and all(np.isfinite(p) and p > 10 for _, p in values) for values in points.values())
    _assert_real_png(plot_psnr_vs_scale(tmp_path / "psnr.png", points, subtitle))


def test_loop_closures_are_read_from_the_usual_layouts():
    assert loop_closures([{"keyframe_i": 3, "keyframe_j": 40}, {"i": 1, "j": 2, "accepted": False}]) == [
        (3, 40, True), (1, 2, False)]
    assert loop_closures({"loops": [{"source": 5, "target": 0, "accepted": True}, {"note": "no ids"}]}) == [(5, 0, True)]
    assert loop_closures(None) == [] and loop_closures("nonsense") == []


def test_top_view_drops_the_axis_of_least_extent():
    t = np.linspace(0, 2 * np.pi, 50)
    circle_in_xz = np.stack([np.cos(t), 0.01 * np.sin(3 * t), 2 * np.sin(t)], axis=1)
    assert top_view_axes(circle_in_xz) == (0, 2)
    circle_in_yz = np.stack([0.1 * t, 3 * np.cos(t), np.sin(t)], axis=1)
    assert top_view_axes(circle_in_yz) == (1, 2)


def test_evaluation_label_names_what_differs_from_the_runs_eval_config(tiny_run):
    config = load_config(tiny_run / "config.yaml")
    own = RenderEvalOptions(frames=config.eval.frames, resolution=config.eval.resolution,
                            scales=tuple(config.eval.scales), modes=tuple(config.eval.modes))
    assert (config.eval.frames, config.eval.resolution) == ("split", "native")
    assert evaluation_label(config) is None and evaluation_label(config, render_options=own) is None
    assert evaluation_label(config, render_options=RenderEvalOptions()) is None
    assert evaluation_label(config, render_options=RenderEvalOptions(resolution="mapping")) == "res-mapping"
    assert evaluation_label(config, render_options=RenderEvalOptions(resolution="mapping", frames="all",
                                                                     scales=(0.5, 1.0))) == "res-mapping_multiscale_all"
    # a run whose config asks for the mapping resolution: that is its own evaluation, native is another
    mapped = load_config(tiny_run / "config.yaml", overrides=["eval.resolution=mapping"])
    assert evaluation_label(mapped, render_options=RenderEvalOptions(resolution="mapping")) is None
    assert evaluation_label(mapped, render_options=RenderEvalOptions()) == "res-native"
    # an old run's config.yaml without eval.resolution takes the default (native)
    data = yaml.safe_load((tiny_run / "config.yaml").read_text())
    del data["eval"]["resolution"]
    old = config_from_dict(data)
    assert old.eval.resolution == "native" and evaluation_label(old, render_options=own) is None
    assert evaluation_label(config, render_options=RenderEvalOptions(scales=(0.5, 1.0))) == "multiscale"
    assert evaluation_label(config, render_options=RenderEvalOptions(scales=(0.5,))) == "scale0p5"
    assert evaluation_label(config, render_options=RenderEvalOptions(modes=("point", "eaa"), every=2,
                                                                     lpips=False)) == "point-eaa_every2_nolpips"
    assert evaluation_label(config, render_options=RenderEvalOptions(modes=(config.render.mode,))) is None
    assert evaluation_label(config, render=False) == "trajectory"
    assert evaluation_label(config, alignment="sim3", render_options=own) == "align-sim3"
    assert evaluation_label(config, association="index", max_diff=0.1) == "match-index_maxdiff0p1"


def test_cli_eval_with_other_scales_writes_beside_the_runs_metrics(tiny_run, capsys):
    for name in ("metrics.json", "metrics_multiscale_point-eaa_every2_nolpips.json"):
        (tiny_run / name).unlink(missing_ok=True)
    assert main(["eval", str(tiny_run), "--no-lpips", "--frames", "all", "--no-report"]) == 0
    assert not (tiny_run / "metrics.json").exists()  # --no-lpips is another request than the run's own
    assert main(["eval", str(tiny_run)]) == 0
    own = (tiny_run / "metrics.json").read_bytes()
    assert json.loads(own)["evaluation"]["label"] is None
    capsys.readouterr()

    code = main(["eval", str(tiny_run), "--scales", "0.5,1", "--modes", "point,eaa", "--every", "2", "--no-lpips",
                 "--frames", "all"])
    assert code == 0
    out = capsys.readouterr().out
    assert "render metrics at scales of the native resolution 48x36" in out and "  all: 2 of 3 frames, every 2" in out
    assert "all eaa x0.5 24x18 PSNR" in " ".join(out.split())
    assert "the run's own metrics.json is unchanged" in out
    assert (tiny_run / "metrics.json").read_bytes() == own
    label = "multiscale_point-eaa_all_every2_nolpips"
    metrics = json.loads((tiny_run / f"metrics_{label}.json").read_text())
    assert metrics["evaluation"] == {**metrics["evaluation"], "label": label, "metrics_file": f"metrics_{label}.json"}
    rows = metrics["render"]["rows"]
    assert [(r["views"], r["scale"], r["mode"]) for r in rows] == [
        ("all", 0.5, "point"), ("all", 0.5, "eaa"), ("all", 1.0, "point"), ("all", 1.0, "eaa")]
    assert metrics["render"]["protocol"]["frames"]["evaluated"] == [0, 2]
    assert metrics["trajectory"]["ate"]["count"] == FRAMES

    # the report keeps the run's own evaluation and adds a section for this one, with its own plots
    report = tiny_run / "report"
    page = (report / "report.html").read_text(encoding="utf-8")
    assert "<h2>Headline</h2>" in page and f"Evaluation '{label}'" in page
    assert f"src='psnr_vs_scale_{label}.png'" in page and f"src='crops_{label}.png'" in page
    assert "src='psnr_vs_scale.png'" in page and "src='trajectory.png'" in page
    _assert_real_png(report / f"psnr_vs_scale_{label}.png")
    # a later evaluation of the run's own rebuilds the page and keeps the section
    assert main(["eval", str(tiny_run), "--no-render"]) == 0  # 'trajectory' section
    assert main(["eval", str(tiny_run), "--no-lpips", "--frames", "all", "--scales", "1"]) == 0
    page = (report / "report.html").read_text(encoding="utf-8")
    assert f"Evaluation '{label}'" in page and "Evaluation 'trajectory'" in page

    assert main(["eval", str(tiny_run), "--scales", "0,1"]) == 2
    assert main(["eval", str(tiny_run), "--modes", "box"]) == 2
    assert main(["eval", str(tiny_run), "--resolution", "camera"]) == 2


def test_cli_eval_prints_the_views_of_each_row_the_map_size_and_the_resolution_label(tmp_path, capsys):
    run = make_tiny_run(tmp_path, kind="replica", downscale=2, frames=6)
    assert main(["eval", str(run)]) == 0  # the run's own evaluation: split, native
    out = capsys.readouterr().out
    metrics = json.loads((run / "metrics.json").read_text())
    size = metrics["map"]
    assert f"map: {size['gaussians']} Gaussians, {size['ply_mb']:.2f} MB (map.ply)" in out
    assert "native resolution 48x36" in out and "  novel views: 1 of 4 non-keyframes (MonoGS" in out
    assert "  training views: 2 of 2 keyframes, every 1" in out
    lines = [" ".join(line.split()) for line in out.splitlines()]
    assert any(line.startswith("novel eaa x1 48x36 PSNR") for line in lines), out
    assert any(line.startswith("training eaa x1 48x36 PSNR") for line in lines), out
    # the report's headline names the novel-view row at scale 1 first, then the training views
    page = (run / "report" / "report.html").read_text(encoding="utf-8")
    novel = page.find("render x1 48x36 (eaa, novel views)")
    training = page.find("render x1 48x36 (eaa, training views)")
    assert 0 < novel < training, (novel, training)
    assert "<td class='l'>novel</td>" in page and "MonoGS" in page and "native resolution 48x36" in page
    assert main(["eval", str(run), "--no-lpips", "--no-report", "--resolution", "mapping"]) == 0
    out = capsys.readouterr().out
    assert "metrics_res-mapping_nolpips.json" in out and "mapping resolution 24x18" in out
    rows = json.loads((run / "metrics_res-mapping_nolpips.json").read_text())["render"]["rows"]
    assert [(r["views"], r["width"], r["height"]) for r in rows] == [("novel", 24, 18), ("training", 24, 18)]


def test_cli_eval_out_says_where(tiny_run, tmp_path):
    out = tmp_path / "elsewhere.json"
    assert main(["eval", str(tiny_run), "--scales", "0.5,1", "--no-lpips", "--every", "3", "--no-report",
                 "--out", str(out)]) == 0
    assert json.loads(out.read_text())["evaluation"]["label"] == "multiscale_every3_nolpips"
    assert not (tiny_run / "metrics_multiscale_every3_nolpips.json").exists()


def test_another_evaluation_before_the_runs_own_says_so(tmp_path):
    run = make_tiny_run(tmp_path)
    metrics = evaluate_run(run, render=False)  # 'trajectory': the run has no metrics.json yet
    assert metrics["evaluation"]["label"] == "trajectory" and metrics["evaluation"]["metrics_file"] == "metrics_trajectory.json"
    page = (run / "report" / "report.html").read_text(encoding="utf-8")
    assert "(metrics.json) is not there" in page and "Evaluation 'trajectory'" in page
    assert not (run / "report" / "trajectory.png").exists()  # the main plots belong to the run's own evaluation
