"""Global image descriptors for loop-candidate retrieval, and candidate selection.

The descriptor of a colour image [H, W, 3] concatenates three parts, each centred and
L2-normalised, then scaled by the square root of its weight (weights sum to 1):

* frequency part: ``log(1 + |F|)`` of the 2D FFT of the Hann-windowed, mean-removed grey image
  area-downsampled to ``fft_size`` x ``fft_size``; only the lowest ``fft_keep`` frequencies per
  axis are kept (half plane: the magnitude of a real image's spectrum is point-symmetric). The
  magnitude ignores where things are in the frame, so small viewpoint shifts barely change it;
* gradient part: histograms of gradient orientation (``orientation_bins`` signed bins,
  magnitude-weighted) on a ``grid`` x ``grid`` layout of cells, square-rooted (Hellinger);
* colour part: per-channel mean and standard deviation and a ``colour_bins``-bin histogram per
  channel, square-rooted.

The similarity of two descriptors is their dot product, i.e. the weighted sum of the parts'
Pearson correlations, in [-1, 1]. Candidates for a query keyframe are older keyframes (at least
``min_gap`` keyframes back) that are near in the current pose estimate and whose similarity
beats both an absolute floor and the query's similarity to its own recent neighbours (scaled by
``reference_ratio``), the test ORB-SLAM applies with its covisible keyframes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

_GREY = (0.299, 0.587, 0.114)


@dataclass(frozen=True)
class DescriptorOptions:
    """Layout and weights of :func:`global_descriptor` (weights are normalised to sum to 1)."""

    fft_size: int = 32
    fft_keep: int = 8
    orientation_bins: int = 8
    grid: int = 2
    gradient_size: int = 64
    colour_bins: int = 8
    weight_frequency: float = 0.4
    weight_gradient: float = 0.3
    weight_colour: float = 0.3

    def __post_init__(self):
        if self.fft_keep < 1 or self.fft_keep > self.fft_size // 2:
            raise ValueError(f"fft_keep must lie in [1, fft_size/2], got {self.fft_keep} for fft_size {self.fft_size}")
        if min(self.weight_frequency, self.weight_gradient, self.weight_colour) < 0 or \
                self.weight_frequency + self.weight_gradient + self.weight_colour <= 0:
            raise ValueError("descriptor weights must be >= 0 and not all zero")

    @property
    def dimension(self) -> int:
        fft = (2 * self.fft_keep + 1) * (self.fft_keep + 1)
        return fft + self.grid * self.grid * self.orientation_bins + 6 + 3 * self.colour_bins


def _normalised_part(v: torch.Tensor, weight: float) -> torch.Tensor:
    """Centre, L2-normalise, scale by sqrt(weight).  v [D] -> [D] (zeros when v is constant)."""
    v = v - v.mean()
    norm = v.norm()
    if float(norm) <= 1e-12:
        return torch.zeros_like(v)
    return v / norm * math.sqrt(weight)


def _frequency_part(grey: torch.Tensor, size: int, keep: int) -> torch.Tensor:
    """log(1 + |FFT|) of the windowed small grey image, lowest ``keep`` frequencies.  grey [H, W] -> [(2k+1)(k+1)]"""
    small = F.adaptive_avg_pool2d(grey[None, None], (size, size))[0, 0]
    small = small - small.mean()
    hann = torch.hann_window(size + 2, periodic=False, dtype=grey.dtype, device=grey.device)[1:-1]
    spectrum = torch.fft.rfft2(small * hann[:, None] * hann[None, :], norm="ortho")  # [S, S/2+1]
    rows = torch.cat([torch.arange(0, keep + 1), torch.arange(size - keep, size)]).to(grey.device)
    block = spectrum[rows][:, : keep + 1]
    return torch.log1p(block.abs()).reshape(-1)


def _gradient_part(grey: torch.Tensor, size: int, bins: int, grid: int) -> torch.Tensor:
    """Magnitude-weighted signed orientation histograms on a grid x grid layout.  grey [H, W] -> [grid^2 * bins]"""
    small = F.adaptive_avg_pool2d(grey[None, None], (size, size))[0, 0]
    gx = torch.zeros_like(small)
    gy = torch.zeros_like(small)
    gx[:, 1:-1] = 0.5 * (small[:, 2:] - small[:, :-2])
    gy[1:-1, :] = 0.5 * (small[2:, :] - small[:-2, :])
    magnitude = torch.sqrt(gx * gx + gy * gy)
    angle = torch.atan2(gy, gx)  # (-pi, pi]
    bin_index = ((angle + math.pi) / (2 * math.pi) * bins).long().clamp(0, bins - 1)
    cell_v = (torch.arange(size, device=grey.device) * grid // size)[:, None].expand(size, size)
    cell_u = (torch.arange(size, device=grey.device) * grid // size)[None, :].expand(size, size)
    flat = ((cell_v * grid + cell_u) * bins + bin_index).reshape(-1)
    hist = torch.zeros(grid * grid * bins, dtype=grey.dtype, device=grey.device)
    hist.index_add_(0, flat, magnitude.reshape(-1))
    return torch.sqrt(hist / hist.sum().clamp_min(1e-12))


def _colour_part(color: torch.Tensor, bins: int) -> torch.Tensor:
    """Per-channel mean, std and sqrt-normalised histograms.  color [H, W, 3] -> [6 + 3 * bins]"""
    pixels = color.reshape(-1, 3)
    index = (pixels.clamp(0, 1) * bins).long().clamp(0, bins - 1) + torch.arange(3, device=color.device) * bins
    hist = torch.zeros(3 * bins, dtype=color.dtype, device=color.device)
    hist.index_add_(0, index.reshape(-1), torch.ones(index.numel(), dtype=color.dtype, device=color.device))
    hist = torch.sqrt(hist / pixels.shape[0])
    return torch.cat([pixels.mean(0), pixels.std(0, unbiased=False), hist])


def global_descriptor(color: torch.Tensor, options: DescriptorOptions = DescriptorOptions()) -> torch.Tensor:
    """Unit-norm global descriptor of a colour image (module docstring).

    color: float in [0, 1], [H, W, 3] -> descriptor [D] float32 (D = ``options.dimension``), same device.
    """
    if color.dim() != 3 or color.shape[-1] != 3:
        raise ValueError(f"global_descriptor expects a colour image [H, W, 3], got {tuple(color.shape)}")
    color = color.to(torch.float32)
    grey = color @ torch.tensor(_GREY, dtype=color.dtype, device=color.device)  # [H, W]
    total = options.weight_frequency + options.weight_gradient + options.weight_colour
    parts = [
        _normalised_part(_frequency_part(grey, options.fft_size, options.fft_keep), options.weight_frequency / total),
        _normalised_part(_gradient_part(grey, options.gradient_size, options.orientation_bins, options.grid),
                         options.weight_gradient / total),
        _normalised_part(_colour_part(color, options.colour_bins), options.weight_colour / total),
    ]
    return torch.cat(parts)


def descriptor_similarity(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Weighted sum of the parts' correlations, in [-1, 1].  a [..., D], b [..., D] -> [...] (broadcasts)"""
    return (a * b).sum(-1)


