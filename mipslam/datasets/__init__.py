"""RGB-D dataset readers behind one protocol, :class:`RGBDSequence`.

``make_sequence(cfg.dataset)`` builds the reader that ``dataset.kind`` names (replica | tum |
synthetic | realsense | realsense_bag; the last two need pyrealsense2). Every reader validates its
folder at construction (lists, poses, files present) and reads images lazily on ``seq[i]``; bad
input raises :class:`~mipslam.errors.DatasetError` with the file (and line). Frames are float32
RGB in [0, 1] ``[H, W, 3]`` and float32 depth in metres ``[H, W]`` (0 = no measurement); ground
truth is camera-to-world, OpenCV axes, float64.
:class:`FrameCache` keeps the last few frames read, on the run's device (mapping revisits keyframes).
"""
from __future__ import annotations

import logging
import os
import sys
import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch

from mipslam.config import DatasetConfig
from mipslam.datasets.base import RGBDSequence
from mipslam.datasets.realsense import StreamEnded
from mipslam.datasets.images import downscale_color, downscale_depth, read_color, read_depth
from mipslam.datasets.replica import ReplicaSequence
from mipslam.datasets.synthetic import SyntheticSequence
from mipslam.datasets.tum import TUM_CAMERAS, TUMSequence, associate_timestamps
from mipslam.errors import DatasetError
from mipslam.types import Frame

__all__ = [
    "RGBDSequence", "make_sequence", "FrameCache", "ReplicaSequence", "TUMSequence", "SyntheticSequence", "TUM_CAMERAS",
    "associate_timestamps", "StreamEnded", "read_color", "read_depth", "downscale_color", "downscale_depth",
]


def make_sequence(cfg: DatasetConfig) -> RGBDSequence:
    """The reader for ``cfg.kind`` on ``cfg.path`` (reads only the dataset section of the config)."""
    if cfg.kind == "realsense":  # dataset.path: the camera's serial number (empty = the first camera)
        from mipslam.datasets.realsense import RealSenseSequence

        return RealSenseSequence(cfg, live_camera=True)
    if not cfg.path:
        raise DatasetError(None, f"dataset.path is empty; point it at a {cfg.kind} folder with --set dataset.path=DIR")
    root = Path(cfg.path).expanduser()
    if cfg.kind == "replica":
        return ReplicaSequence(root, cfg)
    if cfg.kind == "tum":
        return TUMSequence(root, cfg)
    if cfg.kind == "synthetic":
        return SyntheticSequence(root, cfg)
    if cfg.kind == "realsense_bag":
        from mipslam.datasets.realsense import RealSenseSequence

        return RealSenseSequence(cfg, live_camera=False)
    raise DatasetError(root, f"unknown dataset kind {cfg.kind!r}; use replica, tum, synthetic, realsense or realsense_bag")


log = logging.getLogger("mipslam.datasets")

# How long the frame loop waits for a frame the read-ahead thread has not delivered before reading it itself:
# two of its own reads' time (the reader may have started just before it was asked), and at least a
# scheduler slice's worth (small synthetic frames read in a millisecond).
READ_AHEAD_PATIENCE_READS = 2.0
READ_AHEAD_MIN_WAIT_S = 0.05


def _run_at_idle_priority() -> None:
    """Put the calling thread in Linux's SCHED_IDLE class: it runs only on a core nothing else wants.

    Decoding a frame is CPU work (two PNGs: ~20 ms at 640x480); at normal priority the reader takes it from
    the frame loop's threads whenever they use every core, which slows tracking by as much as the read
    costs. At idle priority it fills the gaps the loop leaves (single-threaded Python between the kernels).
    Elsewhere (no per-thread scheduling class) the reader keeps its normal priority."""
    if not (sys.platform.startswith("linux") and hasattr(os, "SCHED_IDLE")):
        return
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # pid 0: this thread
    except OSError as exc:  # a sandbox that forbids it: reading ahead still works, at normal priority
        log.debug("read-ahead thread keeps its priority: %s", exc)


def _frame_bytes(frame: Frame) -> int:
    return frame.color.numel() * frame.color.element_size() + frame.depth.numel() * frame.depth.element_size()


