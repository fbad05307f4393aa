"""Intel RealSense RGB-D input through ``pyrealsense2`` (``pip install 'mipslam[realsense]'``).

Two kinds:

- ``realsense``: a connected camera (``dataset.path`` = its serial number, empty = the first one),
  colour ``rgb8`` and depth ``z16`` at ``dataset.width`` x ``dataset.height`` (default 640x480),
  30 frames/s; ``dataset.max_frames`` (required) frames are processed.
- ``realsense_bag``: a recording (``dataset.path``: a ``.bag`` file, or the ``.db3`` rosbag2 file
  that pyrealsense2 >= 2.58 records) played back at full speed, every frame in order, or with
  ``dataset.realtime: true`` at the recorded rate, as a camera would deliver it.

Depth is aligned to the colour camera by librealsense (``rs.align``) unless it is registered to it
already (same pinhole, identity extrinsic); intrinsics (of the colour stream) and the depth scale
come from the device or file; timestamps are the frames' own (milliseconds -> seconds). A camera
(and a real-time playback) runs on while mipslam works: each read takes the newest frame and drops
the older ones (librealsense's own queue is bounded; nothing here queues more than one frame), and
the colour frame numbers never delivered are recorded in :attr:`RealSenseSequence.dropped_frames`
(the gaps also show in ``source_indices`` and in the timestamps of the trajectory). A stream that
ends (camera unplugged, recording over) raises :class:`StreamEnded` at the next frame; the
pipeline then ends the run as if the sequence had been that long.

A limitation of librealsense (2.59, its pipeline): a full-speed playback now and then starts late
(on the project's machine about one start in ten skipped the first frames of an 8-frame recording,
or repeated its last one). Repeats are skipped, gaps after the first delivered frame are recorded
as dropped; frames lost before the first one delivered cannot be seen from here.

``dataset.first_frame`` skips the stream's first frames (e.g. while auto-exposure settles) and
``dataset.stride`` keeps every stride-th of the rest. The frames the run has read stay available
(mapping and loop closure revisit keyframes): they are kept in memory as uint8 colour and uint16
depth (about 1.5 MB per 640x480 frame). Resuming a run re-plays a recording from its start.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from mipslam.optional import import_optional
from mipslam.config import DatasetConfig
from mipslam.datasets.images import downscale_color, downscale_depth
from mipslam.datasets.base import checked_frame_index
from mipslam.errors import DatasetError
from mipslam.types import Frame, Intrinsics

log = logging.getLogger(__name__)

DEFAULT_SIZE = (640, 480)
CAMERA_FPS = 30
# A camera that delivers no frame for this long has stopped (unplugged); a recording that delivers none for
# RECORDING_TIMEOUT_MS (its playback waits for mipslam, so only reading the file takes time) has ended.
FRAME_TIMEOUT_MS = 5000
RECORDING_TIMEOUT_MS = 2000
RECORDING_SUFFIXES = (".bag", ".db3")
# Upper bound of a recording's frame rate (D400 depth streams reach 90 frames/s): its duration times this
# bounds its frame count where the file does not state it.
MAX_RECORDED_FPS = 90
DROP_REPORT_S = 10.0  # at most one log line about dropped frames per this many seconds


def _same_camera(depth_intrinsics, color_intrinsics, depth_to_color) -> bool:
    """True when depth is already registered to colour: the same pinhole and an identity extrinsic."""
    a, b = depth_intrinsics, color_intrinsics
    same_pinhole = (a.width, a.height) == (b.width, b.height) and all(
        abs(x - y) < 1e-6 for x, y in ((a.fx, b.fx), (a.fy, b.fy), (a.ppx, b.ppx), (a.ppy, b.ppy)))
    identity = (np.allclose(np.asarray(depth_to_color.rotation), np.eye(3).ravel(), atol=1e-9)
                and np.allclose(depth_to_color.translation, 0.0, atol=1e-9))
    return bool(same_pinhole and identity)


class StreamEnded(DatasetError):
    """A stream (camera or recording) delivered its last frame before the frame asked for."""


def import_pyrealsense2():
    """The pyrealsense2 module, or DatasetError saying how to install it."""
    return import_optional("pyrealsense2", needed_by="dataset.kind realsense/realsense_bag",
                           install="install it with pip install 'mipslam[realsense]' (or pip install pyrealsense2)",
                           make_error=lambda message: DatasetError(None, message))


class _LazyTimestamps:
    """Timestamps of a live stream: reading entry i waits for frame i (the pipeline reads the timestamp
    of a frame before the frame)."""

    def __init__(self, sequence: "RealSenseSequence"):
        self._sequence = sequence

    def __len__(self) -> int:
        return len(self._sequence)

    def __getitem__(self, index):
        if isinstance(index, (int, np.integer)):
            self._sequence._ensure(int(index))
            return self._sequence._stamps[int(index)]
        return np.asarray(self._sequence._stamps, dtype=np.float64)[index]

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self._sequence._stamps, dtype=dtype or np.float64)


class RealSenseSequence:
    """An :class:`~mipslam.datasets.base.RGBDSequence` over a RealSense camera or recording (see the module).

    Its length is an upper bound until the stream ends (``dataset.max_frames``, or what the recording
    can hold); from then on it is the number of frames delivered.
    """

    # frames arrive one after another from the device or the recording's playback; the length is not known
    # before the stream ends
    random_access = False
    timestamp_kind = "time"

    def __init__(self, cfg: DatasetConfig, *, live_camera: bool):
        self._rs = import_pyrealsense2()
        self.cfg = cfg
        self.downscale = int(cfg.downscale)
        self.live_camera = live_camera
        self.realtime = live_camera or bool(cfg.realtime)
        self._dropped: set[int] = set()  # colour frame numbers never delivered (mipslam was slower, or lost)
        self._store: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # index -> (uint8 colour, uint16 depth)
        self._stamps: list[float] = []
        self._numbers: list[int] = []  # colour frame number of every delivered frame
        self._last_seen = -1  # colour frame number of the newest frameset taken from the stream
        self._taken = 0  # framesets taken from the stream (before first_frame / stride)
        self._ended = False
        self._last_drop_report = -math.inf
        self._playback = None  # the recording's playback device (None for a camera)
        if live_camera:
            self.root = Path(cfg.path or "realsense")
            self.name = f"realsense {cfg.path}".strip()
            if cfg.max_frames <= 0:
                raise DatasetError(None, "dataset.kind realsense needs dataset.max_frames > 0 (how many frames to "
                                         "process; the camera runs until then)")
        else:
            self.root = Path(cfg.path).expanduser()
            self.name = self.root.stem
            self._check_file()
        self._pipeline, self._align, self.full_intrinsics, self.depth_scale, bound = self._start()
        self._length = cfg.max_frames if cfg.max_frames > 0 else bound
        self.intrinsics = self._delivered_intrinsics(self.full_intrinsics)

    @property
    def dropped_frames(self) -> list[int]:
        """Colour frame numbers the stream produced but mipslam never received, ascending."""
        return sorted(self._dropped)

    # ------------------------------------------------------------------ protocol
    @property
    def timestamps(self) -> _LazyTimestamps:
        return _LazyTimestamps(self)

    @property
    def source_indices(self) -> np.ndarray:
        """Colour frame numbers of the frames delivered so far (gaps: dropped or skipped frames)."""
        return np.array(self._numbers, dtype=np.int64)

    @property
    def gt_T_wc(self):
        return None

    @property
    def gt_valid(self) -> np.ndarray:
        return np.zeros(len(self._stamps), dtype=bool)

    def __len__(self) -> int:
        return len(self._stamps) if self._ended else self._length

    def __getitem__(self, index: int) -> Frame:
        index = checked_frame_index(index, len(self))
        self._ensure(index)
        color_u8, depth_u16 = self._store[index]
        color = color_u8.astype(np.float32) / 255.0
        depth = depth_u16.astype(np.float32) * np.float32(self.depth_scale)
        if self.downscale > 1:
            color = downscale_color(color, self.downscale)
            depth = downscale_depth(depth, self.downscale)
        return Frame(index=index, timestamp=float(self._stamps[index]),
                     color=torch.from_numpy(np.ascontiguousarray(color, dtype=np.float32)),
                     depth=torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)),
                     intrinsics=self.intrinsics, T_wc_gt=None)

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
            self._pipeline = None

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"RealSenseSequence({self.name!r}, {len(self)} frames, {i.width}x{i.height}, root={str(self.root)!r})"

    # ------------------------------------------------------------------ opening
    def _check_file(self) -> None:
        if not self.root.is_file():
            what = "folder, expected a RealSense recording file" if self.root.is_dir() else "file not found"
            raise DatasetError(self.root, f"{what}; give a .bag or .db3 recording with --set dataset.path=FILE")
        if self.root.suffix.lower() not in RECORDING_SUFFIXES:
            suffixes = " or ".join(RECORDING_SUFFIXES)
            raise DatasetError(self.root, f"not a RealSense recording (expected a {suffixes} file)")

    def _start(self):
        """Start the stream -> (pipeline, aligner or None, colour intrinsics, depth scale, bound on the frame count).

        Everything is read from the resolved configuration before the stream starts.
        """
        rs = self._rs
        pipeline, config = rs.pipeline(), rs.config()
        if self.live_camera:
            if self.cfg.path:
                config.enable_device(self.cfg.path)
            width, height = self.cfg.width or DEFAULT_SIZE[0], self.cfg.height or DEFAULT_SIZE[1]
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, CAMERA_FPS)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, CAMERA_FPS)
        else:
            config.enable_device_from_file(str(self.root), repeat_playback=False)
        where = None if self.live_camera else self.root
        try:
            resolved = config.resolve(rs.pipeline_wrapper(pipeline))
        except RuntimeError as exc:
            if self.live_camera:
                raise DatasetError(None, f"cannot start the RealSense camera ({str(exc).strip()}); check that it is "
                                         "connected (and that dataset.path is its serial number, or empty)") from None
            raise DatasetError(self.root, f"cannot play it as a RealSense recording ({str(exc).strip()})") from None
        bound = 10**9
        try:
            device = resolved.get_device()
            if not self.live_camera:
                playback = self._playback = device.as_playback()
                playback.set_real_time(self.realtime)  # before it plays, or its first frames pass unread
                bound = int(playback.get_duration().total_seconds() * MAX_RECORDED_FPS) + MAX_RECORDED_FPS
            depth_scale = float(device.first_depth_sensor().get_depth_scale())
            color_profile = resolved.get_stream(rs.stream.color).as_video_stream_profile()
            depth_profile = resolved.get_stream(rs.stream.depth).as_video_stream_profile()
            k = color_profile.get_intrinsics()
            registered = _same_camera(depth_profile.get_intrinsics(), k, depth_profile.get_extrinsics_to(color_profile))
        except RuntimeError as exc:
            raise DatasetError(where, f"the stream has no colour and depth ({str(exc).strip()})") from None
        try:
            pipeline.start(config)
        except RuntimeError as exc:
            raise DatasetError(where, f"cannot start the stream ({str(exc).strip()})") from None
        if any(abs(c) > 1e-6 for c in k.coeffs):
            log.info("the RealSense colour camera reports lens distortion %s; mipslam models a pinhole and ignores it",
                     [round(c, 4) for c in k.coeffs])
        intrinsics = Intrinsics(fx=k.fx, fy=k.fy, cx=k.ppx, cy=k.ppy, width=k.width, height=k.height)
        # Depth already in the colour camera's pixels needs no alignment (which would only resample it, leaving holes).
        return pipeline, None if registered else rs.align(rs.stream.color), intrinsics, depth_scale, bound

    def _delivered_intrinsics(self, full: Intrinsics) -> Intrinsics:
        d = self.downscale
        if full.width < d or full.height < d:
            raise DatasetError(self.root,
                               f"dataset.downscale={d} is larger than the image ({full.width}x{full.height})")
        cropped = full.with_size(full.width - full.width % d, full.height - full.height % d)
        return cropped.scaled(1.0 / d) if d > 1 else cropped

    # ------------------------------------------------------------------ reading
    def _ensure(self, index: int) -> None:
        """Read frames until frame ``index`` has been delivered (StreamEnded if the stream ends first)."""
        while len(self._stamps) <= index:
            frames = self._next_selected()
            if frames is None:
                self._ended = True
                self.close()
                raise StreamEnded(self.root if not self.live_camera else None,
                                  f"the stream ended after {len(self._stamps)} frames")
            self._keep(frames)

    def _next_selected(self):
        """The next frameset that ``first_frame`` and ``stride`` keep, or None at the end of the stream."""
        while True:
            frames = self._next_frameset()
            if frames is None:
                return None
            position = self._taken - 1
            if position >= self.cfg.first_frame and (position - self.cfg.first_frame) % self.cfg.stride == 0:
                return frames

    def _next_frameset(self):
        """The next frameset with colour and depth, newer than the last one taken; in real time the newest one
        waiting (older ones are dropped). None at the end of the stream."""
        if self._pipeline is None:
            return None
        frames = None
        while frames is None:
            try:
                if self._playback is not None and self._playback.current_status() == self._rs.playback_status.stopped:
                    candidate = self._pipeline.poll_for_frames()  # the file is read: only what is queued is left
                    if not candidate:
                        return None
                else:
                    ok, candidate = self._pipeline.try_wait_for_frames(
                        FRAME_TIMEOUT_MS if self._playback is None else RECORDING_TIMEOUT_MS)
                    if not ok:
                        return None
            except RuntimeError:
                return None
            frames = candidate if self._usable(candidate) else None
            if frames is None:
                self._record_unpaired(candidate)
        if self.realtime:
            while newer := self._pipeline.poll_for_frames():
                if self._usable(newer):
                    frames = newer
        number = int(frames.get_color_frame().get_frame_number())
        if self._last_seen >= 0 and number > self._last_seen + 1:
            self._dropped.update(range(self._last_seen + 1, number))
            self._report_drops()
        self._dropped.discard(number)  # an unpaired colour frame whose depth came after all
        self._last_seen = number
        self._taken += 1
        return frames

    def _report_drops(self) -> None:
        """Say how many frames were dropped so far, at most once every ``DROP_REPORT_S`` seconds."""
        now = time.monotonic()
        if now - self._last_drop_report >= DROP_REPORT_S:
            self._last_drop_report = now
            log.info("%s: %d camera frames dropped so far (mipslam is slower than the camera; the newest frame is "
                     "processed each time)", self.name, len(self._dropped))

    def _record_unpaired(self, frames) -> None:
        """A colour frame the stream delivered without its depth (librealsense's syncer does that, mostly for
        the first frames of a playback) is lost to mipslam: record it as dropped."""
        color = frames.get_color_frame()
        if color and int(color.get_frame_number()) > self._last_seen:
            number = int(color.get_frame_number())
            self._dropped.add(number)

    def _usable(self, frames) -> bool:
        color = frames.get_color_frame()
        return bool(color and frames.get_depth_frame() and int(color.get_frame_number()) > self._last_seen)

    def _keep(self, frames) -> None:
        """Append a frameset as the next frame."""
        aligned = self._align.process(frames) if self._align is not None else frames
        color_frame, depth_frame = aligned.get_color_frame(), aligned.get_depth_frame()
        color = np.asanyarray(color_frame.get_data())
        fmt = color_frame.get_profile().format()
        rs = self._rs
        if fmt == rs.format.bgr8:
            color = color[..., ::-1]
        elif fmt == rs.format.rgba8:
            color = color[..., :3]
        elif fmt == rs.format.bgra8:
            color = color[..., 2::-1]
        elif fmt != rs.format.rgb8:
            raise DatasetError(self.root, f"colour format {fmt} is not supported (rgb8, bgr8, rgba8 or bgra8)")
        depth = np.asanyarray(depth_frame.get_data())
        self._store[len(self._stamps)] = (np.array(color, dtype=np.uint8), np.array(depth, dtype=np.uint16))
        self._stamps.append(color_frame.get_timestamp() / 1000.0)
        self._numbers.append(int(color_frame.get_frame_number()))
