"""The long_run benchmark scenario's checks on probes filled by hand (no run), its plot, and one smoke-size run."""
from __future__ import annotations

import json
from pathlib import Path

from mipslam.bench.scenarios import long_run


def _probe(keyframe: list[bool], cpu_ms: list[float]):
    """A probe as the frame loop would leave it: ``cpu_ms[i]`` is frame i's time (tracking i+1 included)."""
    probe = long_run.FrameProbe(Path("."))
    count = 0
    for index, flag in enumerate(keyframe):
        probe.frame.append(index)
        probe.keyframes_before.append(count)
        count += flag
        probe.seconds.append(float("nan") if index == 0 else cpu_ms[index - 1] / 1000)
        probe.cpu_seconds.append(float("nan") if index == 0 else cpu_ms[index - 1] / 1000)
    probe.last_period_s = probe.last_cpu_s = cpu_ms[-1] / 1000
    probe.final_keyframes = count
    return probe


def test_keyframe_flags_come_from_the_count_at_the_next_probe():
    flags = [True, False, True, True, False, False, True]
    assert _probe(flags, [100.0] * len(flags)).keyframe_flags() == flags


def test_a_changing_share_of_keyframes_does_not_fail_the_time_check():
    # Keyframes cost 250 ms, other frames 100 ms, neither grows; the first quarter is 20 % keyframes and the
    # last 80 %, so one median over both would go from 100 to 250 ms (ratio 2.5).
    n = 400
    flags = [(i % 5 == 0) if i < n // 2 else (i % 5 != 0) for i in range(n)]
    probe = _probe(flags, [250.0 if flag else 100.0 for flag in flags])
    _, passed, detail = long_run.time_growth_check(probe, covered=1)
    assert passed, detail
    assert "keyframes median 250 -> 250" in detail and "other frames median 100 -> 100" in detail


def test_dearer_keyframes_once_the_room_is_covered_do_not_fail_the_time_check():
    # Loop detection runs on revisited keyframes only: they cost twice the first lap's, then stay flat.
    n = 400
    flags = [i % 2 == 0 for i in range(n)]
    times = [(300.0 if i < n // 2 else 600.0) if flag else 150.0 for i, flag in enumerate(flags)]
    _, passed, detail = long_run.time_growth_check(_probe(flags, times), covered=n // 2)
    assert passed, detail
    assert "keyframes median 600 -> 600" in detail and "before the room is covered: keyframes median 300" in detail


def test_growing_keyframe_cost_fails_the_time_check():
    n = 400
    flags = [i % 2 == 0 for i in range(n)]
    # keyframes grow from 200 to 400 ms over the revisits (ratio ~1.8 between their quarters), other frames stay flat
    times = [200.0 + 200.0 * i / n if flag else 100.0 for i, flag in enumerate(flags)]
    _, passed, detail = long_run.time_growth_check(_probe(flags, times), covered=1)
    assert not passed
    assert "other frames median 100 -> 100" in detail


def test_a_progress_file_without_keyframe_counts_is_checked_as_one_class(tmp_path):
    rows = [{"frame": i, "period_before_s": None if i == 0 else 0.1, "cpu_before_s": None if i == 0 else 0.1,
             "rss_mib": 100.0, "gaussians": 10, "checkpoint_files": 0} for i in range(80)]
    progress = tmp_path / "progress.jsonl"
    progress.write_text("".join(json.dumps(row) + "\n" for row in rows))
    printed = long_run.summarise_progress(progress, frames=80, laps=2, rows=4)
    assert "PASS  no growth of per-frame time over the revisits (so far): all frames median 100 -> 100 CPU ms" in printed


# ----------------------------------------------------------------------------- keyframes on revisits

def test_keyframes_that_keep_growing_over_the_revisits_fail():
    n, covered = 200, 100
    flags = [i % 5 == 0 for i in range(n)]  # a keyframe every fifth frame, revisits included
    name, passed, detail = long_run.keyframe_growth_check(_probe(flags, [100.0] * n), covered)
    assert name == "keyframes stop growing on revisits" and not passed
    assert ("20 keyframes when the room is covered (frame 100), 40 at the end: +20 over the revisits "
            "(allowed 2") in detail


def test_keyframes_that_stop_once_the_room_is_covered_pass():
    n, covered = 200, 100
    flags = [(i % 5 == 0) if i < covered else i == 150 for i in range(n)]  # one more keyframe on the revisits
    _, passed, detail = long_run.keyframe_growth_check(_probe(flags, [100.0] * n), covered)
    assert passed, detail
    assert "20 keyframes when the room is covered (frame 100), 21 at the end: +1 over the revisits" in detail


def test_the_keyframe_allowance_is_a_share_of_the_map_above_its_floor():
    n, covered = 1000, 500
    # 100 keyframes by the covered frame, 5 more on the revisits: 5 % of 100 allowed; a sixth is one too many
    for added, expected in ((5, True), (6, False)):
        flags = [(i % 5 == 0) if i < covered else (i - covered) % 50 == 1 and (i - covered) // 50 < added
                 for i in range(n)]
        _, passed, detail = long_run.keyframe_growth_check(_probe(flags, [100.0] * n), covered)
        assert passed is expected, detail
        assert f"+{added} over the revisits (allowed 5: max(2, 5 % of 100))" in detail


# ----------------------------------------------------------------------------- median frame time, late against early

def test_frame_time_windows_are_the_targets_from_3000_frames_and_tenths_below():
    assert long_run.frame_time_windows(10_000) == (range(1000, 2000), range(9000, 10_000))
    assert long_run.frame_time_windows(3000) == (range(1000, 2000), range(2000, 3000))
    assert long_run.frame_time_windows(2999) == (range(299, 598), range(2700, 2999))
    assert long_run.frame_time_windows(500) == (range(50, 100), range(450, 500))


def test_flat_frame_times_pass_the_frame_time_check():
    n = 3000
    name, passed, detail = long_run.frame_time_check(_probe([i % 2 == 0 for i in range(n)], [100.0] * n))
    assert name == "median frame time, last 1000 frames vs frames 1000-2000" and passed, detail
    assert "frames 1000-1999: median 100 wall ms" in detail and "frames 2000-2999: median 100 wall ms" in detail
    assert "tenth" not in detail and "ratio 1.00, allowed 1.2" in detail


def test_frame_times_grown_by_half_fail_the_frame_time_check():
    n = 3000
    times = [100.0 if i < 2000 else 150.0 for i in range(n)]
    _, passed, detail = long_run.frame_time_check(_probe([False] * n, times))
    assert not passed and "ratio 1.50" in detail


def test_a_short_run_compares_its_second_tenth_with_its_last():
    n = 400
    flat = _probe([False] * n, [100.0] * n)
    _, passed, detail = long_run.frame_time_check(flat)
    assert passed, detail
    # the last frame's time runs to the end of the run (outputs): left out, so 39 of the last tenth's 40 frames
    assert ("run of 400 frames, under 3000: the second tenth against the last tenth; frames 40-79: median 100 wall ms "
            "(40 frames, 0 % keyframes); frames 360-399: median 100 wall ms (39 frames, 0 % keyframes)") in detail
    grown = _probe([False] * n, [100.0 if i < n // 2 else 150.0 for i in range(n)])
    assert not long_run.frame_time_check(grown)[1]


def test_the_last_frames_time_to_the_end_of_the_run_is_left_out():
    n = 100
    times = [100.0] * (n - 1) + [100_000.0]  # the final refinement and outputs
    _, passed, detail = long_run.frame_time_check(_probe([False] * n, times))
    assert passed, detail


# ----------------------------------------------------------------------------- outputs: the plot, summarise, smoke run

def _progress_rows(frames: int, keyframe_every: int, covered: int) -> list[dict]:
    rows, count = [], 0
    for i in range(frames):
        rows.append({"frame": i, "period_before_s": None if i == 0 else 0.1, "cpu_before_s": None if i == 0 else 0.1,
                     "rss_mib": 100.0, "gaussians": 10, "checkpoint_files": 0, "keyframes_before": count})
        count += i < covered and i % keyframe_every == 0
    return rows


def test_summarise_writes_the_new_checks_and_the_plot(tmp_path):
    progress = tmp_path / "progress.jsonl"
    progress.write_text("".join(json.dumps(row) + "\n" for row in _progress_rows(80, 4, covered=39)))
    out = tmp_path / "out"
    result = long_run.run(long_run.Options(frames=80, laps=2, rows=4, summarise=str(progress)), out)
    report = (out / "bench.md").read_text()
    assert ("PASS  keyframes stop growing on revisits (so far): 10 keyframes when the room is covered "
            "(frame 39)") in report
    assert "PASS  median frame time, last 1000 frames vs frames 1000-2000 (so far)" in report
    assert f"Plot: `{long_run.PLOT_NAME}`" in report
    assert result.plots == (out / long_run.PLOT_NAME,)
    assert (out / long_run.PLOT_NAME).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_smoke_run_writes_the_plot(tmp_path):
    out = tmp_path / "out"
    result = long_run.run(long_run.Options(**long_run.SMOKE), out)
    plot = out / long_run.PLOT_NAME
    assert result.plots == (plot,) and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"Plot: `{long_run.PLOT_NAME}`" in (out / "bench.md").read_text()
    record = json.loads((out / "bench.json").read_text())["results"]
    assert record["plot"] == long_run.PLOT_NAME
    names = [check["name"] for check in record["checks"]]
    assert "keyframes stop growing on revisits" in names
    assert "median frame time, last 1000 frames vs frames 1000-2000" in names
