"""The observer (mipslam/observer.py): per-frame stage times, nesting, stages after the frames, events."""
from __future__ import annotations

import time

import pytest

from mipslam.observer import Observer


class _Record:
    """The fields of a FrameRecord the observer's users read."""

    def __init__(self, index: int):
        self.index = index


def _frame(observer: Observer, index: int, stages: dict[str, float]) -> None:
    observer.begin_frame(index)
    for name, seconds in stages.items():
        with observer.stage(name):
            time.sleep(seconds)
    observer.end_frame(_Record(index), state=None)


def test_every_declared_stage_has_one_entry_per_frame_and_zero_where_it_did_not_run():
    observer = Observer()
    observer.declare("tracking", "mapping")
    _frame(observer, 0, {"tracking": 0.0, "mapping": 0.02})
    _frame(observer, 1, {"tracking": 0.01})
    _frame(observer, 2, {"tracking": 0.0, "loop": 0.01})  # a stage first seen late gets zeros before
    assert {k: len(v) for k, v in observer.timings.items()} == {"tracking": 3, "mapping": 3, "loop": 3}
    assert observer.timings["mapping"][1] == observer.timings["mapping"][2] == 0.0
    assert observer.timings["mapping"][0] >= 0.02
    assert list(observer.timings["loop"][:2]) == [0.0, 0.0] and observer.timings["loop"][2] >= 0.01
    summary = observer.timing_summary()
    assert summary["frames"] == 3 and set(summary["stages"]) == {"tracking", "mapping", "loop"}
    assert summary["total_s"] == pytest.approx(sum(sum(v) for v in observer.timings.values()))


def test_a_nested_stage_is_charged_to_itself_only():
    observer = Observer()
    observer.begin_frame(0)
    with observer.stage("loop"):
        time.sleep(0.01)
        with observer.stage("pgo"):
            time.sleep(0.05)
    observer.end_frame(_Record(0), state=None)
    loop, pgo = observer.timings["loop"][0], observer.timings["pgo"][0]
    assert pgo >= 0.05 and 0.01 <= loop < 0.05, (loop, pgo)


def test_time_outside_frames_goes_to_the_last_frame_and_nothing_before_the_first_is_charged():
    observer = Observer()
    with observer.stage("refine"):  # before any frame (set-up): not recorded
        time.sleep(0.001)
    assert observer.timings == {}
    _frame(observer, 0, {"tracking": 0.0})
    _frame(observer, 1, {"tracking": 0.0})
    with observer.stage("refine"):
        time.sleep(0.01)
    assert observer.timings["refine"][0] == 0.0 and observer.timings["refine"][1] >= 0.01
    with observer.stage("checkpoint", timed=False):
        pass
    assert "checkpoint" not in observer.timings


def test_events_tell_a_subclass_about_frames_and_stages_and_restore_continues_the_timings():
    events = []

    class Recorder(Observer):
        def on_frame_start(self, index):
            events.append(("frame", index))

        def on_stage(self, name, entering):
            events.append((name, entering, self.frame_index))

        def on_frame(self, record, state):
            events.append(("done", record.index))

    observer = Recorder()
    observer.restore({"tracking": [0.5, 0.25]})  # two frames of an earlier session
    _frame(observer, 2, {"tracking": 0.0})
    assert events == [("frame", 2), ("tracking", True, 2), ("tracking", False, 2), ("done", 2)]
    assert list(observer.timings["tracking"][:2]) == [0.5, 0.25] and len(observer.timings["tracking"]) == 3
    assert not Observer().diagnostics  # diagnostics are asked for, never on by default
