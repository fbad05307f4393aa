"""The tracking_bias benchmark scenario on a tiny data_synth sequence: it maps one true view and reports coverage,
depth biases and tracking errors that are all finite and plausible."""
from __future__ import annotations

import json
import math

import data_synth
from mipslam.bench.scenarios import run_scenario, tracking_bias


def test_bench_tracking_bias_reports_finite_biases_and_errors(tmp_path):
    sequence = tmp_path / "seq"
    data_synth.generate(sequence, layout="replica", trajectory="loop", width=40, height=30, frames=11, seed=0,
                        supersample=2)
    # At 40x30 a one-view map of 20 steps pins a pose to centimetres only: the preset's direct alignment finds
    # that loss's minimum 3-13 cm from the truth, so the bounds below are for the gradient steps alone.
    options = tracking_bias.Options(sequence=str(sequence), pure_motions=True,
                                    config_overrides=("mapping.first_frame_iterations=20", "tracking.iterations=6",
                                                      "tracking.direct_iterations=0"))
    result = run_scenario("tracking_bias", options, tmp_path / "out")
    results = json.loads(result.files.json.read_text())["results"]
    assert results["gaussians"] > 0
    first = results["coverage"]["0"]
    # mapping fits the raw depth of the view it was built from; every pixel of that view is explained
    assert abs(first["raw_depth_bias"]) < 0.05 and first["fraction_used"] > 0.5
    quantiles = list(first["opacity_quantiles"].values())
    assert quantiles == sorted(quantiles) and 0.0 <= quantiles[0] and quantiles[-1] <= 1.0
    assert [row["frame"] for row in results["tracking"]] == list(tracking_bias.TRACKED_FRAMES)
    for row in results["tracking"]:
        values = row["translation_mm"] + row["rotation_mrad"]
        assert all(math.isfinite(v) for v in values) and 1 <= row["iterations"] <= 6
        assert max(abs(v) for v in row["translation_mm"]) < 20.0  # started at the truth: 6 Rprop steps move it a few mm
    assert [row["motion"] for row in results["pure_motions"]] == [m[0] for m in tracking_bias.PURE_MOTIONS]
    for row in results["pure_motions"]:
        assert all(math.isfinite(v) for v in row["translation_mm"] + row["rotation_mrad"])
