"""Rolling-shutter colour images moved to the frame's instant (mipslam.geometry.rolling_shutter, sensor_sync)."""
from __future__ import annotations

import math

import numpy as np
import torch

from data_synth import default_intrinsics, make_scene, render_view, trajectory_poses
from mipslam.geometry.rolling_shutter import colour_at_frame_instant, row_times
from mipslam.geometry.se3 import se3_exp
from mipslam.types import Intrinsics


def _K(intrinsics) -> torch.Tensor:
    return torch.tensor([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]],
                        dtype=torch.float64)


def _rolling_shutter_render(scene, T_wc: np.ndarray, intrinsics, velocity: torch.Tensor, readout_s: float) -> np.ndarray:
    """Each row rendered on its own at its read-out instant, the camera moving at ``velocity`` [v (m/s), omega
    (rad/s)] (camera frame): an independent forward model of the shutter the correction undoes."""
    H, W = intrinsics.height, intrinsics.width
    color = np.zeros((H, W, 3), dtype=np.float32)
    for v, dt in enumerate(row_times(H, readout_s).tolist()):
        T = T_wc @ se3_exp(velocity * dt).numpy()
        row = Intrinsics(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy - v, W, 1)
        color[v] = render_view(scene, T, row, supersample=2)[0][0]
    return color


def test_row_times_are_centred_on_the_middle_row():
    times = row_times(4, 0.04)
    torch.testing.assert_close(times, torch.tensor([-0.015, -0.005, 0.005, 0.015], dtype=torch.float64))


def _blurred(color: torch.Tensor, sigma: float = 1.5) -> torch.Tensor:
    """Gaussian blur of [H, W, 3]: compares where the content sits, not the bilinear reads of a texture finer
    than a pixel (which no resampling recovers: a global rotation warped back leaves 0.4 of its error)."""
    taps = torch.arange(-4, 5, dtype=torch.float32)
    kernel = torch.exp(-taps**2 / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    x = color.permute(2, 0, 1)[:, None]
    x = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (4, 4, 0, 0), mode="replicate"), kernel.view(1, 1, 1, 9))
    x = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (0, 0, 4, 4), mode="replicate"), kernel.view(1, 1, 9, 1))
    return x[:, 0].permute(1, 2, 0)


def test_a_rolling_shutter_image_is_moved_to_the_global_shutter_image():
    scene, intrinsics = make_scene(0), default_intrinsics(96, 72)
    T_wc = trajectory_poses("loop", 300)[40]
    readout = 0.04
    global_shutter, depth = (torch.from_numpy(a) for a in render_view(scene, T_wc, intrinsics, supersample=2))
    K = _K(intrinsics)

    def error(image):  # away from the border, which repeats where a ray left the image
        return float((_blurred(image) - _blurred(global_shutter))[6:-6, 6:-6].abs().mean())

    # turning: about 7 deg over the read-out
    turning = torch.tensor([0.0, 0.0, 0.0, 1.5, -2.5, 1.0], dtype=torch.float64)
    rolling = torch.from_numpy(_rolling_shutter_render(scene, T_wc, intrinsics, turning, readout))
    moved = colour_at_frame_instant(rolling, K, turning, readout)
    assert moved.shape == rolling.shape and moved.dtype == rolling.dtype and torch.isfinite(moved).all()
    assert error(moved) < 0.6 * error(rolling), (error(rolling), error(moved))
    assert error(colour_at_frame_instant(rolling, K, -turning, readout)) > error(rolling)  # the rows' sign
    torch.testing.assert_close(colour_at_frame_instant(rolling, K, turning, readout, depth), moved, atol=1e-5, rtol=0)
    # travelling at 1.5 m/s while turning to keep the view: the two motions' shifts partly cancel, so the
    # rotation alone over-corrects, and the depth puts the translation back
    travelling = torch.tensor([1.5, 0.0, 0.0, 0.0, 0.6, 0.0], dtype=torch.float64)
    rolling = torch.from_numpy(_rolling_shutter_render(scene, T_wc, intrinsics, travelling, readout))
    with_depth = error(colour_at_frame_instant(rolling, K, travelling, readout, depth))
    rotation_only = error(colour_at_frame_instant(rolling, K, travelling, readout))
    assert with_depth < 0.65 * error(rolling) and with_depth < 0.8 * rotation_only, (error(rolling), with_depth, rotation_only)


