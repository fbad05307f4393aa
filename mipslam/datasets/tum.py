"""TUM RGB-D (Sturm et al., 2012).

Folder::

    rgb.txt          "timestamp filename" per line after '#' comments (filename relative to the folder)
    depth.txt        the same for the depth images (uint16 PNG, metres = value / 5000)
    groundtruth.txt  optional: "timestamp tx ty tz qx qy qz qw", camera-to-world, quaternion in TUM order

Association of colour and depth: as TUM's ``associate.py`` does it. Every (rgb, depth) pair whose
timestamps differ by less than ``association_tolerance_s`` is a candidate; candidates are taken in
order of increasing difference, each rgb and each depth image used at most once; the pairs are
then sorted by the rgb timestamp, which becomes the frame's timestamp (seconds,
``timestamp_kind == "time"``). Colour images without a depth partner are dropped (logged).

Ground truth at a frame's timestamp ``t``: the motion-capture poses come at about 100 Hz, the
frames at 30 Hz, so the nearest pose can be up to ~5 ms off, i.e. several millimetres at normal
hand-held speed. Therefore: a ground-truth sample with exactly the timestamp ``t`` is used as is;
otherwise, when the samples just before and just after ``t`` both lie within the tolerance, the
pose is interpolated between them (translation linearly, rotation along the geodesic, i.e. SLERP);
otherwise the nearest sample within the tolerance is used (at the ends of the ground truth);
otherwise the frame has no ground truth: ``gt_valid[i]`` is False, ``gt_T_wc[i]`` holds the
identity (never NaN) and ``seq[i].T_wc_gt`` is None. Without ``groundtruth.txt`` (TUM's
validation/test sequences) ``gt_T_wc`` is None.

Camera: ``dataset.camera`` = freiburg1 | freiburg2 | freiburg3 selects the calibration published on
the TUM benchmark page; when unset, the folder name (``freiburg1``, ``fr1`` ...) or the comment
header of rgb.txt (which names the recording) decides; explicit ``dataset.fx, fy, cx, cy`` override
the preset value by value (all four are needed when no preset applies). ``dataset.depth_scale``
overrides 5000. Width and height always come from the images. Lens distortion: none unless
``dataset.distortion`` gives it. The presets leave TUM's images raw, as TUM advises for its pre-registered
depth: with freiburg1's published coefficients the colour residual of fr1_xyz frame pairs under the
ground-truth poses rises (median 0.0170 -> 0.0175; colour alone undistorted 0.0177).
"""
from __future__ import annotations

import difflib
import logging
import re
from pathlib import Path

import numpy as np
import torch

from mipslam.config import DatasetConfig
from mipslam.datasets.base import (
    FrameRecord,
    SequenceBase,
    check_increasing,
    parse_float,
    read_text_rows,
)
from mipslam.errors import ConfigError, DatasetError
from mipslam.io.tum import read_tum_trajectory as read_trajectory_file
from mipslam.geometry import interpolate_pose

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
# fx, fy, cx, cy of the TUM RGB-D cameras (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
TUM_CAMERAS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
# A quaternion in groundtruth.txt whose norm is further than this from 1 is rejected (files carry 4 decimals).
_CAMERA_IN_NAME = re.compile(r"(?:^|[^a-z0-9])(?:freiburg|fr)([123])(?![0-9])")


def guess_tum_camera(*texts: str) -> str | None:
    """'freiburgN' when the first text that names one (``freiburg2``, ``fr2_desk`` ...) does, else None."""
    for text in texts:
        match = _CAMERA_IN_NAME.search(text.lower())
        if match:
            return f"freiburg{match.group(1)}"
    return None


def read_tum_list(path: Path) -> tuple[np.ndarray, list[str], list[int]]:
    """An rgb.txt / depth.txt list.  -> (timestamps float64 [N], file names, line numbers)

    Raises DatasetError (file and line) for a line that is not "timestamp filename", a bad
    timestamp, unsorted or duplicate timestamps, or an empty list.
    """
    rows = read_text_rows(path)
    stamps, names, lines = [], [], []
    for line, fields in rows:
        if len(fields) != 2:
            raise DatasetError(path, f"expected 'timestamp filename', got {len(fields)} fields", line)
        stamps.append(parse_float(fields[0], path, line, "timestamp"))
        names.append(fields[1])
        lines.append(line)
    if not stamps:
        raise DatasetError(path, "lists no images; the sequence is empty")
    check_increasing(stamps, lines, path, "timestamp")
    return np.asarray(stamps, dtype=np.float64), names, lines


