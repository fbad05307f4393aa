"""TUM RGB-D trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line.

Format (Sturm et al., 2012, https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats):
one pose per line, timestamp in seconds, position in metres, unit quaternion in the file order
``qx qy qz qw`` (scalar last); the pose is camera-to-world ``T_wc``. Lines starting with ``#`` are
comments. Like evo's reader we take space separated fields; commas are accepted as well.

Inside mipslam a trajectory is a :class:`Trajectory` of 4x4 matrices; quaternions exist only at
this file boundary and every variable that holds one names its order (``_xyzw`` / ``_wxyz``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mipslam.errors import DatasetError
from mipslam.geometry import quat_wxyz_to_rotmat, quat_wxyz_to_xyzw, quat_xyzw_to_wxyz, rigidity_error, rotmat_to_quat_wxyz
from mipslam.io.run_folder import write_text_atomic

logger = logging.getLogger(__name__)

TUM_FIELDS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
# A quaternion whose norm lies inside these bounds is taken as a rounded unit quaternion and
# normalised; outside them the line is more likely garbage (or another format) than rounding.
QUATERNION_NORM_MIN = 0.9
QUATERNION_NORM_MAX = 1.1
# Poses written to a file must be rigid to this tolerance (float32 optimiser output is ~1e-6 off).
WRITE_RIGIDITY_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A timed sequence of camera-to-world poses.

    timestamps: seconds, float64                 # [N]
    T_wc: camera-to-world rigid transforms       # [N, 4, 4] float64
    The constructor copies both into contiguous float64 arrays; it checks shapes only (the file
    reader checks the values: finiteness, quaternion norms, sorted timestamps).
    """

    timestamps: np.ndarray
    T_wc: np.ndarray

    def __post_init__(self):
        timestamps = np.array(self.timestamps, dtype=np.float64, copy=True).reshape(-1)
        T_wc = np.array(self.T_wc, dtype=np.float64, copy=True)
        if T_wc.ndim != 3 or T_wc.shape[1:] != (4, 4):
            raise ValueError(f"Trajectory.T_wc must have shape [N, 4, 4], got {list(T_wc.shape)}")
        if T_wc.shape[0] != timestamps.shape[0]:
            raise ValueError(
                f"Trajectory has {timestamps.shape[0]} timestamps but {T_wc.shape[0]} poses; they must match"
            )
        timestamps.setflags(write=False)
        T_wc.setflags(write=False)
        object.__setattr__(self, "timestamps", timestamps)
        object.__setattr__(self, "T_wc", T_wc)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """Camera centres in the world frame, metres.  -> [N, 3]"""
        return self.T_wc[:, :3, 3]

    @property
    def time_range(self) -> tuple[float, float]:
        """(first, last) timestamp in seconds; (nan, nan) for an empty trajectory."""
        if len(self) == 0:
            return (math.nan, math.nan)
        return (float(self.timestamps[0]), float(self.timestamps[-1]))

    def subset(self, indices: np.ndarray) -> "Trajectory":
        """The poses at ``indices`` (in that order).  indices [M] int -> Trajectory of M poses"""
        indices = np.asarray(indices, dtype=np.int64)
        return Trajectory(self.timestamps[indices], self.T_wc[indices])

    @staticmethod
    def from_tum_arrays(timestamps: np.ndarray, positions: np.ndarray, quats_xyzw: np.ndarray) -> "Trajectory":
        """Build from TUM columns.  timestamps [N] s, positions [N, 3] m, quats_xyzw [N, 4] (normalised here)"""
        quats_wxyz = quat_xyzw_to_wxyz(torch.tensor(np.asarray(quats_xyzw, dtype=np.float64)))  # [N, 4]
        rotations = quat_wxyz_to_rotmat(quats_wxyz).numpy()  # [N, 3, 3]
        n = rotations.shape[0]
        T_wc = np.tile(np.eye(4), (n, 1, 1))
        T_wc[:, :3, :3] = rotations
        T_wc[:, :3, 3] = np.asarray(positions, dtype=np.float64)
        return Trajectory(timestamps, T_wc)

    def to_tum_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(timestamps [N], positions [N, 3], quats_xyzw [N, 4] with qw >= 0)."""
        quats_wxyz = rotmat_to_quat_wxyz(torch.tensor(self.T_wc[:, :3, :3]))  # [N, 4]
        quats_xyzw = quat_wxyz_to_xyzw(quats_wxyz).numpy()
        return self.timestamps.copy(), self.positions.copy(), quats_xyzw


def _parse_fields(line: str) -> list[str]:
    """Fields of one data line: separated by spaces/tabs and/or commas."""
    return line.replace(",", " ").split()


def read_tum_trajectory(path: str | Path, *, allow_duplicate_timestamps: bool = False) -> Trajectory:
    """Read a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, camera-to-world).

    Skips blank lines and lines starting with ``#``. Quaternions within
    [QUATERNION_NORM_MIN, QUATERNION_NORM_MAX] of unit norm are normalised.
    Raises DatasetError (naming the file and line) for: a missing/unreadable file, a line without
    exactly 8 fields, a field that is not a number, NaN/Inf, a zero or far-from-unit quaternion,
    a timestamp smaller than the previous one, a timestamp equal to the previous one (unless
    ``allow_duplicate_timestamps``: then both poses are kept, in file order, exactly as evo keeps
    them; the official TUM ground truth of freiburg2_desk has such a pair at line 10863), and a
    file without any pose.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "trajectory file not found (expected a TUM file: timestamp tx ty tz qx qy qz qw)")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read trajectory file as UTF-8 text: {exc}") from exc

    rows: list[list[float]] = []
    line_numbers: list[int] = []
    duplicate_lines: list[int] = []
    for line_number, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.strip()
        if not line or line.startswith("#"):
            continue
        fields = _parse_fields(line)
        if len(fields) != len(TUM_FIELDS):
            raise DatasetError(
                path,
                f"expected {len(TUM_FIELDS)} numbers ({' '.join(TUM_FIELDS)}), found {len(fields)}: '{line[:80]}'",
                line=line_number,
            )
        values = []
        for name, field_text in zip(TUM_FIELDS, fields):
            try:
                value = float(field_text)
            except ValueError:
                raise DatasetError(path, f"field '{name}' is not a number: '{field_text}'", line=line_number) from None
            if not math.isfinite(value):
                raise DatasetError(path, f"field '{name}' is not finite: '{field_text}'", line=line_number)
            values.append(value)
        quat_xyzw_norm = math.sqrt(sum(v * v for v in values[4:8]))
        if quat_xyzw_norm == 0.0:
            raise DatasetError(path, "quaternion qx qy qz qw is zero; it must be a unit quaternion", line=line_number)
        if not QUATERNION_NORM_MIN <= quat_xyzw_norm <= QUATERNION_NORM_MAX:
            raise DatasetError(
                path,
                f"quaternion qx qy qz qw has norm {quat_xyzw_norm:.6g}, far from 1 (accepted: "
                f"[{QUATERNION_NORM_MIN}, {QUATERNION_NORM_MAX}]); is the column order timestamp tx ty tz qx qy qz qw?",
                line=line_number,
            )
        if rows:
            previous = rows[-1][0]
            if values[0] == previous and not allow_duplicate_timestamps:
                raise DatasetError(
                    path,
                    f"duplicate timestamp {fields[0]} (also on line {line_numbers[-1]}); if this is a rounding "
                    "duplicate (the TUM benchmark's own ground truth has a few), read the file with "
                    "allow_duplicate_timestamps=True to keep both poses as evo does",
                    line=line_number,
                )
            if values[0] == previous:
                duplicate_lines.append(line_number)
            if values[0] < previous:
                raise DatasetError(
                    path,
                    f"timestamps must increase: {fields[0]} comes after {previous:.6f} (line {line_numbers[-1]}); "
                    "sort the file by its first column",
                    line=line_number,
                )
        rows.append(values)
        line_numbers.append(line_number)

    if not rows:
        raise DatasetError(path, "trajectory file contains no poses (only blank or '#' comment lines)")
    if duplicate_lines:
        logger.warning(
            "%s: %d pose(s) share their timestamp with the previous line (lines %s); both kept",
            path, len(duplicate_lines), ", ".join(str(n) for n in duplicate_lines[:5]),
        )
    table = np.asarray(rows, dtype=np.float64)  # [N, 8]
    quats_xyzw = table[:, 4:8] / np.linalg.norm(table[:, 4:8], axis=1, keepdims=True)  # [N, 4]
    logger.debug("read %d poses from %s", table.shape[0], path)
    return Trajectory.from_tum_arrays(table[:, 0], table[:, 1:4], quats_xyzw)