class FrameCache:
    """The last ``capacity`` frames read from ``sequence``, moved to ``device``: ``cache[index]`` -> Frame.

    Colour [H, W, 3] and depth [H, W] (metres) are on ``device``; a frame read again after it left the
    cache is read again from the sequence (same values: readers are deterministic). Frames passed to
    :meth:`keep` (keyframes) stay beyond the last ``capacity``, up to ``kept_bytes`` of images.

    ``read_ahead``: :meth:`prefetch` reads a frame on one background thread while the caller works (decoding
    and downscaling release the GIL), so the frame loop does not wait for the disk. The thread runs at idle
    priority (:func:`_run_at_idle_priority`); a frame it has not delivered within two reads' time (at least
    50 ms) of being asked for (the reader starved by other processes on every core) is read by the caller
    instead. A camera's sequence must not read ahead (its reader delivers the newest frame when asked).
    Errors surface when the frame is asked for.

    ``adjust``: applied in the caller's thread to every frame read from the sequence before it is cached
    (the run's depth moved to the colour instant, :mod:`mipslam.sensor_sync`); :meth:`put` caches a
    frame adjusted elsewhere in the cache, the same one ``adjust`` gives when the frame is read again;
    :meth:`adjust_when_read` has ``adjust`` applied to the cached frame at its next read instead (a frame that
    only a later stage may read again: its adjustment costs nothing until it is).
    ``on_read_ahead``: called on the reader's thread with each frame it reads ahead, before ``adjust`` (work on
    the image alone that the frame loop would otherwise wait for: the front-end's keypoints).
    """

    def __init__(self, sequence: RGBDSequence, device: torch.device, capacity: int, *, read_ahead: bool = False,
                 kept_bytes: int = 0):
        self.sequence, self.device, self.capacity = sequence, device, max(1, capacity)
        self._frames: OrderedDict[int, Frame] = OrderedDict()
        # frames the caller asked to keep (keyframes: loop verification re-reads old ones), least recently used
        # first, up to kept_bytes of images
        self.kept_bytes = max(0, kept_bytes)
        self._kept: OrderedDict[int, Frame] = OrderedDict()
        self._kept_size = 0
        self._reader = (ThreadPoolExecutor(max_workers=1, thread_name_prefix="mipslam-read",
                                           initializer=_run_at_idle_priority) if read_ahead else None)
        self._pending: dict[int, Future] = {}
        # how long the latest read in the caller's thread took (the idle-priority reader's own reads can take
        # much longer while it is starved, so they do not count)
        self._read_seconds = 0.0
        self.adjust: Callable[[Frame], Frame] | None = None
        self.on_read_ahead: Callable[[Frame], None] | None = None
        self._adjust_at_read: set[int] = set()  # cached frames that ``adjust`` has not seen since they changed

    def _read(self, index: int, timed: bool = True) -> Frame:
        start = time.perf_counter()
        frame = self.sequence[index]
        frame = replace(frame, color=frame.color.to(self.device), depth=frame.depth.to(self.device))
        if timed:
            self._read_seconds = time.perf_counter() - start
        return frame

    def _collect(self, pending: Future, index: int) -> Frame:
        """The read-ahead's frame ``index``, or the frame read here if the reader has not delivered it in time
        (``READ_AHEAD_*``; the reader's late result is dropped)."""
        try:
            return pending.result(timeout=max(READ_AHEAD_PATIENCE_READS * self._read_seconds, READ_AHEAD_MIN_WAIT_S))
        except TimeoutError:
            pending.cancel()  # not started yet: never starts
            log.debug("frame %d: the read-ahead thread was late; read in the frame loop", index)
            return self._read(index)

    def prefetch(self, index: int) -> None:
        """Start reading frame ``index`` in the background (no-op without read-ahead, past the end, or when
        the frame is cached or already on its way)."""
        if (self._reader is None or not 0 <= index < len(self.sequence) or index in self._frames
                or index in self._pending):
            return
        self._pending[index] = self._reader.submit(self._read_ahead, index)

    def _read_ahead(self, index: int) -> Frame:
        frame = self._read(index, timed=False)
        if self.on_read_ahead is not None:
            self.on_read_ahead(frame)
        return frame

    def keep(self, index: int) -> None:
        """Keep frame ``index`` beyond the last ``capacity`` frames, within ``kept_bytes`` (the least recently
        used kept frame goes first); read now if it is not in memory."""
        if self.kept_bytes == 0 or index in self._kept:
            return
        frame = self[index]
        size = _frame_bytes(frame)
        if size > self.kept_bytes:
            return
        self._kept[index] = frame
        self._kept_size += size
        while self._kept_size > self.kept_bytes:
            dropped_index, dropped = self._kept.popitem(last=False)
            if dropped_index not in self._frames:
                self._adjust_at_read.discard(dropped_index)
            self._kept_size -= _frame_bytes(dropped)

    def __getitem__(self, index: int) -> Frame:
        if index in self._adjust_at_read:
            self._adjust_at_read.discard(index)
            if self.adjust is not None and (index in self._frames or index in self._kept):
                self.put(self.adjust(self._frames[index] if index in self._frames else self._kept[index]))
        if index in self._frames:
            self._frames.move_to_end(index)
            return self._frames[index]
        if index in self._kept:
            self._kept.move_to_end(index)
            return self._kept[index]
        pending = self._pending.pop(index, None)
        frame = self._collect(pending, index) if pending is not None else self._read(index)
        if self.adjust is not None:
            frame = self.adjust(frame)
        self._store(index, frame)
        return frame

    def adjust_when_read(self, index: int) -> None:
        """Apply ``adjust`` to the cached frame ``index`` when it is next read (as to a frame read again from the
        sequence); a frame no longer cached is read and adjusted anyway."""
        self._adjust_at_read.add(index)

    def put(self, frame: Frame) -> None:
        """Cache ``frame`` in place of the frame of its index (wherever that one is kept)."""
        self._adjust_at_read.discard(frame.index)
        if frame.index in self._kept:
            self._kept[frame.index] = frame
        self._store(frame.index, frame)

    def _store(self, index: int, frame: Frame) -> None:
        """``frame`` becomes the newest of the last ``capacity`` frames, as frame ``index``."""
        self._frames[index] = frame
        self._frames.move_to_end(index)
        while len(self._frames) > self.capacity:
            evicted, _ = self._frames.popitem(last=False)
            if evicted not in self._kept:  # read again from the sequence, adjusted then
                self._adjust_at_read.discard(evicted)

    def close(self) -> None:
        """Stop the background reader (frames on their way are finished and dropped)."""
        if self._reader is not None:
            self._reader.shutdown(wait=True, cancel_futures=True)
            self._reader, self._pending = None, {}
