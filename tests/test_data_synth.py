"""data_synth: procedural RGB-D sequences with exact ground truth."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import data_synth
from data_synth import (TRAJECTORIES, default_intrinsics, generate, ground_truth_poses, load_scene, make_scene,
                        read_synth_json, render_view, trajectory_poses)
from data_synth.scene import ROOM_MAX, Room, Scene, SurfaceLayout
from data_synth.textures import Texture, evaluate_texture
from mipslam.errors import ConfigError, DatasetError, RenderError
from mipslam.geometry import quat_wxyz_to_rotmat, quat_xyzw_to_wxyz, unproject_depth

TINY = dict(width=96, height=72, frames=12)
SYNTH_KEYS = {"format_version", "generator", "layout", "trajectory", "seed", "frames", "intrinsics", "depth_scale",
              "fps", "scene", "sensor"}


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _read_depth(path: Path, scale: float) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16 and raw.ndim == 2, path
    return raw.astype(np.float64) / scale


def _read_color(path: Path) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint8 and raw.shape[2] == 3, path
    return raw[..., ::-1]


def _step_sizes(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation (m) and rotation angle (degrees)."""
    translation = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    relative = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return translation, np.degrees(np.arccos(cos))


def _back_project(depth: np.ndarray, intrinsics, T_wc: np.ndarray) -> np.ndarray:
    """Valid pixels to world points with the pinhole model of mipslam.geometry.  -> [N, 3]"""
    K = torch.tensor([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]],
                     dtype=torch.float64)
    points_c = unproject_depth(torch.from_numpy(np.asarray(depth, dtype=np.float64)), K).reshape(-1, 3).numpy()
    points_c = points_c[np.asarray(depth).reshape(-1) > 0]
    return points_c @ T_wc[:3, :3].T + T_wc[:3, 3]


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, Path]:
    """Tiny sequences shared by the tests: replica and tum, clean and with each sensor option."""
    root = tmp_path_factory.mktemp("synth")
    out = {
        "replica": generate(root / "replica", layout="replica", trajectory="loop", seed=3, **TINY),
        "tum": generate(root / "tum", layout="tum", trajectory="zoom", seed=3, **TINY),
    }
    small = dict(width=64, height=48, frames=4, seed=5)
    out["clean"] = generate(root / "clean", **small)
    out["noise"] = generate(root / "noise", depth_noise=0.01, **small)
    out["holes"] = generate(root / "holes", depth_holes=0.05, **small)
    out["exposure"] = generate(root / "exposure", exposure_jitter=0.1, **small)
    out["all"] = generate(root / "all", depth_noise=0.01, depth_holes=0.05, exposure_jitter=0.1, **small)
    return out


# ----------------------------------------------------------------------------- trajectories
def test_trajectory_names_and_argument_errors():
    assert TRAJECTORIES == ("loop", "zoom", "line", "static", "spin")
    with pytest.raises(ConfigError, match="did you mean 'zoom'"):
        trajectory_poses("zom", 10)
    with pytest.raises(ConfigError, match="laps"):
        trajectory_poses("line", 10, laps=2)
    with pytest.raises(ConfigError, match="frames"):
        trajectory_poses("loop", 0)
    with pytest.raises(ConfigError, match="at least 20 frames"):
        trajectory_poses("spin", 19)


@pytest.mark.parametrize("key,value", [("depth_baseline", 0.5), ("depth_focal_ratio", 3.0), ("depth_focal_ratio", 0.0)])
def test_an_unregistered_depth_camera_out_of_range_is_refused(tmp_path, key, value):
    with pytest.raises(ConfigError, match=key):
        data_synth.generate(tmp_path / "seq", width=16, height=12, frames=2, **{key: value})