@dataclass(frozen=True)
class CandidateOptions:
    """Rules of :func:`select_loop_candidates`.

    min_gap: candidates are at least this many keyframes older than the query.
    max_distance_m / max_view_angle_deg: pose proximity in the current estimate (None: no limit);
        keep them generous, the estimate has drifted by the time a loop is needed.
    min_similarity: absolute floor; reference_window / reference_ratio: the score must also reach
        ratio x the lowest similarity between the query and its ``reference_window`` predecessors.
    suppress_radius: of candidates closer than this (in keyframes) only the most similar is kept.
    """

    min_gap: int = 10
    max_distance_m: float | None = 2.0
    max_view_angle_deg: float | None = 60.0
    min_similarity: float = 0.5
    reference_window: int = 3
    reference_ratio: float = 0.9
    suppress_radius: int = 3
    max_candidates: int = 3


@dataclass(frozen=True)
class LoopCandidate:
    """An older keyframe that may close a loop with the query keyframe."""

    keyframe: int
    similarity: float
    distance_m: float
    view_angle_deg: float


def select_loop_candidates(
    query: int,
    descriptors: torch.Tensor,
    poses: torch.Tensor,
    options: CandidateOptions = CandidateOptions(),
) -> tuple[LoopCandidate, ...]:
    """Loop candidates for keyframe ``query`` among the keyframes before it, most similar first.

    descriptors: of every keyframe so far (row k = keyframe k)       # [N, D]
    poses: current estimates T_wc of the same keyframes               # [N, 4, 4]
    """
    n = descriptors.shape[0]
    if not 0 <= query < n or poses.shape[0] != n:
        raise ValueError(f"query keyframe {query} outside [0, {n}) or poses/descriptors disagree ({poses.shape[0]} vs {n})")
    last = query - options.min_gap
    if last < 0:
        return ()
    similarity = descriptor_similarity(descriptors[: last + 1], descriptors[query][None])  # [M]
    T = poses.to(torch.float64)
    distance = (T[: last + 1, :3, 3] - T[query, :3, 3]).norm(dim=-1)
    cos_angle = (T[: last + 1, :3, 2] * T[query, :3, 2]).sum(-1).clamp(-1, 1)  # optical axes (camera z)
    angle = torch.rad2deg(torch.acos(cos_angle))

    threshold = options.min_similarity
    if options.reference_window > 0 and query > 0:
        neighbours = descriptors[max(0, query - options.reference_window): query]
        threshold = max(threshold, options.reference_ratio * float(descriptor_similarity(neighbours, descriptors[query][None]).min()))
    ok = similarity >= threshold
    if options.max_distance_m is not None:
        ok &= distance <= options.max_distance_m
    if options.max_view_angle_deg is not None:
        ok &= angle <= options.max_view_angle_deg

    chosen: list[LoopCandidate] = []
    for k in torch.argsort(similarity, descending=True).tolist():
        if not bool(ok[k]):
            continue
        if any(abs(k - c.keyframe) <= options.suppress_radius for c in chosen):
            continue
        chosen.append(LoopCandidate(int(k), float(similarity[k]), float(distance[k]), float(angle[k])))
        if len(chosen) >= options.max_candidates:
            break
    return tuple(chosen)
