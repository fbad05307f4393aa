"""SLAMState: everything that changes during a run. It is the checkpoint (docs/design.md "State").

Per processed frame a frozen :class:`FrameRecord`; the keyframes (id -> frame position), the
window, the map with its optimizer state, the run's random generator, the running tracking loss,
the Gaussian count over time, and the loop-closure state (pose graph and keyframe descriptors,
:class:`LoopState`, a record of this data layer that the loop-closure stage reads and returns) with its log of
candidates and optimisations.
:meth:`SLAMState.to_checkpoint` gives plain tensors plus JSON metadata (no pickled objects);
:meth:`SLAMState.from_checkpoint` is its inverse. Stage timings are outputs, not state
(:class:`~mipslam.observer.Observer`); the checkpoint carries them beside the state.
"""
from __future__ import annotations

import math
import operator
from array import array
from collections.abc import Iterable, MutableSequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch

from mipslam.checkpoint import capture_rng_state, restore_rng_state, select_prefix, with_prefix
from mipslam.errors import CheckpointError
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.geometry import interpolate_pose, se3_inverse
from mipslam.loop.descriptors import DescriptorOptions
from mipslam.loop.pose_graph import PoseGraph


class LearningRates(Protocol):
    """The map's Adam rates per parameter group (mapping's ``MappingOptions`` has them)."""

    lr_means: float
    lr_quats: float
    lr_scales: float
    lr_opacities: float
    lr_colors: float


STATE_VERSION = 2  # 2: loop-closure state (pose graph, descriptors, loop log)


@dataclass(frozen=True)
class FrameRecord:
    """What the run decided for one frame.

    T_wc [4, 4] float64 camera-to-world estimate; exposure [2] (log_gain, bias); status is the
    tracking status ("initial", "ok" or a failure reason); keyframe_id is -1 for non-keyframes;
    reference_keyframe is the keyframe the frame was tracked after. T_wc_tracked [4, 4] float64 is the
    pose as tracking left it, before mapping's refinement and loop corrections moved ``T_wc``: the
    motion model takes the frame-to-frame motion from it (:func:`~mipslam.tracking.constant_velocity_prediction`).
    """

    index: int
    timestamp: float
    T_wc: torch.Tensor
    exposure: torch.Tensor
    status: str
    tracking_loss: float
    tracking_iterations: int
    keyframe_id: int
    reference_keyframe: int
    T_wc_tracked: torch.Tensor

    @property
    def tracked(self) -> bool:
        return self.status in ("initial", "ok")