def read_ground_truth(path: Path) -> tuple[np.ndarray, torch.Tensor]:
    """A TUM ground-truth file (groundtruth.txt).  -> (timestamps float64 [M], T_wc float64 [M, 4, 4])

    Read and validated by :func:`mipslam.io.tum.read_tum_trajectory` (DatasetError with file and
    line). The benchmark's own files repeat a timestamp now and then (fr2_desk line 10863); the
    first pose of a repeated timestamp is kept so interpolation between neighbours stays defined.
    """
    trajectory = read_trajectory_file(path, allow_duplicate_timestamps=True)
    keep = np.concatenate([[True], np.diff(trajectory.timestamps) > 0])
    if not keep.all():
        logger.info("%s: %d repeated timestamp(s); the first pose of each is used", path, int((~keep).sum()))
    return trajectory.timestamps[keep].copy(), torch.from_numpy(trajectory.T_wc[keep].copy())


def associate_timestamps(first: np.ndarray, second: np.ndarray, tolerance: float) -> list[tuple[int, int]]:
    """Greedy one-to-one association by timestamp, as TUM's associate.py.  first [N], second [M] -> [(i, j)]

    Candidates are pairs with ``|first[i] - second[j]| < tolerance``; they are accepted in order of
    increasing difference (ties: smaller i, then smaller j) when neither side is taken yet. The
    result is sorted by i. Both inputs must be sorted ascending.
    """
    candidates = []
    for i, t in enumerate(first):
        lo = int(np.searchsorted(second, t - tolerance, side="left"))
        hi = int(np.searchsorted(second, t + tolerance, side="right"))
        for j in range(lo, hi):
            diff = abs(float(t) - float(second[j]))
            if diff < tolerance:
                candidates.append((diff, i, j))
    candidates.sort()
    used_first, used_second, pairs = set(), set(), []
    for _, i, j in candidates:
        if i in used_first or j in used_second:
            continue
        used_first.add(i)
        used_second.add(j)
        pairs.append((i, j))
    pairs.sort()
    return pairs


def poses_at_times(
    gt_times: np.ndarray,  # [M] float64 seconds, strictly increasing
    gt_T_wc: torch.Tensor,  # [M, 4, 4] float64
    times: np.ndarray,  # [N] float64 seconds
    tolerance: float,
) -> tuple[torch.Tensor, np.ndarray]:
    """Ground-truth poses at ``times`` (exact, interpolated or nearest; see the module docstring).

    Returns (T_wc [N, 4, 4] float64 with the identity where invalid, valid bool [N]).
    """
    n = len(times)
    out = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    valid = np.zeros(n, dtype=bool)
    m = len(gt_times)
    for k, t in enumerate(times):
        j = int(np.searchsorted(gt_times, t, side="left"))
        if j < m and gt_times[j] == t:
            out[k] = gt_T_wc[j]
            valid[k] = True
            continue
        before = j - 1 if j - 1 >= 0 and t - gt_times[j - 1] <= tolerance else None
        after = j if j < m and gt_times[j] - t <= tolerance else None
        if before is not None and after is not None:
            w = (t - gt_times[before]) / (gt_times[after] - gt_times[before])
            out[k] = interpolate_pose(gt_T_wc[before], gt_T_wc[after], float(w))
            valid[k] = True
        elif before is not None or after is not None:
            out[k] = gt_T_wc[before if after is None else after]
            valid[k] = True
    return out, valid


def resolve_tum_camera(cfg: DatasetConfig, root: Path, rgb_list: Path) -> tuple[tuple[float, float, float, float], str]:
    """(fx, fy, cx, cy) and a description of where they came from (see the module docstring)."""
    preset_name = cfg.camera.strip().lower()
    source = f"dataset.camera={preset_name}"
    if preset_name and preset_name not in TUM_CAMERAS:
        near = difflib.get_close_matches(preset_name, list(TUM_CAMERAS), n=1)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise ConfigError(
            f"config key 'dataset.camera': unknown TUM camera '{cfg.camera}'{hint}; choose one of "
            f"{', '.join(TUM_CAMERAS)} or set dataset.fx, fy, cx, cy"
        )
    explicit = {"fx": cfg.fx, "fy": cfg.fy, "cx": cfg.cx, "cy": cfg.cy}
    if not preset_name and any(v is None for v in explicit.values()):
        header = ""
        if rgb_list.is_file():
            try:
                header = "\n".join(line for line in rgb_list.read_text(encoding="utf-8").splitlines()[:10] if line.startswith("#"))
            except (OSError, UnicodeDecodeError):
                header = ""
        guessed = guess_tum_camera(root.resolve().name, header)
        if guessed is not None:
            preset_name = guessed
            source = f"{guessed} (guessed from the folder name or the rgb.txt header)"
            logger.info("%s: using the %s calibration; set dataset.camera to choose another", root, guessed)
    preset = TUM_CAMERAS.get(preset_name)
    missing = [k for k, v in explicit.items() if v is None and preset is None]
    if missing:
        raise DatasetError(
            root,
            "cannot tell which camera recorded this TUM-layout sequence; set dataset.camera=freiburg1|freiburg2|freiburg3 "
            f"or the intrinsics {', '.join('dataset.' + k for k in missing)}",
        )
    values = tuple(float(explicit[k]) if explicit[k] is not None else preset[i] for i, k in enumerate(("fx", "fy", "cx", "cy")))
    if any(v is not None for v in explicit.values()):
        source = "config dataset.fx..cy" + (f" over {source}" if preset is not None else "")
    return values, source  # type: ignore[return-value]


