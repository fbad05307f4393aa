"""The standard 3D Gaussian Splatting PLY (Kerbl et al., 2023), SH degree 0, read and write.

Layout: ``format binary_little_endian 1.0``, one ``vertex`` element, float32 properties in this
order (what common splat viewers read)::

    x y z              centre, world metres
    nx ny nz           normals, written as 0 (unused, part of the reference layout)
    f_dc_0 f_dc_1 f_dc_2  DC spherical-harmonic colour, f_dc = (rgb - 0.5) / C0, C0 = 0.28209479177387814
    opacity            opacity logit (viewers apply a sigmoid)
    scale_0..2         log std-devs, metres (viewers apply exp)
    rot_0..3           rotation quaternion (w, x, y, z), not necessarily unit (viewers normalise)
    max_sampling_rate  (mipslam's map only, optional) px/m that sizes the 3D filter; viewers ignore it

:func:`write_ply` writes atomically (temporary file, fsync, rename). :func:`read_ply` validates
the header (format, element, property names and types), the data size and finiteness, and
raises DatasetError naming the file (with the header line where that is the problem).
Extra vertex properties (e.g. ``f_rest_*`` of higher SH degrees) are accepted and ignored.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mipslam.errors import DatasetError, MipslamError
from mipslam.gaussians.model import GaussianMap, GaussianParameters, color_logit
from mipslam.io.run_folder import atomic_write

logger = logging.getLogger(__name__)

SH_C0 = 0.28209479177387814
PLY_PROPERTIES: tuple[str, ...] = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)
SAMPLING_RATE_PROPERTY = "max_sampling_rate"
MAX_HEADER_BYTES = 1 << 16
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def rgb_to_f_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC SH coefficient of a colour (3DGS convention).  rgb [..., 3] -> [..., 3]"""
    return (rgb - 0.5) / SH_C0


def f_dc_to_rgb(f_dc: torch.Tensor) -> torch.Tensor:
    """Colour of a DC SH coefficient (not clamped).  f_dc [..., 3] -> [..., 3]"""
    return f_dc * SH_C0 + 0.5


@dataclass(frozen=True)
class SplatPly:
    """The fields of a 3DGS PLY as float32 CPU tensors (file values, no activation applied).

    means [N, 3], f_dc [N, 3], opacity_logits [N], log_scales [N, 3], quats_wxyz [N, 4],
    normals [N, 3] (zeros when written by mipslam), max_sampling_rate [N] px/m or None (not in the file).
    """

    means: torch.Tensor
    f_dc: torch.Tensor
    opacity_logits: torch.Tensor
    log_scales: torch.Tensor
    quats_wxyz: torch.Tensor
    normals: torch.Tensor | None = None
    max_sampling_rate: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.means.shape[0])


def _header(count: int, extra: tuple[str, ...] = ()) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", "comment written by mipslam (3DGS layout, SH degree 0)",
             f"element vertex {count}"]
    lines += [f"property float {name}" for name in PLY_PROPERTIES + extra]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(path: str | Path, splats: SplatPly) -> Path:
    """Write ``splats`` as a 3DGS PLY, atomically. Returns ``path``."""
    n = len(splats)
    normals = splats.normals if splats.normals is not None else torch.zeros((n, 3))
    columns = [splats.means, normals, splats.f_dc, splats.opacity_logits.reshape(n, 1), splats.log_scales,
               splats.quats_wxyz]
    expected = [3, 3, 3, 1, 3, 4]
    extra: tuple[str, ...] = ()
    if splats.max_sampling_rate is not None:
        columns.append(splats.max_sampling_rate.reshape(-1, 1))
        expected.append(1)
        extra = (SAMPLING_RATE_PROPERTY,)
    for column, width in zip(columns, expected):
        if tuple(column.shape) != (n, width):
            raise MipslamError(f"{path}: cannot write PLY, a field has shape {tuple(column.shape)}, expected ({n}, {width})")
    table = torch.cat([c.detach().to(device="cpu", dtype=torch.float32) for c in columns], dim=1)  # [N, 17 (+1)]
    data = np.ascontiguousarray(table.numpy().astype("<f4", copy=False))
    with atomic_write(path) as handle:
        handle.write(_header(n, extra))
        handle.write(data.tobytes())
    logger.debug("wrote %d Gaussians to %s", n, path)
    return Path(path)


