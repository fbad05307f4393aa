"""The one interface every RGB-D reader offers, and the machinery the readers share.

A reader resolves, at construction, the list of frames (file paths, timestamps, original frame
numbers, ground-truth poses), applies the frame selection (``first_frame``, then every
``stride``-th frame, then at most ``max_frames``; 0 = all) and the intrinsics; images are read
only when a frame is accessed (``seq[i]``). All validation that needs no pixels (lists, poses,
files present) happens at construction, so a broken folder fails before any work starts.
"""
from __future__ import annotations

import logging
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal, Protocol, runtime_checkable

import numpy as np
import torch

from mipslam.datasets.images import (DepthRegistration, LensUndistortion, downscale_color, downscale_depth, read_color,
                                     read_depth)
from mipslam.errors import DatasetError
from mipslam.geometry import so3_exp
from mipslam.types import Frame, Intrinsics

logger = logging.getLogger(__name__)

# A ground-truth pose whose rotation deviates from orthonormal by more than this is rejected.
RIGIDITY_TOLERANCE = 1e-4


@runtime_checkable
class RGBDSequence(Protocol):
    """A finite, indexable RGB-D sequence (after frame selection and downscaling).

    name: human-readable name of the sequence
    root: the dataset folder
    intrinsics: pinhole intrinsics of the delivered images (after downscale)
    depth_scale: stored depth value / depth_scale = metres
    timestamps: float64 [N]; seconds for TUM ("time"), the original frame number for Replica ("index")
    timestamp_kind: "time" | "index"
    source_indices: int64 [N]; original frame numbers (Replica: the number in the file name;
        TUM: the position among the associated rgb-depth pairs), before first_frame/stride/max_frames
    gt_T_wc: float64 [N, 4, 4] camera-to-world ground truth, or None when the sequence has none;
        rows where ``gt_valid`` is False hold the identity and must not be used
    gt_valid: bool [N]; all False when ``gt_T_wc`` is None
    ``seq[i]`` -> Frame (images read now); IndexError outside [0, N)
    random_access: True when frames can be read in any order and ahead of use (files); False for a stream
        (a camera or a recording's playback), whose length is not known before it ends
    """

    name: str
    root: Path
    intrinsics: Intrinsics
    depth_scale: float
    timestamp_kind: Literal["time", "index"]
    random_access: bool

    @property
    def timestamps(self) -> np.ndarray: ...

    @property
    def source_indices(self) -> np.ndarray: ...

    @property
    def gt_T_wc(self) -> torch.Tensor | None: ...

    @property
    def gt_valid(self) -> np.ndarray: ...

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Frame: ...


@dataclass(frozen=True)
class FrameRecord:
    """What a reader knows about one frame before reading its pixels."""

    color_path: Path
    depth_path: Path
    timestamp: float
    source_index: int
    depth_time_offset: float = 0.0  # the depth image's timestamp minus the colour image's (seconds)


def select_indices(total: int, first_frame: int, stride: int, max_frames: int, where: Path) -> list[int]:
    """Positions kept by the common options: ``range(first_frame, total, stride)[:max_frames or all]``."""
    if total == 0:
        raise DatasetError(where, "the sequence has no frames; check that the folder holds a complete dataset")
    if first_frame >= total:
        raise DatasetError(
            where, f"dataset.first_frame={first_frame} is beyond the sequence, which has {total} frames (0..{total - 1})"
        )
    indices = list(range(first_frame, total, stride))
    if max_frames > 0:
        indices = indices[:max_frames]
    return indices