class TUMSequence(SequenceBase):
    """A TUM RGB-D folder as an :class:`~mipslam.datasets.RGBDSequence`."""

    timestamp_kind = "time"

    def __init__(self, root: str | Path, cfg: DatasetConfig | None = None, *, name: str | None = None):
        cfg = cfg or DatasetConfig(kind="tum", path=str(root))
        self.root = Path(root)
        self.name = name or f"tum:{self.root.name}"
        if not self.root.is_dir():
            raise DatasetError(self.root, "dataset folder not found; set dataset.path to a TUM RGB-D folder (rgb.txt, depth.txt)")
        rgb_list, depth_list = self.root / "rgb.txt", self.root / "depth.txt"
        rgb_times, rgb_names, _ = read_tum_list(rgb_list)
        depth_times, depth_names, _ = read_tum_list(depth_list)
        self.camera, self.camera_source = resolve_tum_camera(cfg, self.root, rgb_list)

        tolerance = cfg.association_tolerance_s
        pairs = associate_timestamps(rgb_times, depth_times, tolerance)
        if not pairs:
            raise DatasetError(
                rgb_list, f"no colour image has a depth image within {tolerance} s in depth.txt; the sequence is empty "
                "(raise dataset.association_tolerance_s if the clocks are offset)"
            )
        if len(pairs) < len(rgb_times):
            logger.info("%s: %d of %d colour images have no depth partner within %g s and are skipped",
                        rgb_list, len(rgb_times) - len(pairs), len(rgb_times), tolerance)
        records = [
            FrameRecord(self.root / rgb_names[i], self.root / depth_names[j], float(rgb_times[i]), k,
                        float(depth_times[j] - rgb_times[i]))
            for k, (i, j) in enumerate(pairs)
        ]

        gt_path = self.root / "groundtruth.txt"
        gt_T_wc = gt_valid = None
        if gt_path.exists():
            gt_times, gt_poses = read_ground_truth(gt_path)
            frame_times = np.array([r.timestamp for r in records], dtype=np.float64)
            gt_T_wc, gt_valid = poses_at_times(gt_times, gt_poses, frame_times, tolerance)
            if not gt_valid.any():
                logger.warning("%s: no frame has a ground-truth pose within %g s; the sequence has no ground truth",
                               gt_path, tolerance)
                gt_T_wc = gt_valid = None
            elif not gt_valid.all():
                logger.info("%s: %d of %d frames have no ground-truth pose within %g s",
                            gt_path, int((~gt_valid).sum()), len(gt_valid), tolerance)
        else:
            logger.warning("%s: no groundtruth.txt; the sequence has no ground truth (evaluation will be unavailable)", self.root)

        expected = None
        if cfg.width is not None or cfg.height is not None:
            if cfg.width is None or cfg.height is None:
                raise DatasetError(self.root, "dataset.width and dataset.height must be given together (or neither)")
            expected = (cfg.width, cfg.height)
        self._setup(
            records=records, gt_T_wc=gt_T_wc, gt_valid=gt_valid, camera=self.camera,
            expected_size=expected, size_source="dataset.width/height",
            depth_scale=cfg.depth_scale if cfg.depth_scale is not None else TUM_DEPTH_SCALE,
            first_frame=cfg.first_frame, stride=cfg.stride, max_frames=cfg.max_frames, downscale=cfg.downscale,
            where=rgb_list, distortion=tuple(cfg.distortion or ()),
            depth_intrinsics=tuple(cfg.depth_intrinsics or ()), depth_extrinsics=tuple(cfg.depth_extrinsics or ()),
        )

    @classmethod
    def from_config(cls, cfg: DatasetConfig) -> "TUMSequence":
        return cls(cfg.path, cfg)
