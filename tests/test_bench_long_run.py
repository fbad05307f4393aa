"""The long_run benchmark scenario's per-frame time check, on probes filled by hand (no run)."""
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