class SequenceBase:
    """Shared implementation: selection, lazy loading, downscaling, validation of pixels.

    Subclasses call :meth:`_setup` once with the full frame list and ground truth.
    """

    name: str
    root: Path
    timestamp_kind: Literal["time", "index"]
    random_access = True  # frames are files: any frame can be read at any time, also ahead of use

    def _setup(
        self,
        *,
        records: list[FrameRecord],
        gt_T_wc: torch.Tensor | None,  # [M, 4, 4] float64, one per record, or None
        gt_valid: np.ndarray | None,  # bool [M]
        camera: tuple[float, float, float, float],  # fx, fy, cx, cy of the images on disk (pixels)
        expected_size: tuple[int, int] | None,  # (width, height) promised by a file or the config; None = any
        size_source: str,  # where expected_size came from, for the error message
        depth_scale: float,
        first_frame: int,
        stride: int,
        max_frames: int,
        downscale: int,
        where: Path,
        distortion: tuple[float, ...] = (),  # (k1, k2, p1, p2[, k3]) of the images on disk; () = none
        depth_intrinsics: tuple[float, ...] = (),  # fx, fy, cx, cy of a depth camera not registered to colour
        depth_extrinsics: tuple[float, ...] = (),  # its pose in the colour camera: [tx, ty, tz(, rx, ry, rz)]
    ) -> None:
        keep = select_indices(len(records), first_frame, stride, max_frames, where)
        self._records = [records[k] for k in keep]
        for record in self._records:
            for path, what in ((record.color_path, "colour"), (record.depth_path, "depth")):
                if not path.is_file():
                    raise DatasetError(path, f"{what} image listed for frame {record.source_index} is missing on disk")
        self.depth_scale = float(depth_scale)
        self.downscale = int(downscale)
        self._timestamps = np.array([r.timestamp for r in self._records], dtype=np.float64)
        self._source_indices = np.array([r.source_index for r in self._records], dtype=np.int64)
        self._depth_time_offsets = np.array([r.depth_time_offset for r in self._records], dtype=np.float64)
        if gt_T_wc is None:
            self._gt_T_wc = None
            self._gt_valid = np.zeros(len(keep), dtype=bool)
        else:
            index = torch.as_tensor(keep, dtype=torch.long)
            self._gt_T_wc = gt_T_wc.to(torch.float64)[index].contiguous()
            self._gt_valid = np.asarray(gt_valid, dtype=bool)[keep].copy()
        first_color = self._records[0].color_path
        width, height = image_size(first_color)
        if expected_size is not None and (width, height) != tuple(expected_size):
            raise DatasetError(
                first_color,
                f"colour image is {width}x{height} but {size_source} says {expected_size[0]}x{expected_size[1]}; "
                "fix the size there (or unset it to take the size from the images)",
            )
        fx, fy, cx, cy = (float(v) for v in camera)
        self.full_intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
        self.intrinsics = self._delivered_intrinsics(self.full_intrinsics)
        self.distortion = tuple(float(v) for v in distortion)
        self._undistortion = (LensUndistortion((fx, fy, cx, cy), self.distortion, (width, height))
                              if any(v != 0.0 for v in self.distortion) else None)
        # unregistered depth is downscaled first and registered at the delivered resolution (d^2 fewer points)
        self._registration = depth_registration(depth_intrinsics, depth_extrinsics, self.full_intrinsics,
                                                self.intrinsics, self.downscale)

    def _delivered_intrinsics(self, full: Intrinsics) -> Intrinsics:
        d = self.downscale
        if full.width < d or full.height < d:
            raise DatasetError(self.root, f"dataset.downscale={d} is larger than the image ({full.width}x{full.height})")
        cropped = full.with_size(full.width - full.width % d, full.height - full.height % d)
        return cropped.scaled(1.0 / d) if d > 1 else cropped

    # ------------------------------------------------------------------ protocol
    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    @property
    def source_indices(self) -> np.ndarray:
        return self._source_indices

    @property
    def gt_T_wc(self) -> torch.Tensor | None:
        return self._gt_T_wc

    @property
    def gt_valid(self) -> np.ndarray:
        return self._gt_valid

    @property
    def frame_paths(self) -> list[tuple[Path, Path]]:
        """(colour, depth) file of every selected frame."""
        return [(r.color_path, r.depth_path) for r in self._records]

    def __len__(self) -> int:
        return len(self._records)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Frame:
        index = checked_frame_index(index, len(self))
        record = self._records[index]
        color = read_color(record.color_path)  # [H, W, 3]
        depth = read_depth(record.depth_path, self.depth_scale)  # [H, W]
        full = self.full_intrinsics
        if color.shape[:2] != (full.height, full.width):
            raise DatasetError(
                record.color_path,
                f"colour image is {color.shape[1]}x{color.shape[0]} but the sequence is {full.width}x{full.height}; "
                "all frames must have the size of the first one (or of the configured width/height)",
            )
        if self._registration is not None:  # a depth camera of its own: any size, moved into the colour camera
            depth = self._registration(downscale_depth(depth, self.downscale))
        elif depth.shape != color.shape[:2]:
            raise DatasetError(
                record.depth_path,
                f"depth image is {depth.shape[1]}x{depth.shape[0]} but its colour image {record.color_path.name} is "
                f"{color.shape[1]}x{color.shape[0]}; colour and depth must be registered at the same size",
            )
        if self._undistortion is not None:
            color = self._undistortion.color(color)
            if self._registration is None:  # the coefficients are the colour camera's
                depth = self._undistortion.depth(depth)
        if self.downscale > 1:
            color = downscale_color(color, self.downscale)
            if self._registration is None:
                depth = downscale_depth(depth, self.downscale)
        T_wc = None
        if self._gt_T_wc is not None and self._gt_valid[index]:
            T_wc = self._gt_T_wc[index].clone()
        return Frame(
            index=index,
            timestamp=float(self._timestamps[index]),
            color=torch.from_numpy(np.ascontiguousarray(color, dtype=np.float32)),
            depth=torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)),
            intrinsics=self.intrinsics,
            T_wc_gt=T_wc,
            depth_time_offset=float(self._depth_time_offsets[index]),
        )

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"{type(self).__name__}({self.name!r}, {len(self)} frames, {i.width}x{i.height}, root={str(self.root)!r})"