def _to_numpy_float64(array) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().to(torch.float64).numpy()
    return np.asarray(array, dtype=np.float64)


def write_tum_trajectory(path: str | Path, timestamps, T_wc) -> Path:
    """Write poses as a TUM trajectory file, atomically (temporary file, fsync, ``os.replace``).

    timestamps: seconds                           # [N] (numpy or torch)
    T_wc: camera-to-world rigid transforms        # [N, 4, 4] (numpy or torch)
    Timestamps are written with 6 decimals (microseconds), positions and quaternions (``qx qy qz
    qw``, ``qw >= 0``) with 9. Creates the parent folder. Raises DatasetError (naming the file)
    for mismatched shapes, non-finite values, non-rigid matrices or timestamps that do not increase
    at the printed precision (the file could not be read back); nothing is written then.
    Returns the path written.
    """
    path = Path(path)
    timestamps = _to_numpy_float64(timestamps).reshape(-1)  # [N]
    T_wc = _to_numpy_float64(T_wc)  # [N, 4, 4]
    if T_wc.ndim != 3 or T_wc.shape[1:] != (4, 4) or T_wc.shape[0] != timestamps.shape[0]:
        raise DatasetError(
            path,
            f"cannot write trajectory: need timestamps [N] and T_wc [N, 4, 4], got {list(timestamps.shape)} "
            f"and {list(T_wc.shape)}",
        )
    bad_time = np.flatnonzero(~np.isfinite(timestamps))
    if bad_time.size:
        raise DatasetError(path, f"cannot write trajectory: timestamp of pose {int(bad_time[0])} is not finite")
    rigidity = rigidity_error(torch.tensor(T_wc)).numpy() if len(T_wc) else np.zeros(0)  # [N]
    bad_pose = np.flatnonzero(~(rigidity <= WRITE_RIGIDITY_TOLERANCE))
    if bad_pose.size:
        i = int(bad_pose[0])
        raise DatasetError(
            path,
            f"cannot write trajectory: pose {i} (t={timestamps[i]:.6f}) is not a finite rigid transform "
            f"(rigidity error {rigidity[i]:.3g} > {WRITE_RIGIDITY_TOLERANCE})",
        )
    stamp_texts = [f"{t:.6f}" for t in timestamps]
    printed = np.array([float(text) for text in stamp_texts])  # [N] what a reader will see
    not_increasing = np.flatnonzero(np.diff(printed) <= 0)
    if not_increasing.size:
        i = int(not_increasing[0]) + 1
        raise DatasetError(
            path,
            f"cannot write trajectory: timestamp of pose {i} ({stamp_texts[i]}) is not larger than that of pose "
            f"{i - 1} ({stamp_texts[i - 1]}) at the file's microsecond precision",
        )
    _, positions, quats_xyzw = Trajectory(timestamps, T_wc).to_tum_arrays()
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, written by mipslam)\n"]
    for t_text, p, q_xyzw in zip(stamp_texts, positions, quats_xyzw):
        lines.append(
            f"{t_text} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q_xyzw[0]:.9f} {q_xyzw[1]:.9f} {q_xyzw[2]:.9f} {q_xyzw[3]:.9f}\n"
        )

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(path, f"cannot create the folder ({exc.strerror or exc}); choose a writable output path") from exc
    # The run folder's atomic write: temporary file, fsync, rename, fsync of the folder; an OSError
    # (disk full, permission) becomes a one-line MipslamError naming the file, the old file unchanged.
    write_text_atomic(path, "".join(lines))
    logger.debug("wrote %d poses to %s", len(stamp_texts), path)
    return path