class FrameTable(MutableSequence):
    """The run's :class:`FrameRecord` s, one per processed frame, stored as columns: a list of records in
    memory that a long run can keep (a record as three tensors and a dataclass costs about 2.3 KB; a row here
    320 bytes).

    It reads as a list of records: ``table[i]`` (negative ``i`` too) builds the record of row ``i`` with its own
    copies of the tensors, ``table[a:b]`` a list of them, ``table[i] = record`` and :meth:`append` store one.
    Columns, grown by doubling: T_wc, T_wc_tracked [N, 4, 4] float64; exposure [N, 2] float32; index, keyframe_id,
    reference_keyframe, tracking_iterations [N] int64; timestamp, tracking_loss [N] float64; status an index into
    the table's list of distinct status strings.
    """

    _INT_COLUMNS = ("index", "keyframe_id", "reference_keyframe", "tracking_iterations")  # then the status code
    _STATUS_COLUMN = len(_INT_COLUMNS)
    _FLOAT_COLUMNS = ("timestamp", "tracking_loss")
    SCALAR_COLUMNS = _INT_COLUMNS + _FLOAT_COLUMNS
    # attribute -> (row shape, dtype) of each column tensor
    _LAYOUT = {"_T_wc": ((4, 4), torch.float64), "_T_wc_tracked": ((4, 4), torch.float64),
               "_exposure": ((2,), torch.float32), "_ints": ((len(_INT_COLUMNS) + 1,), torch.int64),
               "_floats": ((len(_FLOAT_COLUMNS),), torch.float64)}

    def __init__(self, records: Iterable[FrameRecord] = ()):
        self._size = 0
        self._capacity = 0
        self._statuses: list[str] = []
        self._status_codes: dict[str, int] = {}
        for name, (shape, dtype) in self._LAYOUT.items():
            setattr(self, name, torch.zeros((0, *shape), dtype=dtype))
        self._grow(16)
        for record in records:
            self.append(record)

    def _grow(self, capacity: int) -> None:
        for name, (shape, dtype) in self._LAYOUT.items():
            grown = torch.zeros((capacity, *shape), dtype=dtype)
            grown[: self._size] = getattr(self, name)[: self._size]
            setattr(self, name, grown)
        self._capacity = capacity

    def _position(self, position: int) -> int:
        position = operator.index(position)  # any integer (numpy's, a 0-d tensor's); TypeError for the rest
        if position < 0:
            position += self._size
        if not 0 <= position < self._size:
            raise IndexError(f"frame position {position} outside the {self._size} recorded frames")
        return position

    def _code(self, status: str) -> int:
        code = self._status_codes.get(status)
        if code is None:
            code = self._status_codes[status] = len(self._statuses)
            self._statuses.append(status)
        return code

    def _store(self, row: int, record: FrameRecord) -> None:
        self._T_wc[row] = record.T_wc.detach().to("cpu", torch.float64)
        self._T_wc_tracked[row] = record.T_wc_tracked.detach().to("cpu", torch.float64)
        self._exposure[row] = record.exposure.detach().to("cpu", torch.float32)
        self._ints[row] = torch.tensor([record.index, record.keyframe_id, record.reference_keyframe,
                                        record.tracking_iterations, self._code(record.status)], dtype=torch.int64)
        self._floats[row, 0], self._floats[row, 1] = float(record.timestamp), float(record.tracking_loss)

    def _record(self, row: int) -> FrameRecord:
        index, keyframe_id, reference, iterations, status = self._ints[row].tolist()
        timestamp, loss = self._floats[row].tolist()
        return FrameRecord(index, timestamp, self._T_wc[row].clone(), self._exposure[row].clone(),
                           self._statuses[status], loss, iterations, keyframe_id, reference,
                           self._T_wc_tracked[row].clone())

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, position):
        if isinstance(position, slice):
            return [self._record(row) for row in range(*position.indices(self._size))]
        return self._record(self._position(position))

    def __setitem__(self, position, record: FrameRecord) -> None:
        if isinstance(position, slice):
            raise TypeError("frame table: set records one position at a time")
        self._store(self._position(position), record)

    def __delitem__(self, position) -> None:
        raise TypeError("frame table: a recorded frame is never removed")

    def insert(self, position: int, record: FrameRecord) -> None:
        if position != self._size:
            raise TypeError("frame table: records are appended in frame order, never inserted")
        self.append(record)

    def append(self, record: FrameRecord) -> None:
        if self._size == self._capacity:
            self._grow(2 * self._capacity)
        self._store(self._size, record)
        self._size += 1

    def pose(self, position: int) -> torch.Tensor:
        """Row ``position``'s T_wc [4, 4] float64 (a copy), without building its record."""
        return self._T_wc[self._position(position)].clone()

    def set_pose(self, position: int, T_wc: torch.Tensor) -> None:
        """Row ``position`` takes the pose ``T_wc`` [4, 4] (stored float64)."""
        self._T_wc[self._position(position)] = T_wc.detach().to("cpu", torch.float64)

    def set_poses(self, T_wc: torch.Tensor) -> None:
        """Every row takes its pose from ``T_wc`` [N, 4, 4] (stored float64)."""
        if T_wc.shape != (self._size, 4, 4):
            raise ValueError(f"{tuple(T_wc.shape)} poses for {self._size} frames")
        self._T_wc[: self._size] = T_wc.detach().to("cpu", torch.float64)

    def poses_at(self, rows: torch.Tensor) -> torch.Tensor:
        """The T_wc of rows ``rows`` [M] int64 (positions in ``[0, len)``) -> [M, 4, 4] float64 (a copy)."""
        return self._T_wc[: self._size][rows]

    def set_poses_at(self, rows: torch.Tensor, T_wc: torch.Tensor) -> None:
        """Rows ``rows`` [M] int64 (positions in ``[0, len)``) take the poses ``T_wc`` [M, 4, 4] (stored float64)."""
        if T_wc.shape != (len(rows), 4, 4):
            raise ValueError(f"{tuple(T_wc.shape)} poses for {len(rows)} rows")
        self._T_wc[: self._size][rows] = T_wc.detach().to("cpu", torch.float64)

    def poses(self, *, as_tracked: bool = False) -> torch.Tensor:
        """Every row's T_wc (or T_wc_tracked) -> [N, 4, 4] float64 (a copy)."""
        return (self._T_wc_tracked if as_tracked else self._T_wc)[: self._size].clone()

    def column(self, name: str) -> torch.Tensor:
        """One of :attr:`SCALAR_COLUMNS` as a tensor [N] (a copy): int64 or float64."""
        if name in self._INT_COLUMNS:
            return self._ints[: self._size, self._INT_COLUMNS.index(name)].clone(memory_format=torch.contiguous_format)
        if name in self._FLOAT_COLUMNS:
            return self._floats[: self._size, self._FLOAT_COLUMNS.index(name)].clone(memory_format=torch.contiguous_format)
        raise KeyError(f"frame table has no column {name!r}; it has {', '.join(self.SCALAR_COLUMNS)}")

    def exposures(self) -> torch.Tensor:
        """[N, 2] float32 (a copy)."""
        return self._exposure[: self._size].clone()

    def nbytes(self) -> int:
        """Bytes the columns hold, spare capacity included."""
        return sum(getattr(self, name).numel() * getattr(self, name).element_size() for name in self._LAYOUT)

    def statuses(self) -> list[str]:
        return [self._statuses[c] for c in self._ints[: self._size, self._STATUS_COLUMN].tolist()]


