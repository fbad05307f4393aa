"""The Gaussian map: unconstrained parameters as leaf tensors, their activations, add/remove,
rigid motion with anchor keyframes, and a plain-tensor state dict.

Parameters (trained, each a leaf tensor with ``requires_grad``) and their activations (what the
renderer receives, see :class:`ActivatedGaussians`):

============== ======== ================================ ====================================
name           shape    activation                       activated meaning
============== ======== ================================ ====================================
means          [N, 3]   identity                         centre in world coordinates, metres
quats_wxyz     [N, 4]   q / |q|                          unit rotation quaternion (w, x, y, z)
log_scales     [N, 3]   exp                              std-devs along the local axes, metres
opacity_logits [N]      sigmoid                          peak opacity in (0, 1)
colors_raw     [N, 3]   sigmoid                          RGB in (0, 1)
============== ======== ================================ ====================================

Colours use a sigmoid rather than a clamp: a clamp has zero gradient once a value leaves
[0, 1] and the colour can never come back, a sigmoid keeps every colour trainable and in range.
Initial raw colours are ``logit(clamp(rgb, 1e-3, 1 - 1e-3))``.

Buffers (not trained), [N]:
- ``anchor_keyframe`` (int64): id of the keyframe that created the Gaussian (index in the run's
  keyframe list, 0-based; -1 = none, e.g. a map read from a PLY). After pose-graph optimisation
  each Gaussian moves rigidly with its anchor (:meth:`GaussianMap.transform_by_anchor`).
- ``created_frame`` (int64): index of the frame whose pixels created it (-1 = unknown).
- ``max_sampling_rate`` (the map's float dtype): the highest sampling rate, ``focal / depth`` in
  pixels per metre, among the keyframes that trained the Gaussian (0 = unknown; with the filter off,
  mapping leaves it at the creating view's rate). It sizes the
  Mip-Splatting 3D smoothing filter (``render.filter_3d``), which belongs to the map and so must not
  change with the camera that renders it (Yu et al., 2024, section 4.1).

Resizing keeps a :class:`mipslam.gaussians.optimizer.GaussianOptimizer` aligned: pass it to
:meth:`GaussianMap.add` / :meth:`GaussianMap.remove` and its Adam moments are resized with the
parameters (new rows start at zero, removed rows are dropped).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Callable, Mapping

import torch

from mipslam.errors import MipslamError
from mipslam.geometry.se3 import rotmat_to_quat_wxyz

if TYPE_CHECKING:
    from mipslam.gaussians.optimizer import GaussianOptimizer

logger = logging.getLogger(__name__)

PARAMETER_NAMES: tuple[str, ...] = ("means", "quats_wxyz", "log_scales", "opacity_logits", "colors_raw")
BUFFER_NAMES: tuple[str, ...] = ("anchor_keyframe", "created_frame", "max_sampling_rate")
#: Buffers that hold ids (int64); the others take the map's floating dtype.
ID_BUFFER_NAMES: tuple[str, ...] = ("anchor_keyframe", "created_frame")
TRAILING_SHAPES: dict[str, tuple[int, ...]] = {
    "means": (3,),
    "quats_wxyz": (4,),
    "log_scales": (3,),
    "opacity_logits": (),
    "colors_raw": (3,),
    "anchor_keyframe": (),
    "created_frame": (),
    "max_sampling_rate": (),
}
COLOR_EPS = 1e-3
QUAT_NORM_EPS = 1e-12


def color_logit(rgb: torch.Tensor) -> torch.Tensor:
    """Raw colour parameter of an RGB value (inverse of the sigmoid, clamped).  rgb [..., 3] in [0, 1]"""
    return torch.logit(rgb.clamp(COLOR_EPS, 1.0 - COLOR_EPS))


def quat_multiply_wxyz(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product q1 * q2 (rotation q2 first, then q1).  q1 [..., 4], q2 [..., 4] -> [..., 4] (wxyz)"""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


@dataclass(frozen=True)
class ActivatedGaussians:
    """What the renderer receives (all on the map's device and dtype; ``means`` is the map's
    leaf tensor itself, the others are computed, so treat all of them as read-only).

    means      [N, 3] world, metres
    quats      [N, 4] unit quaternions (w, x, y, z), local-to-world rotation
    scales     [N, 3] std-devs in metres (linear)
    opacities  [N]    in (0, 1)
    colors     [N, 3] RGB in (0, 1)
    max_sampling_rate [N] px/m the map's sampling rates for the 3D filter (0 = unknown), or None
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    max_sampling_rate: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def _map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> "ActivatedGaussians":
        """``fn`` applied to every per-Gaussian tensor; an absent optional field (None) stays absent."""
        return ActivatedGaussians(**{f.name: None if (value := getattr(self, f.name)) is None else fn(value)
                                     for f in fields(self)})

    def detached(self) -> "ActivatedGaussians":
        """The same Gaussians cut from the autograd graph (a frozen map for tracking and evaluation); the
        sampling rates come along, so the 3D filter stays the map's."""
        return self._map(torch.Tensor.detach)

    def rows(self, index: torch.Tensor) -> "ActivatedGaussians":
        """The Gaussians at ``index`` [M] int64, every field (the sampling rates included) alike."""
        return self._map(lambda value: value.index_select(0, index))