@pytest.mark.parametrize("frames,laps", [(12, 1), (100, 1), (301, 1), (101, 2), (721, 3)])
def test_loop_returns_exactly_to_its_start(frames, laps):
    poses = trajectory_poses("loop", frames, laps=laps)
    assert poses.shape == (frames, 4, 4)
    assert np.array_equal(poses[0], poses[-1])
    lap = (frames - 1) // laps
    for k in range(1, laps):  # every lap ends at the start pose
        assert np.array_equal(poses[k * lap], poses[0])
    # ...and in between it really travels: half a lap away the camera is a diameter from the start.
    radius = np.linalg.norm(poses[0, :2, 3])
    assert np.linalg.norm(poses[lap // 2, :2, 3] - poses[0, :2, 3]) > 1.9 * radius * math.cos(math.pi / lap)


def test_loop_with_enough_frames_turns_all_the_way_round():
    poses = trajectory_poses("loop", 400)
    heading = np.degrees(np.arctan2(poses[:, 1, 2], poses[:, 0, 2]))  # viewing direction's azimuth
    covered = np.unique(np.floor((heading + 180) / 30).astype(int))
    assert len(covered) == 12  # every 30-degree sector of the room is looked at
    assert np.linalg.norm(poses[0, :2, 3]) == pytest.approx(1.0)


@pytest.mark.parametrize("name", TRAJECTORIES)
@pytest.mark.parametrize("frames", [12, 100, 500])
def test_trajectories_have_handheld_speeds_and_stay_clear_of_surfaces(name, frames):
    if name == "spin" and frames < 20:
        frames = 20  # the spin's shortest
    poses = trajectory_poses(name, frames)
    R = poses[:, :3, :3]
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-12
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert np.array_equal(poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (frames, 1)))
    translation, rotation = _step_sizes(poses)
    assert translation.max() <= 0.0301
    if name == "spin":  # 9 degrees a frame in its two spins, handheld speed on the way back between them
        spin = max(2, round(0.1 * frames))
        assert np.allclose(rotation[:spin], 9.0, atol=0.05) and np.allclose(rotation[-spin:], 9.0, atol=0.05)
        rotation = rotation[spin:-spin]
        assert rotation.max() <= (2.0 if frames >= 60 else 3.0)
    assert rotation.max() <= 2.0 or name == "spin"
    if name not in ("static", "spin"):  # the spin turns on the spot (a 5 cm circle)
        assert translation.mean() >= 0.003  # it does move
    for seed in (0, 1, 2, 3):
        clearance = make_scene(seed).clearance(poses[:, :3, 3])
        assert clearance.min() >= 0.3, (seed, clearance.min())


def test_zoom_changes_the_distance_to_the_wall_a_lot():
    for frames, ratio in ((100, 2.5), (400, 7.0)):
        poses = trajectory_poses("zoom", frames)
        distance = ROOM_MAX[0] - poses[:, 0, 3]
        assert np.allclose(poses[:, :3, 2], [1.0, 0.0, 0.0])  # always facing the +x wall
        assert distance.min() == pytest.approx(0.4, abs=1e-3)
        assert distance.max() / distance.min() >= ratio
        assert np.array_equal(poses[0], poses[-1])


# ----------------------------------------------------------------------------- rendering
@pytest.mark.parametrize("seed", [0, 1])
def test_depth_back_projects_onto_the_scene_surfaces(seed):
    scene = make_scene(seed)
    intrinsics = default_intrinsics(64, 48)
    poses = [trajectory_poses("loop", 301)[i] for i in (0, 75, 150, 225)] + [trajectory_poses("zoom", 50)[25]]
    for T_wc in poses:
        _, depth = render_view(scene, T_wc, intrinsics, supersample=1)
        assert depth.dtype == np.float32 and depth.shape == (48, 64)
        assert (depth > 0).all()  # a closed room: every pixel sees a surface
        distance = scene.surface_distance(_back_project(depth, intrinsics, T_wc))
        assert distance.max() < 1e-4


def _box_average_checker(s0, s1, t0, t1, period):
    """Exact fraction of parity-1 area of an axis-aligned checker over [s0, s1] x [t0, t1]."""
    def integral_of_square_wave(x):  # int_0^x of +1 on even cells, -1 on odd cells
        return period - np.abs(np.mod(x, 2 * period) - period)
    mean_s = (integral_of_square_wave(s1) - integral_of_square_wave(s0)) / (s1 - s0)
    mean_t = (integral_of_square_wave(t1) - integral_of_square_wave(t0)) / (t1 - t0)
    return 0.5 * (1 - mean_s * mean_t)


def test_color_is_the_pixel_footprint_average_of_the_texture():
    """A fronto-parallel wall with a checker of 0.7 pixel period: the exact box-filtered colour is
    known in closed form; supersampling converges to it, point sampling aliases."""
    distance, height = 1.3, 1.3
    intrinsics = default_intrinsics(40, 30, fov_deg=40.0)
    pixel_on_wall = distance / intrinsics.fx  # metres of wall per pixel
    period = 0.71 * pixel_on_wall
    checker = SurfaceLayout(Texture("checker", {"c0": [0.1, 0.2, 0.3], "c1": [0.9, 0.8, 0.6], "period": period,
                                                 "angle": 0.0}))
    room = Room((-2.0, -2.0, 0.0), (2.0, 2.0, 2.6), (checker,) * 6)
    scene = Scene(room, (), seed=0)
    T_wc = np.eye(4)
    T_wc[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # facing +x, level
    T_wc[:3, 3] = [2.0 - distance, 0.0, height]
    u = np.arange(40)[None, :]
    v = np.arange(30)[:, None]
    # Wall coordinates of the +x wall: s = y_max - y = 2 + x_cam * d, t = z = height - y_cam * d.
    s0, s1 = 2 + (u - 0.5 - intrinsics.cx) * pixel_on_wall, 2 + (u + 0.5 - intrinsics.cx) * pixel_on_wall
    t0, t1 = height - (v + 0.5 - intrinsics.cy) * pixel_on_wall, height - (v - 0.5 - intrinsics.cy) * pixel_on_wall
    fraction = _box_average_checker(s0, s1, t0, t1, period)
    shade = 0.75 + 0.25 * (-np.asarray(scene.light)[0] / np.linalg.norm(scene.light))
    c0, c1 = np.array([0.1, 0.2, 0.3]), np.array([0.9, 0.8, 0.6])
    exact = shade * (c0 + (c1 - c0) * fraction[..., None])
    errors = {}
    for S in (1, 4, 8):
        color, depth = render_view(scene, T_wc, intrinsics, supersample=S)
        assert np.allclose(depth, distance, atol=1e-6)
        errors[S] = np.abs(color - exact).mean()
    # Midpoint-rule error shrinks like 1/S (measured: 0.17, 0.013, 0.0066 for S = 1, 4, 8).
    assert errors[8] < 0.01
    assert errors[4] < 0.02
    assert errors[8] < 0.7 * errors[4]
    assert errors[1] > 8 * errors[4]


def test_supersampled_render_matches_a_2x_render_averaged_down():
    scene = make_scene(0)
    T_wc = trajectory_poses("static", 1)[0]  # facing the test chart of fine textures
    intrinsics = default_intrinsics(64, 48)
    color_1x, _ = render_view(scene, T_wc, intrinsics, supersample=4)
    color_2x, _ = render_view(scene, T_wc, intrinsics.scaled(2), supersample=4)
    averaged = color_2x.reshape(48, 2, 64, 2, 3).mean(axis=(1, 3))
    point, _ = render_view(scene, T_wc, intrinsics, supersample=1)
    diff_supersampled = np.abs(color_1x - averaged).mean()
    diff_point = np.abs(point - averaged).mean()
    assert diff_supersampled < 0.03
    assert diff_point > 3 * diff_supersampled


def test_render_view_argument_errors():
    scene = make_scene(0)
    T_wc = trajectory_poses("static", 1)[0]
    intrinsics = default_intrinsics(16, 12)
    with pytest.raises(RenderError, match="supersample"):
        render_view(scene, T_wc, intrinsics, supersample=0)
    bad = T_wc.copy()
    bad[:3, :3] *= 2
    with pytest.raises(RenderError, match="rotation"):
        render_view(scene, bad, intrinsics)
    with pytest.raises(RenderError, match="4x4"):
        render_view(scene, T_wc[:3], intrinsics)
    color, depth = render_view(scene, torch.from_numpy(T_wc), intrinsics)  # torch poses work too
    assert color.shape == (12, 16, 3) and color.dtype == np.float32 and 0 <= color.min() and color.max() <= 1


def test_textures_are_analytic_functions_of_surface_coordinates():
    rng = np.random.default_rng(0)
    s, t = rng.uniform(0, 2, 20000), rng.uniform(0, 2, 20000)
    stripes = Texture("stripes", {"c0": [0, 0, 0], "c1": [1, 1, 1], "period": 0.01, "duty": 0.6, "angle": 90.0})
    rgb = evaluate_texture(stripes, s, t)
    assert np.mean(rgb[:, 0] > 0) == pytest.approx(0.6, abs=0.02)  # duty cycle
    assert np.array_equal(rgb, evaluate_texture(stripes, s + 0.37, t))  # horizontal slats: s-invariant
    text = Texture("print", {"paper": [1, 1, 1], "ink": [0, 0, 0], "cell_w": 0.004, "cell_h": 0.006,
                             "line_spacing": 1.5, "line_chars": 40, "key": 7})
    ink = evaluate_texture(text, s, t)[:, 0] == 0
    assert 0.1 < ink.mean() < 0.5
    assert np.array_equal(ink, evaluate_texture(text, s, t)[:, 0] == 0)
    other_key = Texture("print", dict(text.params, key=8))
    assert (ink != (evaluate_texture(other_key, s, t)[:, 0] == 0)).mean() > 0.1


# ----------------------------------------------------------------------------- generated folders
def test_replica_layout_follows_the_contract(folders):
    root = folders["replica"]
    info = read_synth_json(root)
    assert SYNTH_KEYS <= set(info)
    assert (info["format_version"], info["generator"], info["layout"], info["trajectory"]) == (1, "data_synth", "replica", "loop")
    assert (info["seed"], info["frames"], info["fps"], info["depth_scale"]) == (3, 12, 30.0, 6553.5)
    k = info["intrinsics"]
    assert (k["width"], k["height"], k["cx"], k["cy"]) == (96, 72, 47.5, 35.5)
    camera = json.loads((root / "cam_params.json").read_text())["camera"]
    assert camera == {"w": 96, "h": 72, "fx": k["fx"], "fy": k["fy"], "cx": 47.5, "cy": 35.5, "scale": 6553.5}
    traj = np.loadtxt(root / "traj.txt")
    assert traj.shape == (12, 16)
    poses = trajectory_poses("loop", 12)
    assert np.allclose(traj.reshape(12, 4, 4), poses, atol=1e-15, rtol=1e-15)
    assert np.array_equal(ground_truth_poses(root), poses)
    scene = load_scene(root)
    for i in (0, 5, 11):
        color = _read_color(root / "results" / f"frame{i:06d}.png")
        assert color.shape == (72, 96, 3)
        depth = _read_depth(root / "results" / f"depth{i:06d}.png", 6553.5)
        assert depth.shape == (72, 96) and (depth > 0).all()
        # 16-bit quantisation moves a point by at most half a step along its ray.
        ray_factor = math.hypot(1, math.hypot(47.5, 35.5) / k["fx"])
        distance = scene.surface_distance(_back_project(depth, data_synth.synth_intrinsics(root), traj[i].reshape(4, 4)))
        assert distance.max() <= 0.5 / 6553.5 * ray_factor + 1e-6
    assert sorted(p.name for p in (root / "results").iterdir()) == sorted(
        [f"frame{i:06d}.png" for i in range(12)] + [f"depth{i:06d}.png" for i in range(12)])


def _tum_list(path: Path) -> list[list[str]]:
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#")
    return [line.split() for line in lines if line and not line.startswith("#")]


def test_tum_layout_follows_the_contract(folders):
    root = folders["tum"]
    info = read_synth_json(root)
    assert SYNTH_KEYS <= set(info)
    assert (info["layout"], info["trajectory"], info["depth_scale"]) == ("tum", "zoom", 5000.0)
    rgb, depth_list, gt = _tum_list(root / "rgb.txt"), _tum_list(root / "depth.txt"), _tum_list(root / "groundtruth.txt")
    stamps = [f"{1000.0 + i / 30:.6f}" for i in range(12)]
    assert [r[0] for r in rgb] == [d[0] for d in depth_list] == [g[0] for g in gt] == stamps
    assert [r[1] for r in rgb] == [f"rgb/{s}.png" for s in stamps]
    assert [d[1] for d in depth_list] == [f"depth/{s}.png" for s in stamps]
    values = np.array([[float(v) for v in g[1:]] for g in gt])
    assert values.shape == (12, 7)
    poses = trajectory_poses("zoom", 12)
    assert np.allclose(values[:, :3], poses[:, :3, 3], atol=1e-9)
    R = quat_wxyz_to_rotmat(quat_xyzw_to_wxyz(torch.from_numpy(values[:, 3:]))).numpy()
    assert np.allclose(R, poses[:, :3, :3], atol=1e-8)
    scene = load_scene(root / "synth.json")
    intrinsics = data_synth.synth_intrinsics(root)
    for i in (0, 6):
        assert _read_color(root / rgb[i][1]).shape == (72, 96, 3)
        depth = _read_depth(root / depth_list[i][1], 5000.0)
        distance = scene.surface_distance(_back_project(depth, intrinsics, poses[i]))
        assert distance.max() <= 0.5 / 5000.0 * 1.5 + 1e-6


def test_generation_is_deterministic_and_the_seed_changes_the_scene(folders, tmp_path):
    again = generate(tmp_path / "again", layout="replica", trajectory="loop", seed=3, **TINY)
    assert _files(again) == _files(folders["replica"])
    noisy_again = generate(tmp_path / "all", width=64, height=48, frames=4, seed=5, depth_noise=0.01,
                           depth_holes=0.05, exposure_jitter=0.1)
    assert _files(noisy_again) == _files(folders["all"])
    assert make_scene(3).to_dict() != make_scene(4).to_dict()
    assert make_scene(3).to_dict() == make_scene(3).to_dict()
    other = generate(tmp_path / "other", layout="replica", trajectory="loop", seed=4, width=96, height=72, frames=2)
    first = _read_color(other / "results" / "frame000000.png").astype(int)
    assert np.abs(first - _read_color(folders["replica"] / "results" / "frame000000.png")).mean() > 5


def test_load_scene_rebuilds_the_scene_exactly(folders):
    root = folders["replica"]
    T_wc = ground_truth_poses(root)[4]
    intrinsics = default_intrinsics(48, 36)
    from_file = render_view(load_scene(root), T_wc, intrinsics)
    direct = render_view(make_scene(3), T_wc, intrinsics)
    assert np.array_equal(from_file[0], direct[0]) and np.array_equal(from_file[1], direct[1])
    written = _read_color(root / "results" / "frame000004.png")
    rendered, _ = render_view(load_scene(root), T_wc, data_synth.synth_intrinsics(root))
    assert np.array_equal(written, np.round(rendered * 255).astype(np.uint8))


def test_sensor_options_change_only_what_they_say(folders):
    clean, noise, holes, exposure = (_files(folders[k]) for k in ("clean", "noise", "holes", "exposure"))
    colors = [k for k in clean if "/frame" in k]
    depths = [k for k in clean if "/depth" in k]
    assert len(colors) == len(depths) == 4
    for other in (noise, holes, exposure):
        assert other["traj.txt"] == clean["traj.txt"] and other["cam_params.json"] == clean["cam_params.json"]
    assert all(noise[k] == clean[k] for k in colors) and all(noise[k] != clean[k] for k in depths)
    assert all(holes[k] == clean[k] for k in colors) and all(holes[k] != clean[k] for k in depths)
    assert all(exposure[k] == clean[k] for k in depths) and all(exposure[k] != clean[k] for k in colors)

    z = np.stack([_read_depth(folders["clean"] / k, 6553.5) for k in depths])
    z_noise = np.stack([_read_depth(folders["noise"] / k, 6553.5) for k in depths])
    z_holes = np.stack([_read_depth(folders["holes"] / k, 6553.5) for k in depths])
    normalised = (z_noise - z)[z_noise > 0] / z[z_noise > 0] ** 2
    assert normalised.std() == pytest.approx(0.01, rel=0.1)  # sigma * z^2
    assert abs(normalised.mean()) < 0.001
    dropped = z_holes == 0
    assert 0.04 <= dropped.mean() < 0.2  # random dropouts plus edges
    assert np.array_equal(z_holes[~dropped], z[~dropped])  # holes only remove, never move

    sensor = read_synth_json(folders["exposure"])["sensor"]
    assert sensor["exposure_jitter"] == 0.1 and len(sensor["exposure"]) == 4
    assert read_synth_json(folders["clean"])["sensor"]["exposure"] == []
    gain, bias = sensor["exposure"][1]
    assert gain != 1.0
    c = _read_color(folders["clean"] / colors[1]).astype(float)
    c_exp = _read_color(folders["exposure"] / colors[1]).astype(float)
    assert np.abs(c_exp - np.clip(gain * c + 255 * bias, 0, 255)).max() <= 2.0
    # All options together: each one's part is what it was alone.
    everything = _files(folders["all"])
    assert all(everything[k] == exposure[k] for k in colors)
    z_all = np.stack([_read_depth(folders["all"] / k, 6553.5) for k in depths])
    assert np.array_equal(z_all == 0, (z_holes == 0) | (z_noise == 0))
    assert np.array_equal(z_all[z_all > 0], z_noise[z_all > 0])


def test_generate_rejects_bad_arguments_and_existing_folders(folders, tmp_path):
    with pytest.raises(ConfigError, match="did you mean 'replica'"):
        generate(tmp_path / "a", layout="replika", **TINY)
    with pytest.raises(ConfigError, match="trajectory"):
        generate(tmp_path / "a", trajectory="circle", **TINY)
    with pytest.raises(ConfigError, match="width"):
        generate(tmp_path / "a", width=0, height=10, frames=2)
    with pytest.raises(ConfigError, match="depth_holes"):
        generate(tmp_path / "a", depth_holes=1.0, **TINY)
    with pytest.raises(ConfigError, match="supersample"):
        generate(tmp_path / "a", supersample=0, **TINY)
    with pytest.raises(ConfigError, match="laps"):
        generate(tmp_path / "a", trajectory="zoom", laps=2, **TINY)
    assert not (tmp_path / "a").exists()  # nothing written on bad arguments
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        generate(busy, width=16, height=12, frames=2)
    with pytest.raises(ConfigError, match="not empty"):
        generate(busy, width=16, height=12, frames=2, overwrite=True)  # not a data_synth folder
    redo = generate(tmp_path / "redo", width=16, height=12, frames=3)
    generate(redo, width=16, height=12, frames=2, overwrite=True)
    assert len(list((redo / "results").iterdir())) == 4 and read_synth_json(redo)["frames"] == 2


def test_reading_a_broken_folder_names_the_file(tmp_path):
    with pytest.raises(DatasetError, match="synth.json"):
        load_scene(tmp_path)
    bad = tmp_path / "synth.json"
    bad.write_text('{"format_version": 1,\n "generator": ')
    with pytest.raises(DatasetError, match=r"synth.json:2"):
        read_synth_json(tmp_path)
    bad.write_text(json.dumps({"format_version": 2}))
    with pytest.raises(DatasetError, match="lacks"):
        read_synth_json(bad)