@dataclass(frozen=True)
class LoopState:
    """The loop-closure part of the SLAM state (it goes into the checkpoint as plain tensors).

    graph: pose graph whose node k is keyframe k (poses are the estimates of the last update)
    descriptors: global descriptor of every keyframe, float32 CPU   # [K, D]
    recent_corrections: the corrections implied by the recent keyframes' verified loop edges, the evidence a
        later edge is confirmed by (``loop.confirm_keyframes``): rows (query keyframe, the world-frame correction
        ``C = T_i Z_ik T_k^-1`` of :func:`~mipslam.loop.closer.implied_corrections`, row-major 4x4), float64 CPU
        # [P, 17]
    """

    graph: PoseGraph
    descriptors: torch.Tensor
    recent_corrections: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 17, dtype=torch.float64))

    @staticmethod
    def empty(descriptor_options: DescriptorOptions = DescriptorOptions()) -> "LoopState":
        return LoopState(PoseGraph.empty(), torch.zeros(0, descriptor_options.dimension, dtype=torch.float32))

    @property
    def num_keyframes(self) -> int:
        return int(self.descriptors.shape[0])

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors only (``torch.load(..., weights_only=True)`` reads them)."""
        tensors = {f"graph.{k}": v for k, v in self.graph.state_dict().items()}
        tensors["descriptors"] = self.descriptors.detach().cpu().clone()
        tensors["recent_corrections"] = self.recent_corrections.detach().cpu().clone()
        return tensors

    @staticmethod
    def from_state_dict(tensors: dict[str, torch.Tensor]) -> "LoopState":
        """Inverse of :meth:`state_dict`; raises CheckpointError on a missing or inconsistent entry."""
        if "descriptors" not in tensors:
            raise CheckpointError("loop-closure state in checkpoint lacks 'descriptors'; start a new run")
        graph = PoseGraph.from_state_dict({k[len("graph."):]: v for k, v in tensors.items() if k.startswith("graph.")})
        descriptors = tensors["descriptors"].to(torch.float32).cpu()
        if descriptors.dim() != 2 or descriptors.shape[0] != graph.num_nodes:
            raise CheckpointError(f"loop-closure state in checkpoint is inconsistent: {graph.num_nodes} pose-graph nodes "
                                  f"but descriptors of shape {tuple(descriptors.shape)}; start a new run")
        # a checkpoint written before the confirmation existed has none: the next edges wait for new evidence
        recent = tensors.get("recent_corrections", torch.zeros(0, 17, dtype=torch.float64)).to(torch.float64).cpu()
        if recent.dim() != 2 or recent.shape[1] != 17:
            raise CheckpointError("loop-closure state in checkpoint has recent corrections of shape "
                                  f"{tuple(recent.shape)}, expected [P, 17]; start a new run")
        return LoopState(graph, descriptors, recent)


class TrackedPose(Protocol):
    """What the state records of a frame's tracking: :class:`mipslam.tracking.TrackingResult` is one (the state,
    the data layer, does not import the stage; docs/design.md "Import layers")."""

    T_wc: torch.Tensor  # [4, 4] float64
    exposure: torch.Tensor  # [2]
    loss: float
    iterations: int
    status: str
    depth_disagreement: float  # fraction of the mapped pixels whose rendered depth disagrees (NaN: not measured)


@dataclass
class SLAMState:
    gaussian_map: GaussianMap
    optimizer: GaussianOptimizer
    generator: torch.Generator
    frames: FrameTable = field(default_factory=FrameTable)  # a list of FrameRecord given here becomes a table
    keyframe_frames: list[int] = field(default_factory=list)  # keyframe id -> position in ``frames``
    window: list[int] = field(default_factory=list)  # keyframe ids, newest first
    running_loss: float | None = None
    running_disagreement: float | None = None  # the same average of tracked frames' depth disagreement
    gaussian_counts: array = field(default_factory=lambda: array("q"))  # per frame, as C int64 (8 bytes a frame)
    loop: LoopState = field(default_factory=LoopState.empty)
    loop_log: dict[str, list[dict[str, Any]]] = field(default_factory=lambda: {"candidates": [], "optimisations": []})

    @classmethod
    def initial(cls, mapping_options: LearningRates, seed: int, device: torch.device) -> "SLAMState":
        gmap = GaussianMap.empty(device=device)
        generator = torch.Generator(device="cpu")
        generator.manual_seed(seed)
        return cls(gmap, GaussianOptimizer.from_config(gmap, mapping_options), generator)

    def __post_init__(self):
        if not isinstance(self.frames, FrameTable):
            self.frames = FrameTable(self.frames)
        if not isinstance(self.gaussian_counts, array):
            self.gaussian_counts = array("q", self.gaussian_counts)

    # ------------------------------------------------------------------ queries

    @property
    def next_frame(self) -> int:
        return len(self.frames)

    def keyframe_record(self, keyframe_id: int) -> FrameRecord:
        return self.frames[self.keyframe_frames[keyframe_id]]

    def last_keyframe_id(self) -> int | None:
        return len(self.keyframe_frames) - 1 if self.keyframe_frames else None

    def newest_tracked_frame(self) -> FrameRecord | None:
        """The newest frame whose tracking succeeded (the reference of the next frame's start), or None."""
        return next((f for f in reversed(self.frames) if f.tracked), None)

    def poses(self, *, as_tracked: bool = False) -> torch.Tensor:
        """All estimated poses so far (``as_tracked``: as tracking left them, ``FrameRecord.T_wc_tracked``).
        -> [F, 4, 4] float64"""
        return self.frames.poses(as_tracked=as_tracked)

    # ------------------------------------------------------------------ updates

    def set_keyframe_pose(self, keyframe_id: int, T_wc: torch.Tensor) -> None:
        """Keyframe ``keyframe_id`` takes pose ``T_wc`` [4, 4] (camera-to-world; stored float64 on CPU)."""
        position = self.keyframe_frames[keyframe_id]
        self.frames.set_pose(position, T_wc)

    def keyframe_poses(self) -> torch.Tensor:
        """Current poses of all keyframes, by keyframe id.  -> [K, 4, 4] float64"""
        return self.frames.poses_at(torch.tensor(self.keyframe_frames, dtype=torch.int64))

    def set_poses(self, T_wc: torch.Tensor) -> None:
        """Every frame takes its pose from ``T_wc`` [F, 4, 4] (as :meth:`poses` returned it): undoes a correction
        exactly, where applying the inverse correction would blend the non-keyframes again."""
        if T_wc.shape != (len(self.frames), 4, 4):
            raise ValueError(f"{tuple(T_wc.shape)} poses for {len(self.frames)} frames")
        self.frames.set_poses(T_wc)

    def correct_keyframe_poses(self, T_wc_new: torch.Tensor, *, move_map: bool = True) -> int:
        """Apply a pose-graph correction: keyframes take their new poses, every other frame moves with the
        keyframes around it, and (``move_map``) every Gaussian moves with its anchor keyframe.

        T_wc_new: corrected poses of all keyframes   # [K, 4, 4]
        With ``C_k = T_new_k inv(T_old_k)``: a non-keyframe tracked after keyframe r, a fraction ``s`` of the
        frames from r to the next keyframe n, becomes ``interpolate_pose(C_r T_wc, C_n T_wc, s)``; after the
        newest keyframe (no n yet) it becomes ``C_r T_wc``. Moving a whole stretch by ``C_r`` alone would leave
        a step at n wherever the graph corrects neighbouring keyframes differently. Frames without a reference
        keyframe stay. :meth:`GaussianMap.transform_by_anchor` applies ``C`` to the map; without ``move_map`` (the
        map was fitted at the new poses already) it stays. Returns how many Gaussians moved.
        """
        T_old = self.keyframe_poses()
        if T_wc_new.shape != T_old.shape:
            raise ValueError(f"correction for {tuple(T_wc_new.shape)} keyframe poses, the state has {tuple(T_old.shape)}")
        T_new = T_wc_new.detach().to(dtype=torch.float64, device="cpu")
        changed = [not torch.equal(a, b) for a, b in zip(T_new, T_old)]
        corrections = T_new @ se3_inverse(T_old)  # [K, 4, 4]
        corrections[[not c for c in changed]] = torch.eye(4, dtype=torch.float64)  # exactly: those frames stay
        if not any(changed):  # no keyframes, or none moved: no frame moves
            return self.gaussian_map.transform_by_anchor(corrections) if move_map else 0
        changed_ids = torch.tensor(changed, dtype=torch.bool)
        positions = torch.tensor(self.keyframe_frames, dtype=torch.int64)  # keyframe id -> row
        self.frames.set_poses_at(positions[changed_ids], T_new[changed_ids])
        keyframe_ids = self.frames.column("keyframe_id")
        references = self.frames.column("reference_keyframe")
        # the other frames whose reference keyframe r, or the next one n, moved: [M] rows
        last = len(changed) - 1
        has_next = (references >= 0) & (references < last)
        next_moved = has_next & changed_ids[(references + 1).clamp(0, last)]
        moved = (keyframe_ids < 0) & (references >= 0) & (changed_ids[references.clamp(0, last)] | next_moved)
        rows = torch.nonzero(moved).flatten()
        if len(rows):
            r = references[rows]
            T_wc = self.frames.poses_at(rows)  # [M, 4, 4]
            T = corrections[r] @ T_wc
            between = has_next[rows]  # frames before the newest keyframe: interpolated towards n
            if bool(between.any()):
                rb, kb = r[between], rows[between]
                start, end = positions[rb], positions[rb + 1]
                weight = (kb - start).to(torch.float64) / (end - start).to(torch.float64)
                T[between] = interpolate_pose(T[between], corrections[rb + 1] @ T_wc[between], weight)
            self.frames.set_poses_at(rows, T)
        return self.gaussian_map.transform_by_anchor(corrections) if move_map else 0

    def append_frame(self, index: int, timestamp: float, tracked: TrackedPose, is_keyframe: bool) -> FrameRecord:
        """Record a tracked frame (sequence ``index``, ``timestamp`` in seconds); a keyframe takes the next
        keyframe id, every frame the last keyframe as its reference. Returns the record."""
        last = self.last_keyframe_id()
        record = FrameRecord(index, timestamp, tracked.T_wc, tracked.exposure, tracked.status, tracked.loss,
                             tracked.iterations, len(self.keyframe_frames) if is_keyframe else -1,
                             last if last is not None else -1, T_wc_tracked=tracked.T_wc)
        self.frames.append(record)
        return record

    def end_frame(self, tracked: TrackedPose, running_loss_momentum: float) -> FrameRecord:
        """After all stages: a well-tracked frame updates the running tracking loss (:func:`update_running_loss`),
        a tracked frame (well or flagged for its depth disagreement, so that the level follows a scene whose depth
        agrees less everywhere) the running depth disagreement, and the map's size is recorded. Returns the
        frame's record."""
        if tracked.status == "ok":
            self.running_loss = update_running_loss(self.running_loss, tracked.loss, running_loss_momentum)
        if tracked.status in ("ok", "depth_disagreement") and math.isfinite(tracked.depth_disagreement):
            self.running_disagreement = update_running_loss(self.running_disagreement, tracked.depth_disagreement,
                                                            running_loss_momentum)
        self.gaussian_counts.append(len(self.gaussian_map))
        return self.frames[-1]

    # ------------------------------------------------------------------ checkpoint

    def to_checkpoint(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Plain tensors and JSON metadata that :meth:`from_checkpoint` turns back into this state."""
        frames = self.frames
        tensors = {
            **{f"frames.{name}": frames.column(name) for name in FrameTable.SCALAR_COLUMNS},
            "frames.T_wc": self.poses(),
            "frames.T_wc_tracked": self.poses(as_tracked=True),
            "frames.exposure": frames.exposures(),
            "keyframe_frames": torch.tensor(self.keyframe_frames, dtype=torch.int64),
            "window": torch.tensor(self.window, dtype=torch.int64),
            **with_prefix("map", {k: v.detach().cpu() for k, v in self.gaussian_map.state_dict().items()}),
            **with_prefix("optim", {k: v.detach().cpu() for k, v in self.optimizer.state_dict().items()}),
            **with_prefix("loop", self.loop.state_dict()),
        }
        rng_tensors, rng_meta = capture_rng_state({"run": self.generator})
        tensors.update(rng_tensors)
        metadata = {
            "state_version": STATE_VERSION,
            "next_frame": self.next_frame,
            "statuses": frames.statuses(),
            "running_loss": self.running_loss,
            "running_disagreement": self.running_disagreement,
            "gaussian_counts": self.gaussian_counts.tolist(),
            "rng": rng_meta,
            "loop_log": self.loop_log,
        }
        return tensors, metadata

    @classmethod
    def from_checkpoint(cls, tensors: dict[str, torch.Tensor], metadata: dict[str, Any],
                        mapping_options: LearningRates, device: torch.device) -> "SLAMState":
        if metadata.get("state_version") != STATE_VERSION:
            raise CheckpointError(f"checkpoint holds SLAM state version {metadata.get('state_version')}, this mipslam "
                                  f"reads version {STATE_VERSION}; start a new run")
        gmap = GaussianMap.from_state_dict(select_prefix("map", tensors), device=device)
        optimizer = GaussianOptimizer.from_config(gmap, mapping_options)
        optimizer.load_state_dict({k: v.to(device) for k, v in select_prefix("optim", tensors).items()})
        generator = torch.Generator(device="cpu")
        restore_rng_state(tensors, metadata["rng"], {"run": generator})
        statuses = metadata["statuses"]
        # checkpoints written before the tracked poses were kept: the current poses stand in for them (the motion
        # model then differences them, as it did when those checkpoints were written)
        tracked = tensors.get("frames.T_wc_tracked", tensors["frames.T_wc"])
        frames = FrameTable(
            FrameRecord(
                index=int(tensors["frames.index"][i]),
                timestamp=float(tensors["frames.timestamp"][i]),
                T_wc=tensors["frames.T_wc"][i],
                exposure=tensors["frames.exposure"][i],
                status=statuses[i],
                tracking_loss=float(tensors["frames.tracking_loss"][i]),
                tracking_iterations=int(tensors["frames.tracking_iterations"][i]),
                keyframe_id=int(tensors["frames.keyframe_id"][i]),
                reference_keyframe=int(tensors["frames.reference_keyframe"][i]),
                T_wc_tracked=tracked[i],
            )
            for i in range(len(statuses))
        )
        running = metadata["running_loss"]
        disagreement = metadata.get("running_disagreement")  # absent from checkpoints of earlier versions
        return cls(
            gaussian_map=gmap, optimizer=optimizer, generator=generator, frames=frames,
            keyframe_frames=[int(v) for v in tensors["keyframe_frames"].tolist()],
            window=[int(v) for v in tensors["window"].tolist()],
            running_loss=None if running is None else float(running),
            running_disagreement=None if disagreement is None else float(disagreement),
            gaussian_counts=array("q", (int(v) for v in metadata["gaussian_counts"])),
            loop=LoopState.from_state_dict(select_prefix("loop", tensors)),
            loop_log={"candidates": list(metadata["loop_log"]["candidates"]),
                      "optimisations": list(metadata["loop_log"]["optimisations"])},
        )


def update_running_loss(previous: float | None, loss: float, momentum: float) -> float:
    """Exponential moving average of good tracking losses (the level a loss jump is measured against):
    ``momentum * previous + (1 - momentum) * loss`` (``TrackingOptions.running_loss_momentum``)."""
    if previous is None or not math.isfinite(previous):
        return loss
    return momentum * previous + (1 - momentum) * loss
