"""Adam over a :class:`GaussianMap`, one parameter group per parameter with its own learning rate,
kept aligned with the map when Gaussians are added or removed.

torch's Adam keys its state (``exp_avg``, ``exp_avg_sq``, ``step``) by the parameter tensor
object. Resizing the map creates new leaf tensors, so :meth:`GaussianOptimizer.on_map_resized`
(called by ``GaussianMap.add/remove``) moves each state entry to the new tensor, transforming
the per-row moments the same way as the rows (zeros appended for new Gaussians, removed rows
dropped). The ``step`` count is one scalar per tensor in torch's Adam, so it is kept as is: new
rows start with zero moments at the tensor's current step (the 3D Gaussian Splatting practice).

:meth:`step` checks that the optimizer still holds the map's current tensors, so a resize done
without passing the optimizer is an error instead of silently training detached copies.
"""
from __future__ import annotations

import logging
from typing import Callable, Mapping

import torch

from mipslam.errors import MipslamError
from mipslam.gaussians.model import PARAMETER_NAMES, GaussianMap

logger = logging.getLogger(__name__)

_MOMENTS = ("exp_avg", "exp_avg_sq")


class GaussianOptimizer:
    """Adam with one group per map parameter (``name`` = parameter name, own ``lr``).

    learning_rates: mapping parameter name -> lr; every name in
    ``mipslam.gaussians.model.PARAMETER_NAMES`` must be present (lr 0 freezes a parameter).
    eps defaults to 1e-15 as in 3D Gaussian Splatting (gradients of tiny Gaussians are tiny).
    """

    def __init__(self, gaussian_map: GaussianMap, learning_rates: Mapping[str, float], *,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15):
        missing = [name for name in PARAMETER_NAMES if name not in learning_rates]
        unknown = [name for name in learning_rates if name not in PARAMETER_NAMES]
        if missing or unknown:
            raise MipslamError(f"learning rates: missing {missing or 'none'}, unknown {unknown or 'none'}; "
                               f"give one per parameter of {PARAMETER_NAMES}")
        self.map = gaussian_map
        groups = [{"params": [param], "lr": float(learning_rates[name]), "name": name}
                  for name, param in gaussian_map.parameters().items()]
        # One fused kernel per tensor instead of about ten elementwise passes: 1.1-1.7 ms against 3.1-3.4 ms
        # per step on a 50k-Gaussian map (2 CPU threads), a few per cent of a mapping iteration.
        fused = gaussian_map.device.type in ("cpu", "cuda")  # the map's tensors are floating point (model.py)
        self.adam = torch.optim.Adam(groups, betas=betas, eps=eps, fused=fused)

    @classmethod
    def from_config(cls, gaussian_map: GaussianMap, mapping_config) -> "GaussianOptimizer":
        """Learning rates from a :class:`mipslam.mapping.MappingOptions` (lr_means, lr_quats, lr_scales,
        lr_opacities, lr_colors)."""
        return cls(gaussian_map, {
            "means": mapping_config.lr_means,
            "quats_wxyz": mapping_config.lr_quats,
            "log_scales": mapping_config.lr_scales,
            "opacity_logits": mapping_config.lr_opacities,
            "colors_raw": mapping_config.lr_colors,
        })

    # --------------------------------------------------------------------------- stepping
    def _group(self, name: str) -> dict:
        for group in self.adam.param_groups:
            if group["name"] == name:
                return group
        raise MipslamError(f"no parameter group named '{name}'")

    def check_aligned(self) -> None:
        """Raise if the map's tensors are not the ones this optimizer updates."""
        current = self.map.parameters()
        for group in self.adam.param_groups:
            if group["params"][0] is not current[group["name"]]:
                raise MipslamError(
                    f"the Gaussian map's '{group['name']}' was replaced without its optimizer; "
                    "pass optimizer= to GaussianMap.add/remove (or rebuild the optimizer)"
                )

    def zero_grad(self) -> None:
        self.adam.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.check_aligned()
        self.adam.step()

    @property
    def learning_rates(self) -> dict[str, float]:
        return {group["name"]: float(group["lr"]) for group in self.adam.param_groups}

    def set_learning_rate(self, name: str, lr: float) -> None:
        self._group(name)["lr"] = float(lr)

    # --------------------------------------------------------------------------- resizing
    def on_map_resized(self, old: Mapping[str, torch.Tensor], new: Mapping[str, torch.Tensor],
                       transform_rows: Callable[[torch.Tensor], torch.Tensor]) -> None:
        """Point each group at the new tensor and carry its Adam state across.

        old/new: parameter name -> old/new leaf tensor; ``transform_rows`` maps a per-row state
        tensor [N_old, ...] to [N_new, ...] exactly as the parameter rows were transformed.
        """
        for group in self.adam.param_groups:
            name = group["name"]
            old_param, new_param = old[name], new[name]
            if group["params"][0] is not old_param:
                raise MipslamError(f"optimizer group '{name}' does not hold the map's tensor being resized")
            group["params"][0] = new_param
            state = self.adam.state.pop(old_param, None)
            if state:
                moved = dict(state)
                for key in _MOMENTS:
                    if key in moved:
                        moved[key] = transform_rows(moved[key])
                self.adam.state[new_param] = moved

    # --------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors: per parameter ``NAME.lr`` (float64 scalar) and, once stepped,
        ``NAME.step``, ``NAME.exp_avg``, ``NAME.exp_avg_sq``; plus ``betas`` [2] and ``eps``."""
        out: dict[str, torch.Tensor] = {}
        defaults = self.adam.defaults
        out["betas"] = torch.tensor(defaults["betas"], dtype=torch.float64)
        out["eps"] = torch.tensor(defaults["eps"], dtype=torch.float64)
        for group in self.adam.param_groups:
            name = group["name"]
            out[f"{name}.lr"] = torch.tensor(group["lr"], dtype=torch.float64)
            state = self.adam.state.get(group["params"][0])
            if state:
                out[f"{name}.step"] = torch.as_tensor(state["step"]).detach().clone()
                for key in _MOMENTS:
                    out[f"{name}.{key}"] = state[key].detach().clone()
        return out

    def load_state_dict(self, state: Mapping[str, torch.Tensor]) -> None:
        """Restore :meth:`state_dict` output onto the map's current tensors (sizes must match)."""
        if "betas" in state:
            betas = tuple(float(b) for b in state["betas"].tolist())
            for group in self.adam.param_groups:
                group["betas"] = betas
            self.adam.defaults["betas"] = betas
        if "eps" in state:
            eps = float(state["eps"])
            for group in self.adam.param_groups:
                group["eps"] = eps
            self.adam.defaults["eps"] = eps
        for group in self.adam.param_groups:
            name = group["name"]
            param = group["params"][0]
            if f"{name}.lr" in state:
                group["lr"] = float(state[f"{name}.lr"])
            self.adam.state.pop(param, None)
            if f"{name}.step" not in state:
                continue
            # the fused Adam keeps its step count on the parameter's device
            step_device = param.device if self.adam.defaults.get("fused") else "cpu"
            restored = {"step": state[f"{name}.step"].detach().clone().to(dtype=torch.float32, device=step_device)}
            for key in _MOMENTS:
                value = state[f"{name}.{key}"]
                if tuple(value.shape) != tuple(param.shape):
                    raise MipslamError(
                        f"optimizer state '{name}.{key}' has shape {tuple(value.shape)}, the map's '{name}' has "
                        f"{tuple(param.shape)}; load the map and the optimizer from the same checkpoint"
                    )
                restored[key] = value.detach().to(device=param.device, dtype=param.dtype).clone()
            self.adam.state[param] = restored