def _parse_header(path: Path, raw: bytes) -> tuple[int, np.dtype, int]:
    """-> (vertex count, structured dtype of one vertex, byte offset of the data)."""
    end = raw.find(b"end_header\n", 0, MAX_HEADER_BYTES)
    if not raw.startswith(b"ply\n") and not raw.startswith(b"ply\r\n"):
        raise DatasetError(path, "not a PLY file (first line is not 'ply')", line=1)
    if end < 0:
        raise DatasetError(path, "PLY header has no 'end_header' line within the first 64 KiB (truncated or not a PLY)")
    data_start = end + len(b"end_header\n")
    try:
        lines = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise DatasetError(path, "PLY header is not ASCII text") from exc
    count = None
    fields: list[tuple[str, str]] = []
    element = None
    saw_format = False
    for number, line in enumerate(lines, start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format":
            if words[1:] != ["binary_little_endian", "1.0"]:
                raise DatasetError(path, f"unsupported PLY format '{' '.join(words[1:])}'; "
                                         "3DGS PLY files are 'binary_little_endian 1.0'", line=number)
            saw_format = True
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise DatasetError(path, f"malformed element line '{line}'", line=number)
            element = words[1]
            if element == "vertex":
                if count is not None:
                    raise DatasetError(path, "two 'element vertex' lines", line=number)
                count = int(words[2])
            elif int(words[2]) != 0:
                raise DatasetError(path, f"unexpected non-empty element '{element}' (a 3DGS PLY has only vertices)",
                                   line=number)
        elif words[0] == "property":
            if element != "vertex":
                raise DatasetError(path, f"property outside the vertex element: '{line}'", line=number)
            if len(words) != 3 or words[1] == "list":
                raise DatasetError(path, f"unsupported property line '{line}' (list properties are not 3DGS)",
                                   line=number)
            if words[1] not in _PLY_TYPES:
                raise DatasetError(path, f"unknown property type '{words[1]}'", line=number)
            if any(name == words[2] for name, _ in fields):
                raise DatasetError(path, f"duplicate property '{words[2]}'", line=number)
            fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
        else:
            raise DatasetError(path, f"unexpected header line '{line}'", line=number)
    if not saw_format:
        raise DatasetError(path, "PLY header has no 'format' line")
    if count is None:
        raise DatasetError(path, "PLY header has no 'element vertex N' line")
    names = [name for name, _ in fields]
    missing = [name for name in PLY_PROPERTIES if name not in names and name not in ("nx", "ny", "nz")]
    if missing:
        raise DatasetError(path, f"PLY lacks the 3DGS vertex properties {', '.join(missing)}; "
                                 "is this a Gaussian-splat PLY (not a mesh or point cloud)?")
    wrong_type = [name for name, kind in fields if name in PLY_PROPERTIES and kind[1] != "f"]
    if wrong_type:
        raise DatasetError(path, f"PLY properties {', '.join(wrong_type)} must be float or double")
    return count, np.dtype(fields), data_start


def ply_vertex_count(path: str | Path) -> int:
    """The Gaussian count of a 3DGS PLY from its header alone (the data is not read)."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            raw = handle.read(MAX_HEADER_BYTES)
    except FileNotFoundError:
        raise DatasetError(path, "PLY file not found") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read PLY file ({exc.strerror or exc})") from None
    return _parse_header(path, raw)[0]


def read_ply(path: str | Path) -> SplatPly:
    """Read and validate a 3DGS PLY (see the module docstring) -> float32 CPU tensors."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(path, "PLY file not found") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read PLY file ({exc.strerror or exc})") from None
    count, vertex_dtype, data_start = _parse_header(path, raw)
    expected = count * vertex_dtype.itemsize
    available = len(raw) - data_start
    if available < expected:
        raise DatasetError(path, f"truncated PLY: {count} vertices need {expected} bytes of data, found {available}")
    if available > expected:
        raise DatasetError(path, f"PLY has {available - expected} unexpected bytes after the {count} vertices")
    table = np.frombuffer(raw, dtype=vertex_dtype, count=count, offset=data_start)

    def columns(*names: str) -> torch.Tensor:
        stacked = np.stack([table[name].astype(np.float32) for name in names], axis=-1) if count else \
            np.zeros((0, len(names)), dtype=np.float32)
        return torch.from_numpy(np.ascontiguousarray(stacked))

    means = columns("x", "y", "z")
    f_dc = columns("f_dc_0", "f_dc_1", "f_dc_2")
    opacity = columns("opacity")[:, 0].contiguous()
    log_scales = columns("scale_0", "scale_1", "scale_2")
    quats = columns("rot_0", "rot_1", "rot_2", "rot_3")
    normals = columns("nx", "ny", "nz") if "nx" in vertex_dtype.names else torch.zeros((count, 3))
    rates = columns(SAMPLING_RATE_PROPERTY)[:, 0].contiguous() if SAMPLING_RATE_PROPERTY in vertex_dtype.names else None
    for name, values in (("position", means), ("f_dc", f_dc), ("opacity", opacity), ("scale", log_scales),
                         ("rotation", quats)):
        finite = torch.isfinite(values)
        finite = finite.all(dim=1) if finite.dim() == 2 else finite
        if not bool(finite.all()):
            first = int(torch.nonzero(~finite)[0, 0])
            raise DatasetError(path, f"vertex {first} has a non-finite {name}; the file is corrupt")
    zero_quat = quats.norm(dim=1) == 0
    if bool(zero_quat.any()):
        raise DatasetError(path, f"vertex {int(torch.nonzero(zero_quat)[0, 0])} has a zero rotation quaternion")
    if rates is not None:
        bad = ~(torch.isfinite(rates) & (rates >= 0))
        if bool(bad.any()):
            raise DatasetError(path, f"vertex {int(torch.nonzero(bad)[0, 0])} has a negative or non-finite "
                                     f"{SAMPLING_RATE_PROPERTY}; the file is corrupt")
    return SplatPly(means=means, f_dc=f_dc, opacity_logits=opacity, log_scales=log_scales, quats_wxyz=quats,
                    normals=normals, max_sampling_rate=rates)


