"""3DGS PLY: exact round trip, the reference header layout, map conversion and header validation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mipslam.errors import DatasetError
from mipslam.gaussians import GaussianMap, GaussianParameters
from mipslam.io.ply import (
    PLY_PROPERTIES,
    SH_C0,
    SplatPly,
    f_dc_to_rgb,
    read_map_ply,
    read_ply,
    rgb_to_f_dc,
    splats_from_map,
    write_map_ply,
    write_ply,
)

# The vertex layout the 3DGS reference code writes for SH degree 0 (Kerbl et al., 2023).
REFERENCE_HEADER_PROPERTIES = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
]


def random_splats(n: int, seed: int = 0) -> SplatPly:
    g = torch.Generator().manual_seed(seed)
    return SplatPly(
        means=torch.randn(n, 3, generator=g) * 3,
        f_dc=torch.randn(n, 3, generator=g),
        opacity_logits=torch.randn(n, generator=g) * 4,
        log_scales=torch.randn(n, 3, generator=g) - 4,
        quats_wxyz=torch.randn(n, 4, generator=g),
        normals=torch.zeros(n, 3),
    )


def header_lines(path) -> list[str]:
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode("ascii").splitlines()


def test_write_read_round_trip_is_exact(tmp_path):
    splats = random_splats(257)
    path = write_ply(tmp_path / "map.ply", splats)
    back = read_ply(path)
    for name in ("means", "f_dc", "opacity_logits", "log_scales", "quats_wxyz", "normals"):
        assert torch.equal(getattr(back, name), getattr(splats, name)), name
        assert getattr(back, name).dtype == torch.float32


def test_header_matches_the_3dgs_layout(tmp_path):
    path = write_ply(tmp_path / "map.ply", random_splats(10))
    lines = [line for line in header_lines(path) if not line.startswith("comment")]
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 10"]
    assert lines[3:-1] == [f"property float {name}" for name in REFERENCE_HEADER_PROPERTIES]
    assert lines[-1] == "end_header"
    assert list(PLY_PROPERTIES) == REFERENCE_HEADER_PROPERTIES
    header_size = len("\n".join(header_lines(path)) + "\n")
    assert path.stat().st_size == header_size + 10 * 17 * 4
    # the data is plain little-endian float32 rows in that order
    table = np.frombuffer(path.read_bytes()[header_size:], dtype="<f4").reshape(10, 17)
    splats = random_splats(10)
    assert np.array_equal(table[:, 13:17], splats.quats_wxyz.numpy())
    assert np.array_equal(table[:, 9], splats.opacity_logits.numpy())


def test_empty_map_round_trip(tmp_path):
    back = read_ply(write_ply(tmp_path / "empty.ply", random_splats(0)))
    assert len(back) == 0 and back.means.shape == (0, 3) and back.opacity_logits.shape == (0,)


def test_sh_dc_convention():
    rgb = torch.tensor([[0.0, 0.5, 1.0]])
    torch.testing.assert_close(rgb_to_f_dc(rgb), torch.tensor([[-0.5 / SH_C0, 0.0, 0.5 / SH_C0]]))
    torch.testing.assert_close(f_dc_to_rgb(rgb_to_f_dc(rgb)), rgb)


def test_map_round_trip_through_ply(tmp_path):
    g = torch.Generator().manual_seed(3)
    n = 40
    params = GaussianParameters(
        means=torch.randn(n, 3, generator=g), quats_wxyz=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3, opacity_logits=torch.randn(n, generator=g),
        colors_raw=torch.randn(n, 3, generator=g), anchor_keyframe=torch.arange(n), created_frame=torch.arange(n),
    )
    gmap = GaussianMap(params)
    back = read_map_ply(write_map_ply(tmp_path / "map.ply", gmap))
    for name in ("means", "quats_wxyz", "log_scales", "opacity_logits"):
        assert torch.equal(getattr(back, name).detach(), getattr(gmap, name).detach()), name
    torch.testing.assert_close(back.activated().colors, gmap.activated().colors, rtol=0, atol=2e-6)
    assert (back.anchor_keyframe == -1).all() and (back.created_frame == -1).all()


def test_baked_3d_filter_widens_and_dims_the_gaussians():
    scales = torch.tensor([[0.01, 0.02, 0.03], [0.1, 0.1, 0.1]])
    params = GaussianParameters.from_activated(
        torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]] * 2), scales, torch.tensor([0.8, 0.8]), torch.full((2, 3), 0.5))
    gmap = GaussianMap(params)
    unfiltered = splats_from_map(gmap, torch.zeros(2))
    torch.testing.assert_close(unfiltered.log_scales, torch.log(scales))
    torch.testing.assert_close(torch.sigmoid(unfiltered.opacity_logits), torch.tensor([0.8, 0.8]))
    variance = torch.tensor([0.01**2, 0.01**2])
    baked = splats_from_map(gmap, variance)
    expected_scales = torch.sqrt(scales**2 + variance[:, None])
    torch.testing.assert_close(baked.log_scales.exp(), expected_scales)
    expected_opacity = 0.8 * torch.prod(scales / expected_scales, dim=1)
    torch.testing.assert_close(torch.sigmoid(baked.opacity_logits), expected_opacity)
    assert expected_opacity[0] < 0.8 * 0.7 and expected_opacity[1] > 0.8 * 0.98  # small ones dim most


def _write_raw_ply(path, header: list[str], data: bytes) -> None:
    path.write_bytes(("\n".join(header) + "\n").encode("ascii") + data)


def _standard_header(count: int, fmt: str = "binary_little_endian 1.0") -> list[str]:
    return ["ply", f"format {fmt}", f"element vertex {count}"] + \
        [f"property float {name}" for name in PLY_PROPERTIES] + ["end_header"]


def test_read_accepts_extra_properties_and_double_precision(tmp_path):
    # the full SH degree-3 layout of the reference code, with opacity stored as double
    names = PLY_PROPERTIES[:9] + tuple(f"f_rest_{i}" for i in range(45)) + PLY_PROPERTIES[9:]
    types = ["<f8" if name == "opacity" else "<f4" for name in names]
    dtype = np.dtype(list(zip(names, types)))
    rows = np.zeros(3, dtype=dtype)
    for i, name in enumerate(names):
        rows[name] = np.arange(3) + i
    header = ["ply", "format binary_little_endian 1.0", "element vertex 3"] + \
        [f"property {'double' if name == 'opacity' else 'float'} {name}" for name in names] + ["end_header"]
    path = tmp_path / "sh3.ply"
    _write_raw_ply(path, header, rows.tobytes())
    splats = read_ply(path)
    # column i holds row + i: opacity is column 9 + 45, rot_0..3 are columns 58..61
    assert splats.opacity_logits.tolist() == [54.0, 55.0, 56.0]
    assert splats.quats_wxyz[1].tolist() == [59.0, 60.0, 61.0, 62.0]
    assert splats.means[2].tolist() == [2.0, 3.0, 4.0]


@pytest.mark.parametrize(
    "header, data, message, line",
    [
        (_standard_header(2, "ascii 1.0"), b"", "unsupported PLY format", 2),
        (["ply", "format binary_little_endian 1.0", "element vertex 2", "property float x", "end_header"], b"\0" * 8,
         "lacks the 3DGS vertex properties", None),
        (["ply", "format binary_little_endian 1.0", "element vertex 1", "property list uchar int vertex_indices",
          "end_header"], b"", "unsupported property", 4),
        (["ply", "format binary_little_endian 1.0", "element vertex one", "end_header"], b"", "malformed element", 3),
        (["ply", "format binary_little_endian 1.0", "element vertex 1", "element face 3", "end_header"], b"",
         "non-empty element 'face'", 4),
        (["ply", "element vertex 1", "end_header"], b"", "no 'format' line", None),
        (_standard_header(2), b"\0" * (2 * 17 * 4 - 5), "truncated PLY", None),
        (_standard_header(1), b"\0" * (17 * 4 + 3), "unexpected bytes", None),
        (["not a ply"], b"", "not a PLY file", 1),
    ],
)
def test_read_rejects_bad_files_naming_them(tmp_path, header, data, message, line):
    path = tmp_path / "bad.ply"
    _write_raw_ply(path, header, data)
    with pytest.raises(DatasetError, match=message) as info:
        read_ply(path)
    assert info.value.path == path and str(path) in str(info.value)
    assert info.value.line == line


def test_read_rejects_nonfinite_values_and_missing_files(tmp_path):
    splats = random_splats(5)
    means = splats.means.clone()
    means[3, 1] = float("nan")
    path = write_ply(tmp_path / "nan.ply", SplatPly(means, splats.f_dc, splats.opacity_logits, splats.log_scales,
                                                    splats.quats_wxyz))
    with pytest.raises(DatasetError, match="vertex 3 has a non-finite position"):
        read_ply(path)
    with pytest.raises(DatasetError, match="not found"):
        read_ply(tmp_path / "missing.ply")
    # a truncated copy of a good file
    good = write_ply(tmp_path / "good.ply", random_splats(50))
    cut = tmp_path / "cut.ply"
    cut.write_bytes(good.read_bytes()[:-100])
    with pytest.raises(DatasetError, match="truncated"):
        read_ply(cut)


def test_write_is_atomic_and_leaves_no_temporary(tmp_path, monkeypatch):
    path = write_ply(tmp_path / "map.ply", random_splats(5, seed=1))
    good = path.read_bytes()

    def no_space(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("os.fsync", no_space)
    with pytest.raises(Exception, match="No space left on device") as info:
        write_ply(path, random_splats(500, seed=2))
    assert str(path) in str(info.value)
    assert path.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.ply"]
