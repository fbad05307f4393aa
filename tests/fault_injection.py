"""Fault injection for tests and benchmarks of loop closure (hooks of :class:`mipslam.pipeline.PipelineHooks`).

* :class:`BiasedOdometer` makes a run drift in a controlled way: each frame's pose becomes the
  previous estimate composed with the ground-truth relative motion and a constant bias,
  ``T_k = T_{k-1} (G_{k-1}^-1 G_k) Exp(b)`` (b a twist [rho, phi] in the camera frame). The
  tracker's own pose is discarded, as if tracking were a visual odometer with a systematic error;
  mapping, keyframe selection and loop closure then run on the drifting poses as usual. After a
  loop correction the odometer continues from the corrected estimate.
* :class:`WrongLoop` turns one verified loop into a wrong one: its measurement is composed with a
  fixed offset while it keeps its stated information and its "accepted" verdict, so only the
  pose graph's robustness (kernel and pruning) can stop it.

Nothing here is used in a normal run.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch

from mipslam.geometry import se3_exp, se3_inverse
from mipslam.loop.registration import RegistrationResult


@dataclass
class BiasedOdometer:
    """``after_tracking`` hook: ground-truth relative motion times a constant bias (module docstring).

    gt_T_wc: ground-truth poses of the sequence, indexed by frame index   # [N, 4, 4]
    bias: per-frame twist [rho (m), phi (rad)] applied on the right (camera frame)   # [6]
    """

    gt_T_wc: torch.Tensor
    bias: torch.Tensor

    def __call__(self, index: int, result, state):
        if not state.frames:
            return result  # the first frame defines the map's frame
        previous = state.frames[-1]
        G = self.gt_T_wc.to(torch.float64)
        motion = se3_inverse(G[previous.index]) @ G[index]
        T_wc = previous.T_wc.to(torch.float64) @ motion @ se3_exp(self.bias.to(torch.float64))
        return replace(result, T_wc=T_wc)


@dataclass
class WrongLoop:
    """``loop_verification`` hook: the ``nth`` accepted verification (0-based) gets a wrong measurement
    ``T_ij Exp(offset)`` (offset [6] = [rho (m), phi (rad)]); ``corrupted`` records its (i, j)."""

    offset: torch.Tensor
    nth: int = 0
    seen: int = 0
    corrupted: list[tuple[int, int]] = field(default_factory=list)

    def __call__(self, i: int, j: int, result: RegistrationResult) -> RegistrationResult:
        if not result.accepted:
            return result
        self.seen += 1
        if self.seen - 1 != self.nth:
            return result
        self.corrupted.append((i, j))
        return replace(result, T_ij=result.T_ij @ se3_exp(self.offset.to(torch.float64)))