# ----------------------------------------------------------------------------- GaussianMap <-> PLY


def splats_from_map(gaussian_map: GaussianMap, filter_3d_variance: torch.Tensor | None = None) -> SplatPly:
    """The map's PLY fields. Colours: ``f_dc = (sigmoid(colors_raw) - 0.5) / C0``.

    filter_3d_variance [N] (metres^2, optional): a Mip-Splatting 3D smoothing filter to bake in
    for viewers that do not apply it: ``Sigma' = Sigma + v I`` gives scales ``sqrt(s^2 + v)``
    and opacity ``o * sqrt(det Sigma / det Sigma')`` (Yu et al., 2024). Without it the map's
    ``max_sampling_rate`` is kept as an extra property, so mipslam can apply the filter when it reads
    the file back; with it baked in the rates are left out (the filter must not apply twice).
    """
    with torch.no_grad():
        log_scales = gaussian_map.log_scales.detach()
        opacity_logits = gaussian_map.opacity_logits.detach()
        if filter_3d_variance is not None:
            variance = filter_3d_variance.to(log_scales).reshape(-1, 1)  # [N, 1]
            scales_sq = torch.exp(2 * log_scales)  # [N, 3]
            filtered_sq = scales_sq + variance
            coefficient = torch.sqrt(torch.prod(scales_sq / filtered_sq, dim=1))  # [N]
            opacity = torch.sigmoid(opacity_logits) * coefficient
            log_scales = 0.5 * torch.log(filtered_sq)
            opacity_logits = torch.logit(opacity.clamp(1e-6, 1 - 1e-6))
        return SplatPly(
            means=gaussian_map.means.detach().cpu().float(),
            f_dc=rgb_to_f_dc(torch.sigmoid(gaussian_map.colors_raw.detach())).cpu().float(),
            opacity_logits=opacity_logits.cpu().float(),
            log_scales=log_scales.cpu().float(),
            quats_wxyz=gaussian_map.quats_wxyz.detach().cpu().float(),
            max_sampling_rate=None if filter_3d_variance is not None else
            gaussian_map.max_sampling_rate.detach().cpu().float(),
        )


def write_map_ply(path: str | Path, gaussian_map: GaussianMap, filter_3d_variance: torch.Tensor | None = None) -> Path:
    """Write a map as ``map.ply`` (3DGS layout, atomic). See :func:`splats_from_map`."""
    return write_ply(path, splats_from_map(gaussian_map, filter_3d_variance))


def read_map_ply(path: str | Path, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> GaussianMap:
    """A GaussianMap from a 3DGS PLY (anchors and creation frames -1: unknown; sampling rates 0, unknown,
    unless the file has mipslam's ``max_sampling_rate`` property).

    Colours: ``colors_raw = logit(clamp(f_dc * C0 + 0.5, 1e-3, 1 - 1e-3))``.
    """
    splats = read_ply(path)
    n = len(splats)
    params = GaussianParameters(
        means=splats.means.to(device=device, dtype=dtype),
        quats_wxyz=splats.quats_wxyz.to(device=device, dtype=dtype),
        log_scales=splats.log_scales.to(device=device, dtype=dtype),
        opacity_logits=splats.opacity_logits.to(device=device, dtype=dtype),
        colors_raw=color_logit(f_dc_to_rgb(splats.f_dc)).to(device=device, dtype=dtype),
        anchor_keyframe=torch.full((n,), -1, dtype=torch.int64, device=device),
        created_frame=torch.full((n,), -1, dtype=torch.int64, device=device),
        max_sampling_rate=None if splats.max_sampling_rate is None else
        splats.max_sampling_rate.to(device=device, dtype=dtype),
    )
    return GaussianMap(params)