def test_no_read_out_or_no_rotation_keeps_the_image():
    color = torch.rand(12, 16, 3)
    K = torch.tensor([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]], dtype=torch.float64)
    assert colour_at_frame_instant(color, K, torch.tensor([0.1, 0.0, 0.0, 1.0, 0.0, 0.0]), 0.0) is color
    assert colour_at_frame_instant(color, K, torch.zeros(6), 0.03) is color
    assert colour_at_frame_instant(color, K, torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.03) is color  # no depth
    moved_by_depth = colour_at_frame_instant(color, K, torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.03,
                                             torch.full((12, 16), 1.0))
    assert not torch.equal(moved_by_depth, color) and torch.isfinite(moved_by_depth).all()


def test_the_run_moves_colour_rows_with_its_tracked_rotation():
    from mipslam.geometry.se3 import se3_exp
    from mipslam.sensor_sync import SensorTiming, synchronised, tracked_velocity
    from mipslam.state import FrameRecord
    from mipslam.types import Frame

    step = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(2.0), 0.0], dtype=torch.float64))
    T0 = torch.eye(4, dtype=torch.float64)
    previous = FrameRecord(0, 0.0, T0, torch.zeros(2), "ok", 0.0, 0, -1, -1, T_wc_tracked=T0)
    color = torch.rand(12, 16, 3)
    frame = Frame(1, 1 / 30, color, torch.full((12, 16), 2.0), Intrinsics(20.0, 20.0, 7.5, 5.5, 16, 12))
    velocity = tracked_velocity(previous, frame, step, True)
    torch.testing.assert_close(velocity[4], torch.tensor(math.radians(2.0) * 30, dtype=torch.float64))
    moved = synchronised(frame, velocity, SensorTiming(readout_s=0.03))
    expected = colour_at_frame_instant(color, frame.intrinsics.matrix(torch.float64), velocity, 0.03, frame.depth)
    assert torch.equal(moved.color, expected) and not torch.equal(moved.color, color)
    assert moved.depth is frame.depth  # no depth offset to undo
    assert synchronised(frame, velocity, SensorTiming()) is frame  # a global shutter


def test_tracking_refines_on_the_frame_re_timed_by_the_motion_to_its_start():
    """The motion model repeats the last interval's motion; the refinement's frame is re-timed with the motion
    from the previous frame to the chosen start, the frame's own."""
    from types import SimpleNamespace

    from mipslam.geometry.se3 import se3_exp
    from mipslam.pipeline import frame_at_start
    from mipslam.sensor_sync import SensorTiming, synchronised, tracked_velocity
    from mipslam.state import FrameRecord
    from mipslam.types import Frame

    T0 = torch.eye(4, dtype=torch.float64)
    previous = FrameRecord(0, 0.0, T0, torch.zeros(2), "ok", 0.0, 0, -1, -1, T_wc_tracked=T0)
    frame = Frame(1, 1 / 30, torch.rand(12, 16, 3), torch.full((12, 16), 2.0), Intrinsics(20.0, 20.0, 7.5, 5.5, 16, 12))
    state = SimpleNamespace(frames=[previous])
    start = se3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, math.radians(2.0), 0.0], dtype=torch.float64))
    timing = SensorTiming(readout_s=0.03)
    at_start = frame_at_start(SimpleNamespace(timing=timing), state, frame)
    expected = synchronised(frame, tracked_velocity(previous, frame, start, True), timing)
    assert torch.equal(at_start(start).color, expected.color)
    assert frame_at_start(SimpleNamespace(timing=SensorTiming()), state, frame) is None  # nothing to re-time


def test_the_source_field_computed_on_a_coarser_grid_moves_the_image_as_the_full_one(monkeypatch):
    import mipslam.geometry.rolling_shutter as rolling_shutter

    scene, intrinsics = make_scene(0), default_intrinsics(160, 120)
    color, depth = (torch.from_numpy(a) for a in render_view(scene, trajectory_poses("loop", 300)[40], intrinsics,
                                                              supersample=1))
    velocity = torch.tensor([0.5, -0.2, 0.3, 1.5, -2.5, 1.0], dtype=torch.float64)
    monkeypatch.setattr(rolling_shutter, "FIELD_MAX_PIXELS", 160 * 120 // 4)  # every 2nd pixel
    coarse = colour_at_frame_instant(color, _K(intrinsics), velocity, 0.03, depth)
    monkeypatch.setattr(rolling_shutter, "FIELD_MAX_PIXELS", 160 * 120)
    full = colour_at_frame_instant(color, _K(intrinsics), velocity, 0.03, depth)
    # the field is smooth but for the translation's part at depth edges: a few pixels differ there
    difference = (coarse - full).abs()
    assert float(difference.mean()) < 0.1 * float((full - color).abs().mean())