def depth_registration(depth_intrinsics: tuple[float, ...], depth_extrinsics: tuple[float, ...],
                       color_on_disk: Intrinsics, delivered: Intrinsics, downscale: int) -> DepthRegistration | None:
    """The registration of depth images from a camera of their own (``dataset.depth_intrinsics`` fx, fy, cx, cy at
    its images' resolution, default the colour camera's ``color_on_disk``; ``dataset.depth_extrinsics`` [tx, ty, tz]
    metres, optionally then a rotation vector [rx, ry, rz] radians: the depth camera's pose in the colour camera's
    frame) into the ``delivered`` colour camera, for depth images already downscaled by ``downscale``; None when
    neither key is given (depth registered to colour)."""
    if not depth_intrinsics and not depth_extrinsics:
        return None
    fx, fy, cx, cy = (tuple(depth_intrinsics) if depth_intrinsics else
                      (color_on_disk.fx, color_on_disk.fy, color_on_disk.cx, color_on_disk.cy))
    on_disk = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=color_on_disk.width, height=color_on_disk.height)
    depth_camera = on_disk.scaled(1.0 / downscale) if downscale > 1 else on_disk
    T_cd = np.eye(4)
    if depth_extrinsics:
        T_cd[:3, 3] = depth_extrinsics[:3]
        if len(depth_extrinsics) == 6:
            T_cd[:3, :3] = so3_exp(torch.tensor(depth_extrinsics[3:], dtype=torch.float64)).numpy()
    return DepthRegistration((depth_camera.fx, depth_camera.fy, depth_camera.cx, depth_camera.cy), T_cd,
                             (delivered.fx, delivered.fy, delivered.cx, delivered.cy),
                             (delivered.width, delivered.height))


def checked_frame_index(index, length: int) -> int:
    """``index`` as an int in [0, length); TypeError for a non-integer, IndexError outside the sequence."""
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
        raise TypeError(f"frame index must be an integer, got {type(index).__name__}")
    index = int(index)
    if not 0 <= index < length:
        raise IndexError(f"frame index {index} out of range for a sequence of {length} frames")
    return index


def read_json(path: Path):
    """A JSON file of a dataset folder; DatasetError naming the file (and line for syntax errors)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DatasetError(path, f"invalid JSON ({exc.msg})", exc.lineno) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read file ({exc})") from None


def read_text_rows(path: Path) -> list[tuple[int, list[str]]]:
    """Non-empty, non-comment (``#``) lines of a text file as (1-based line number, fields)."""
    if not path.is_file():
        what = "folder, expected a file" if path.is_dir() else "file not found"
        raise DatasetError(path, what)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(path, f"not a text file (undecodable byte at offset {exc.start})") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read file ({exc.strerror or exc})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        rows.append((number, stripped.replace(",", " ").split()))
    return rows


def parse_float(text: str, path: Path, line: int, what: str) -> float:
    """A finite float, or DatasetError naming the file and line."""
    try:
        value = float(text)
    except ValueError:
        raise DatasetError(path, f"{what} {text!r} is not a number", line) from None
    if not np.isfinite(value):
        raise DatasetError(path, f"{what} is not finite ({text})", line)
    return value


def check_increasing(values: list[float], lines: list[int], path: Path, what: str) -> None:
    """DatasetError at the first value that is not strictly larger than the previous one."""
    for k in range(1, len(values)):
        if values[k] == values[k - 1]:
            raise DatasetError(path, f"duplicate {what} {values[k]!r} (also on line {lines[k - 1]})", lines[k])
        if values[k] < values[k - 1]:
            raise DatasetError(
                path, f"{what}s are not sorted: {values[k]!r} comes after {values[k - 1]!r} (line {lines[k - 1]})", lines[k]
            )


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of a colour image file (decoded once; errors as in read_color)."""
    color = read_color(path)
    return color.shape[1], color.shape[0]
