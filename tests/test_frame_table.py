"""FrameTable: the run's per-frame records stored as columns, read and written as a list of FrameRecord."""
from __future__ import annotations

import math

import pytest
import torch

from mipslam.checkpoint import read_checkpoint, save_checkpoint
from mipslam.gaussians import GaussianMap, GaussianOptimizer
from mipslam.geometry import se3_exp
from mipslam.mapping import MappingOptions
from mipslam.state import FrameRecord, FrameTable, SLAMState


def _record(k: int, status: str = "ok", keyframe_id: int = -1, reference: int = 0) -> FrameRecord:
    T = se3_exp(torch.tensor([0.01 * k, -0.02, 0.003 * k, 0.001 * k, 0.02, -0.01], dtype=torch.float64))
    return FrameRecord(k, 0.1 * k + 1e9, T, torch.tensor([0.01 * k, -0.5]), status, 1.0 / (k + 1), k % 7,
                       keyframe_id, reference, T @ se3_exp(torch.full((6,), 1e-3, dtype=torch.float64)))


def _assert_same(a: FrameRecord, b: FrameRecord) -> None:
    assert (a.index, a.timestamp, a.status, a.tracking_loss, a.tracking_iterations, a.keyframe_id,
            a.reference_keyframe) == (b.index, b.timestamp, b.status, b.tracking_loss, b.tracking_iterations,
                                      b.keyframe_id, b.reference_keyframe)
    assert torch.equal(a.T_wc, b.T_wc) and torch.equal(a.T_wc_tracked, b.T_wc_tracked)
    assert torch.equal(a.exposure, b.exposure)
    assert a.T_wc.dtype == torch.float64 and a.exposure.dtype == torch.float32


def test_records_read_back_exactly_past_every_growth():
    records = [_record(k, status=("ok", "initial", "loss_jump")[k % 3], keyframe_id=k if k % 10 == 0 else -1)
               for k in range(100)]  # past the first capacities (16, 32, 64)
    table = FrameTable()
    assert not table and len(table) == 0
    for record in records:
        table.append(record)
    assert len(table) == 100 and table
    for k in (0, 15, 16, 17, 63, 64, 99):
        _assert_same(table[k], records[k])
    _assert_same(table[-1], records[99])
    _assert_same(table[-100], records[0])
    for a, b in zip(table, records, strict=True):
        _assert_same(a, b)
    for a, b in zip(reversed(table), reversed(records), strict=True):
        _assert_same(a, b)
    tail = table[-2:]
    assert isinstance(tail, list) and [r.index for r in tail] == [98, 99]
    assert [r.index for r in table[10:40:10]] == [10, 20, 30]
    assert table.statuses() == [r.status for r in records]
    assert table.column("keyframe_id").tolist() == [r.keyframe_id for r in records]
    assert table.column("timestamp").tolist() == [r.timestamp for r in records]
    assert torch.equal(table.poses(), torch.stack([r.T_wc for r in records]))
    assert torch.equal(table.poses(as_tracked=True), torch.stack([r.T_wc_tracked for r in records]))


def test_a_read_record_is_a_copy_and_writes_go_through_the_table():
    table = FrameTable([_record(0), _record(1)])
    record = table[1]
    record.T_wc.zero_()
    record.exposure.fill_(7.0)
    _assert_same(table[1], _record(1))
    moved = _record(5)
    table[1] = moved
    _assert_same(table[1], moved)
    table.set_pose(0, torch.eye(4))
    assert torch.equal(table.pose(0), torch.eye(4, dtype=torch.float64))
    assert torch.equal(table[0].T_wc_tracked, _record(0).T_wc_tracked)  # the tracked pose stays
    poses = torch.stack([torch.eye(4, dtype=torch.float64)] * 2) * 2.0
    table.set_poses(poses)
    assert torch.equal(table.poses(), poses)


def test_out_of_range_and_unsupported_edits_are_errors():
    table = FrameTable([_record(0)])
    with pytest.raises(IndexError, match="outside the 1 recorded"):
        table[1]
    with pytest.raises(IndexError):
        table[-2]
    with pytest.raises(TypeError, match="never removed"):
        del table[0]
    with pytest.raises(TypeError, match="never inserted"):
        table.insert(0, _record(1))
    with pytest.raises(ValueError, match="poses for 1 frames"):
        table.set_poses(torch.zeros(2, 4, 4))
    with pytest.raises(KeyError, match="tracking_loss"):
        table.column("loss")


def test_a_row_costs_a_few_hundred_bytes():
    table = FrameTable(_record(k) for k in range(5000))
    per_row = table.nbytes() / len(table)
    assert per_row < 2 * 400  # 320 bytes a row, doubled at most by the growth's spare capacity


@pytest.mark.parametrize("frames", [1, 40])
def test_the_state_keeps_its_records_in_a_table_through_a_checkpoint_file(tmp_path, frames):
    gmap = GaussianMap.empty()
    options = MappingOptions()
    records = [_record(k, keyframe_id=0 if k == 0 else -1, reference=-1 if k == 0 else 0) for k in range(frames)]
    state = SLAMState(gmap, GaussianOptimizer.from_config(gmap, options), torch.Generator(), frames=list(records),
                      keyframe_frames=[0], window=[0], gaussian_counts=list(range(frames)))
    assert isinstance(state.frames, FrameTable)
    tensors, metadata = state.to_checkpoint()
    path = save_checkpoint(tmp_path, tensors, metadata, config={})
    checkpoint = read_checkpoint(path)
    restored = SLAMState.from_checkpoint(checkpoint.tensors, checkpoint.metadata, options, torch.device("cpu"))
    assert isinstance(restored.frames, FrameTable) and len(restored.frames) == frames
    assert list(restored.gaussian_counts) == list(range(frames))
    for a, b in zip(restored.frames, records, strict=True):
        _assert_same(a, b)
    assert math.isclose(restored.frames[-1].tracking_loss, 1.0 / frames)