@dataclass(frozen=True)
class GaussianParameters:
    """A batch of Gaussians in raw (unconstrained) form: what :meth:`GaussianMap.add` takes.

    means [N, 3], quats_wxyz [N, 4], log_scales [N, 3], opacity_logits [N], colors_raw [N, 3]
    (floating, one device), anchor_keyframe [N] int64, created_frame [N] int64, max_sampling_rate [N]
    floating, px/m (None: zeros, unknown).
    """

    means: torch.Tensor
    quats_wxyz: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors_raw: torch.Tensor
    anchor_keyframe: torch.Tensor
    created_frame: torch.Tensor
    max_sampling_rate: torch.Tensor | None = None

    def __post_init__(self):
        if self.max_sampling_rate is None and isinstance(self.means, torch.Tensor):
            object.__setattr__(self, "max_sampling_rate", torch.zeros(self.means.shape[:1], dtype=self.means.dtype,
                                                                      device=self.means.device))
        count = self.means.shape[0] if self.means.dim() >= 1 else -1
        for f in fields(self):
            value = getattr(self, f.name)
            expected = (count, *TRAILING_SHAPES[f.name])
            if not isinstance(value, torch.Tensor) or tuple(value.shape) != expected:
                shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
                raise ValueError(f"GaussianParameters.{f.name}: expected shape {expected}, got {shape}")
            if f.name in ID_BUFFER_NAMES and value.dtype != torch.int64:
                raise ValueError(f"GaussianParameters.{f.name}: expected int64, got {value.dtype}")
            if f.name not in ID_BUFFER_NAMES and not value.is_floating_point():
                raise ValueError(f"GaussianParameters.{f.name}: expected a floating dtype, got {value.dtype}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @classmethod
    def from_activated(cls, means: torch.Tensor, quats_wxyz: torch.Tensor, scales: torch.Tensor,
                       opacities: torch.Tensor, colors: torch.Tensor, anchor_keyframe: torch.Tensor | int = -1,
                       created_frame: torch.Tensor | int = -1,
                       max_sampling_rate: torch.Tensor | None = None) -> "GaussianParameters":
        """Raw parameters from activated values (inverse activations; opacities/colours clamped
        to [1e-3, 1 - 1e-3] before the logit).

        means [N, 3], quats_wxyz [N, 4] (need not be unit), scales [N, 3] > 0 metres,
        opacities [N] in [0, 1], colors [N, 3] in [0, 1]; anchor/created: int64 [N] or one int;
        max_sampling_rate [N] px/m or None (unknown).
        """
        n = means.shape[0]

        def ids(value: torch.Tensor | int) -> torch.Tensor:
            if isinstance(value, torch.Tensor):
                return value.to(device=means.device, dtype=torch.int64)
            return torch.full((n,), int(value), dtype=torch.int64, device=means.device)

        return cls(
            means=means,
            quats_wxyz=quats_wxyz,
            log_scales=torch.log(scales),
            opacity_logits=torch.logit(opacities.clamp(COLOR_EPS, 1.0 - COLOR_EPS)),
            colors_raw=color_logit(colors),
            anchor_keyframe=ids(anchor_keyframe),
            created_frame=ids(created_frame),
            max_sampling_rate=max_sampling_rate,
        )

    @classmethod
    def concatenate(cls, batches: list["GaussianParameters"]) -> "GaussianParameters":
        if not batches:
            raise ValueError("concatenate needs at least one batch")
        return cls(**{f.name: torch.cat([getattr(b, f.name) for b in batches]) for f in fields(cls)})

    def subset(self, index: torch.Tensor) -> "GaussianParameters":
        """Rows selected by a bool mask [N] or an index tensor [M]."""
        return GaussianParameters(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


class GaussianMap:
    """The map: leaf parameters (see the module docstring) plus per-Gaussian buffers.

    Device and dtype come from the tensors it is built from (or the arguments of :meth:`empty`).
    Parameters are replaced by new leaf tensors on every resize, so hold the map, not its
    tensors, across :meth:`add` / :meth:`remove`.
    """

    def __init__(self, params: GaussianParameters):
        device = params.means.device
        dtype = params.means.dtype
        for name in PARAMETER_NAMES:
            value = getattr(params, name).detach().to(device=device, dtype=dtype).clone()
            setattr(self, name, value.requires_grad_(True))
        for name in BUFFER_NAMES:
            setattr(self, name, getattr(params, name).detach().to(device=device, dtype=self._buffer_dtype(name)).clone())

    # --------------------------------------------------------------------------- construction
    @classmethod
    def empty(cls, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> "GaussianMap":
        def zeros(*shape: int, kind: torch.dtype = dtype) -> torch.Tensor:
            return torch.zeros(shape, dtype=kind, device=device)

        return cls(GaussianParameters(
            means=zeros(0, 3), quats_wxyz=zeros(0, 4), log_scales=zeros(0, 3), opacity_logits=zeros(0),
            colors_raw=zeros(0, 3), anchor_keyframe=zeros(0, kind=torch.int64), created_frame=zeros(0, kind=torch.int64),
            max_sampling_rate=zeros(0),
        ))

    def _buffer_dtype(self, name: str) -> torch.dtype:
        return torch.int64 if name in ID_BUFFER_NAMES else self.means.dtype

    # --------------------------------------------------------------------------- inspection
    def __len__(self) -> int:
        return int(self.means.shape[0])

    def __repr__(self) -> str:
        return f"GaussianMap(n={len(self)}, device={self.device}, dtype={self.dtype})"

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def parameters(self) -> dict[str, torch.Tensor]:
        """The current leaf tensors by name (the objects an optimizer must hold)."""
        return {name: getattr(self, name) for name in PARAMETER_NAMES}

    def buffers(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in BUFFER_NAMES}

    def detached(self) -> GaussianParameters:
        """A detached copy of everything, e.g. to build another map or compare states."""
        return GaussianParameters(**{name: getattr(self, name).detach().clone() for name in PARAMETER_NAMES + BUFFER_NAMES})

    def activated(self, index: torch.Tensor | None = None) -> ActivatedGaussians:
        """Renderer inputs (differentiable w.r.t. the leaf parameters); see :class:`ActivatedGaussians`.

        ``index`` [M] int64: only those rows (gradients flow back to them; the other rows get zeros).
        """
        if index is None:
            means, quats, log_scales, opacity_logits, colors_raw, rates = (
                self.means, self.quats_wxyz, self.log_scales, self.opacity_logits, self.colors_raw,
                self.max_sampling_rate)
        else:
            means, quats, log_scales, opacity_logits, colors_raw, rates = (t.index_select(0, index) for t in (
                self.means, self.quats_wxyz, self.log_scales, self.opacity_logits, self.colors_raw,
                self.max_sampling_rate))
        norm = quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_NORM_EPS)
        return ActivatedGaussians(
            means=means,
            quats=quats / norm,
            scales=torch.exp(log_scales),
            opacities=torch.sigmoid(opacity_logits),
            colors=torch.sigmoid(colors_raw),
            max_sampling_rate=rates,
        )

    # --------------------------------------------------------------------------- resizing
    def add(self, new: GaussianParameters, optimizer: "GaussianOptimizer | None" = None) -> slice:
        """Append Gaussians; returns the slice of their rows.

        With ``optimizer`` its Adam state grows with the parameters: the new rows' first and
        second moments are zero (the step count is shared per tensor, as torch's Adam keeps it).
        """
        count = len(new)
        start = len(self)
        if count == 0:
            return slice(start, start)
        old = self.parameters()
        for name in PARAMETER_NAMES:
            extra = getattr(new, name).detach().to(device=self.device, dtype=self.dtype)
            setattr(self, name, torch.cat([old[name].detach(), extra]).requires_grad_(True))
        for name in BUFFER_NAMES:
            extra = getattr(new, name).to(device=self.device, dtype=self._buffer_dtype(name))
            setattr(self, name, torch.cat([getattr(self, name), extra]))
        if optimizer is not None:
            optimizer.on_map_resized(old, self.parameters(), lambda state: torch.cat(
                [state, torch.zeros((count, *state.shape[1:]), dtype=state.dtype, device=state.device)]))
        logger.debug("added %d Gaussians (now %d)", count, len(self))
        return slice(start, start + count)

    def remove(self, mask: torch.Tensor, optimizer: "GaussianOptimizer | None" = None) -> int:
        """Delete the Gaussians where ``mask`` [N] (bool) is True; returns how many were removed.

        With ``optimizer`` the kept rows keep their Adam moments and step, so the next step on
        the kept Gaussians is exactly the step they would have taken without the removal.
        """
        mask = torch.as_tensor(mask, device=self.device)
        if mask.dtype != torch.bool or tuple(mask.shape) != (len(self),):
            raise ValueError(f"remove mask must be bool of shape ({len(self)},), got {mask.dtype} {tuple(mask.shape)}")
        removed = int(mask.sum())
        if removed == 0:
            return 0
        keep = ~mask
        old = self.parameters()
        for name in PARAMETER_NAMES:
            setattr(self, name, old[name].detach()[keep].clone().requires_grad_(True))
        for name in BUFFER_NAMES:
            setattr(self, name, getattr(self, name)[keep].clone())
        if optimizer is not None:
            optimizer.on_map_resized(old, self.parameters(), lambda state: state[keep].clone())
        logger.debug("removed %d Gaussians (now %d)", removed, len(self))
        return removed

    @torch.no_grad()
    def observe_sampling_rates(self, rates: torch.Tensor) -> None:
        """Raise ``max_sampling_rate`` to ``rates`` [N] (px/m, 0 where a view does not see the Gaussian)."""
        if tuple(rates.shape) != (len(self),):
            raise ValueError(f"sampling rates must have shape ({len(self)},), got {tuple(rates.shape)}")
        self.max_sampling_rate = torch.maximum(self.max_sampling_rate, rates.to(self.max_sampling_rate))

    # --------------------------------------------------------------------------- pose-graph correction
    @torch.no_grad()
    def transform_by_anchor(self, T_new_old: torch.Tensor) -> int:
        """Move every Gaussian rigidly with its anchor keyframe (after SA-PGO).

        T_new_old [K, 4, 4]: for keyframe k, the world-frame correction ``T_wc_new @ inv(T_wc_old)``
        (identity for keyframes that did not move). A Gaussian anchored at k gets
        ``mean <- R_k mean + t_k`` and ``q <- q(R_k) * q`` (its local axes rotate with it; scales,
        opacity and colour are unchanged). Gaussians with anchor -1 stay where they are.
        Parameters are updated in place (same leaf tensors), so an optimizer stays valid; its
        moments are not rotated (they decay within a few steps). Returns how many moved.
        """
        if T_new_old.dim() != 3 or tuple(T_new_old.shape[1:]) != (4, 4):
            raise ValueError(f"T_new_old must have shape [K, 4, 4], got {tuple(T_new_old.shape)}")
        anchors = self.anchor_keyframe
        movable = anchors >= 0
        if movable.any() and int(anchors.max()) >= T_new_old.shape[0]:
            raise MipslamError(
                f"a Gaussian is anchored to keyframe {int(anchors.max())} but only {T_new_old.shape[0]} keyframe "
                "corrections were given; pass one 4x4 per keyframe (identity where unchanged)"
            )
        if not movable.any():
            return 0
        index = anchors[movable]
        T = T_new_old.to(device=self.device, dtype=self.dtype)
        rotations = T[:, :3, :3]  # [K, 3, 3]
        quats_k = rotmat_to_quat_wxyz(rotations)  # [K, 4]
        R = rotations[index]  # [M, 3, 3]
        t = T[index, :3, 3]  # [M, 3]
        self.means[movable] = (R @ self.means[movable].unsqueeze(-1)).squeeze(-1) + t
        self.quats_wxyz[movable] = quat_multiply_wxyz(quats_k[index], self.quats_wxyz[movable])
        return int(movable.sum())

    # --------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors (detached clones): the five parameters and the three buffers."""
        return {name: getattr(self, name).detach().clone() for name in PARAMETER_NAMES + BUFFER_NAMES}

    def load_state_dict(self, state: Mapping[str, torch.Tensor]) -> None:
        """Replace the contents with ``state`` (as written by :meth:`state_dict`), on this map's
        device and dtype. Any optimizer must be rebuilt or reloaded afterwards."""
        loaded = GaussianMap.from_state_dict(state, device=self.device, dtype=self.dtype)
        for name in PARAMETER_NAMES + BUFFER_NAMES:
            setattr(self, name, getattr(loaded, name))

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor], *, device: torch.device | str | None = None,
                        dtype: torch.dtype | None = None) -> "GaussianMap":
        missing = [name for name in PARAMETER_NAMES + ID_BUFFER_NAMES if name not in state]
        if missing:
            raise MipslamError(f"Gaussian map state lacks {', '.join(missing)}")
        device = device if device is not None else state["means"].device
        dtype = dtype if dtype is not None else state["means"].dtype
        values = {name: state[name].to(device=device, dtype=dtype) for name in PARAMETER_NAMES}
        values.update({name: state[name].to(device=device, dtype=torch.int64) for name in ID_BUFFER_NAMES})
        if "max_sampling_rate" in state:  # absent from checkpoints written before it existed: unknown
            values["max_sampling_rate"] = state["max_sampling_rate"].to(device=device, dtype=dtype)
        try:
            return cls(GaussianParameters(**values))
        except ValueError as exc:
            raise MipslamError(f"Gaussian map state is inconsistent: {exc}") from exc
