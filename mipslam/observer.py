"""One way to observe a run: stage times per frame, optional diagnostics, and events for benchmarks.

The frame loop opens a frame (:meth:`Observer.begin_frame`), runs each stage inside
``with observer.stage(name):`` and closes the frame (:meth:`Observer.end_frame`). Times are
exclusive wall-clock seconds: a stage nested in another (the pose-graph optimisation inside loop
closure) is charged to itself only. Every declared stage gets one entry per frame (0.0 where it did not
run), so ``timings[stage][i]`` is frame i's time; a stage timed outside any frame (the final refinement)
is charged to the last frame. Nothing before the first frame (loading, warm-up) is timed.

``diagnostics`` asks stages for measurements that cost time and change nothing (the map's PSNR
around a loop correction); off by default, so the hot path never pays for them.

Benchmarks observe a run by subclassing and overriding the event methods :meth:`on_frame_start`,
:meth:`on_stage` (a stage starts or ends; also the untimed "checkpoint" and "outputs") and
:meth:`on_frame` (a frame is done); they never patch pipeline functions.
Timings are outputs (``timings.json``), not SLAM state; a checkpoint carries them so that a resumed
run's ``timings.json`` covers every session.
"""
from __future__ import annotations

import time
from array import array
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Iterator

if TYPE_CHECKING:
    from mipslam.state import FrameRecord, SLAMState


class Observer:
    """Records per-frame stage times (seconds) and tells subclasses about stages and frames."""

    def __init__(self, *, diagnostics: bool = False):
        self.diagnostics = diagnostics
        self.frames = None  # the run's FrameCache once attached (:meth:`attach`)
        # stage -> seconds per frame, as C doubles (8 bytes a frame, where a list of floats takes 32)
        self.timings: dict[str, array] = {}
        self.frame_index: int | None = None  # the sequence index of the open frame (None between frames)
        self._frame: dict[str, float] | None = None  # the open frame's times
        self._open: list[tuple[str, float]] = []  # stages entered and not yet left: (name, start)
        self._nested: list[float] = []  # per open stage: seconds of the stages nested in it

    # ------------------------------------------------------------------ recording

    def attach(self, frames) -> None:
        """The frames the run reads (a :class:`~mipslam.datasets.FrameCache`, with ``.sequence``), for observers
        that show images, such as the live viewer; set when the stages are built."""
        self.frames = frames

    def declare(self, *stages: str) -> None:
        """Stages that get an entry on every frame, even frames they skip (0.0)."""
        frames = self.frames_recorded
        for stage in stages:
            self.timings.setdefault(stage, array("d", [0.0]) * frames)

    @property
    def frames_recorded(self) -> int:
        return max((len(v) for v in self.timings.values()), default=0)

    def restore(self, timings: dict[str, list[float]]) -> None:
        """Continue the timings of an earlier session (from its checkpoint)."""
        self.timings = {stage: array("d", (float(v) for v in values)) for stage, values in timings.items()}

    def timing_lists(self) -> dict[str, list[float]]:
        """The timings as plain lists (for JSON: the checkpoint's metadata, timings.json)."""
        return {stage: values.tolist() for stage, values in self.timings.items()}

    def begin_frame(self, index: int) -> None:
        self.frame_index, self._frame = index, {}
        self.on_frame_start(index)

    def end_frame(self, record: "FrameRecord", state: "SLAMState") -> None:
        """Close the open frame: one entry per declared stage, then :meth:`on_frame`."""
        times, frames = self._frame or {}, self.frames_recorded
        self.declare(*times)
        for stage, values in self.timings.items():
            values.extend([0.0] * (frames - len(values)))
            values.append(times.get(stage, 0.0))
        self.frame_index, self._frame = None, None
        self.on_frame(record, state)

    @contextmanager
    def stage(self, name: str, *, timed: bool = True) -> Iterator[None]:
        """Time the block as stage ``name`` (``timed=False``: only announce it, e.g. writing a checkpoint)."""
        self.on_stage(name, True)
        start = time.perf_counter()
        self._open.append((name, start))
        self._nested.append(0.0)
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            self._open.pop()
            nested = self._nested.pop()
            if timed:
                self._charge(name, elapsed - nested)
                if self._nested:
                    self._nested[-1] += elapsed
            self.on_stage(name, False)

    def _charge(self, stage: str, seconds: float) -> None:
        if self._frame is not None:
            self._frame[stage] = self._frame.get(stage, 0.0) + seconds
            return
        frames = self.frames_recorded  # after the frames (the final refinement): charged to the last one
        if frames == 0:
            return
        values = self.timings.setdefault(stage, array("d"))
        values.extend([0.0] * (frames - len(values)))
        values[-1] += seconds

    # ------------------------------------------------------------------ events (override in benchmarks)

    def on_frame_start(self, index: int) -> None:
        """Frame ``index`` of the sequence starts (before it is read)."""

    def on_stage(self, name: str, entering: bool) -> None:
        """A stage starts (``entering``) or ends; :attr:`frame_index` is the open frame (None outside frames)."""

    def on_frame(self, record: "FrameRecord", state: "SLAMState") -> None:
        """Frame ``record.index`` is done (its record appended to ``state``, timings recorded)."""

    # ------------------------------------------------------------------ outputs

    def timing_summary(self) -> dict[str, Any]:
        """timings.json: per stage total seconds, median and mean milliseconds per frame, and the per-frame list."""
        import statistics

        stages = {}
        for stage, values in self.timings.items():
            stages[stage] = {
                "total_s": sum(values),
                "median_ms": 1000 * statistics.median(values) if values else 0.0,
                "mean_ms": 1000 * statistics.fmean(values) if values else 0.0,
                "per_frame_s": values.tolist(),
            }
        total = sum(sum(v) for v in self.timings.values())
        frames = self.frames_recorded
        return {
            "frames": frames,
            "total_s": total,
            "frames_per_second": frames / total if total > 0 else None,
            "note": "seconds of each stage per frame, summed over all sessions of the run (resume included)",
            "stages": stages,
        }
