"""The visual run report: every plot is written as a readable, non-trivial PNG and report.html ties them together;
loops.json is read; the top view uses the two axes of largest extent; the CLI writes it all with the new flags."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from mipslam.cli import main
from mipslam.evaluation.render_eval import RenderEvalOptions, evaluate_render
from mipslam.evaluation.report import loop_closures, top_view_axes, write_report
from mipslam.evaluation.run_eval import evaluate_run
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
    (tiny_run / "loops.json").unlink()


def test_single_scale_evaluation_plots_psnr_against_scale_from_the_showcase_frame(tiny_run, tmp_path):
    from mipslam.evaluation.report import _psnr_points, plot_psnr_vs_scale

    evaluation = evaluate_render(tiny_run, RenderEvalOptions(every=3, lpips=False, showcase_scales=(0.5, 1.0)))
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


def test_cli_eval_with_scales_and_modes_writes_metrics_and_report(tiny_run, capsys):
    code = main(["eval", str(tiny_run), "--scales", "0.5,1", "--modes", "point,eaa", "--every", "2", "--no-lpips",
                 "--frames", "all", "--no-report"])
    assert code == 0
    out = capsys.readouterr().out
    assert "render metrics on 2 of 3 frames" in out and "eaa x0.5" in out.replace("  ", " ")
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    rows = metrics["render"]["rows"]
    assert [(r["scale"], r["mode"]) for r in rows] == [(0.5, "point"), (0.5, "eaa"), (1.0, "point"), (1.0, "eaa")]
    assert metrics["render"]["protocol"]["frames"]["evaluated"] == [0, 2]
    assert metrics["trajectory"]["ate"]["count"] == FRAMES
    assert "report" not in metrics  # --no-report (the report itself is tested above)
    assert main(["eval", str(tiny_run), "--scales", "0,1"]) == 2
    assert main(["eval", str(tiny_run), "--modes", "box"]) == 2
