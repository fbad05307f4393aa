"""Local frequency-domain perceptual loss (mipslam.losses.frequency), against docs/design.md's definition."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mipslam.losses.frequency import frequency_loss, frequency_loss_reference, hann_window_2d, image_to_patches


def _images(height: int, width: int, channels: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    rendered = torch.rand(height, width, channels, generator=generator)
    target = torch.rand(height, width, channels, generator=generator)
    return rendered, target


def _reference_loss(rendered: np.ndarray, target: np.ndarray, patch: int, alpha: float, mask=None) -> float:
    """Direct, loop-and-sum float64 implementation of docs/design.md's formula (no FFT, no vectorised tiling)."""
    rendered = rendered.astype(np.float64)
    target = target.astype(np.float64)
    if mask is not None:
        rendered = rendered * mask[..., None]
        target = target * mask[..., None]
    height, width, channels = rendered.shape
    rows, cols = math.ceil(height / patch), math.ceil(width / patch)
    window_1d = np.array([math.sin(math.pi * (n + 0.5) / patch) ** 2 for n in range(patch)])
    m = np.arange(patch)
    # explicit DFT sum: F[k, l] = 1/P sum_{m, n} x[m, n] exp(-2 pi i (k m + l n) / P)
    phase = np.exp(-2j * np.pi * (m[:, None, None, None] * m[None, None, :, None] + m[None, :, None, None] * m[None, None, None, :]) / patch)
    # phase[k, l, m, n]
    terms = []
    for row in range(rows):
        for col in range(cols):
            for channel in range(channels):
                spectra = []
                for image in (rendered, target):
                    x = np.zeros((patch, patch))
                    for i in range(patch):
                        for j in range(patch):
                            y, u = row * patch + i, col * patch + j
                            if y < height and u < width:
                                x[i, j] = image[y, u, channel] * window_1d[i] * window_1d[j]
                    spectra.append((phase * x[None, None]).sum(axis=(2, 3)) / patch)
                distance = np.abs(spectra[0] - spectra[1])
                peak = distance.max()
                weight = (distance / peak) ** alpha if peak > 0 else np.zeros_like(distance)
                terms.append(weight * distance**2)
    return float(np.mean(terms))


def test_zero_on_identical_images():
    rendered, _ = _images(20, 24)
    assert frequency_loss(rendered, rendered.clone(), patch_size=8).item() == 0.0


def test_window_is_symmetric_positive_hann_at_pixel_centres():
    window = hann_window_2d(8, dtype=torch.float64)
    assert torch.allclose(window, window.T) and torch.allclose(window, window.flip(0))
    assert window.min() > 0
    h = torch.sin(math.pi * (torch.arange(8, dtype=torch.float64) + 0.5) / 8) ** 2
    assert torch.allclose(window[3], h[3] * h)
    # sin^2 samples at pixel centres of one period sum to P/2
    assert h.sum().item() == pytest.approx(4.0)


@pytest.mark.parametrize("height,width,patch,alpha", [(8, 16, 8, 1.0), (11, 13, 4, 2.0), (6, 6, 4, 0.5)])
def test_matches_direct_dft_reference(height, width, patch, alpha):
    rendered, target = _images(height, width, seed=height)
    value = frequency_loss(rendered.double(), target.double(), patch_size=patch, alpha=alpha).item()
    reference = _reference_loss(rendered.numpy(), target.numpy(), patch, alpha)
    assert value == pytest.approx(reference, rel=1e-10, abs=1e-14)
    value32 = frequency_loss(rendered, target, patch_size=patch, alpha=alpha).item()
    assert value32 == pytest.approx(reference, rel=1e-4)


def test_mask_matches_reference_and_ignores_garbage_under_mask():
    rendered, target = _images(8, 12, seed=5)
    mask = torch.ones(8, 12, dtype=torch.bool)
    mask[2:5, 3:9] = False
    reference = _reference_loss(rendered.numpy(), target.numpy(), 4, 1.0, mask=mask.numpy())
    garbage = rendered.clone()
    garbage[~mask] = float("nan")
    garbage.requires_grad_(True)
    value = frequency_loss(garbage.double(), target.double(), patch_size=4, mask=mask)
    assert value.item() == pytest.approx(reference, rel=1e-10)
    value.backward()
    assert torch.isfinite(garbage.grad).all()
    assert garbage.grad[~mask].abs().max() == 0.0


def test_padding_equals_masking_of_a_larger_image():
    # a 10x14 image is padded to 12x16 with 4x4 patches; the same as a 12x16 image whose extra pixels are masked
    rendered, target = _images(12, 16, seed=7)
    mask = torch.zeros(12, 16, dtype=torch.bool)
    mask[:10, :14] = True
    padded = frequency_loss(rendered[:10, :14], target[:10, :14], patch_size=4)
    masked = frequency_loss(rendered, target, patch_size=4, mask=mask)
    assert padded.item() == pytest.approx(masked.item(), rel=1e-6)
    assert image_to_patches(rendered[:10, :14], 4).shape == (3 * 4, 3, 4, 4)


def test_finite_gradients_on_constant_and_black_patches():
    rendered = torch.zeros(16, 16, 3)
    target = torch.zeros(16, 16, 3)
    rendered[:8, 8:] = 0.5  # a constant patch that differs only at DC
    target[:8, 8:] = 0.5
    target[8:, :8] = 0.25  # constant target patch against black rendered patch
    rendered.requires_grad_(True)
    loss = frequency_loss(rendered, target, patch_size=8)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() > 0
    assert torch.isfinite(rendered.grad).all()
    assert rendered.grad[:8, :8].abs().max() == 0.0  # identical black patches: weight 0, no gradient
    assert rendered.grad[:8, 8:].abs().max() == 0.0  # identical constant patches
    assert rendered.grad[8:, :8].abs().max() > 0  # the differing patch is pulled towards the target
    assert (rendered.grad[8:, :8] <= 0).all()  # ... upwards (rendered is darker)
    # all-black against all-black, with every alpha including 0
    for alpha in (0.0, 1.0, 3.0):
        black = torch.zeros(8, 8, 3, requires_grad=True)
        value = frequency_loss(black, torch.zeros(8, 8, 3), patch_size=4, alpha=alpha)
        value.backward()
        assert value.item() == 0.0 and torch.isfinite(black.grad).all()


def test_invariant_to_moving_image_and_target_by_whole_patches():
    rendered, target = _images(16, 24, seed=3)
    base = frequency_loss(rendered, target, patch_size=8).item()
    for shift in ((8, 0), (0, 16), (8, 8), (-8, 16)):
        moved = frequency_loss(
            torch.roll(rendered, shifts=shift, dims=(0, 1)), torch.roll(target, shifts=shift, dims=(0, 1)), patch_size=8
        ).item()
        assert moved == pytest.approx(base, rel=1e-6)
    # a shift by a non-multiple of P changes the tiling, hence (generically) the loss
    off = frequency_loss(torch.roll(rendered, 3, 1), torch.roll(target, 3, 1), patch_size=8).item()
    assert abs(off - base) > 1e-4 * base


def test_gradient_step_reduces_the_loss():
    rendered, target = _images(16, 16, seed=11)
    rendered.requires_grad_(True)
    loss = frequency_loss(rendered, target, patch_size=8, alpha=1.0)
    loss.backward()
    with torch.no_grad():
        stepped = rendered - 0.5 * rendered.grad / rendered.grad.abs().max() * 0.1
    assert frequency_loss(stepped, target, patch_size=8).item() < loss.item()


def test_focal_weight_emphasises_hard_frequencies():
    # same total error energy: alpha > 0 weights a concentrated error relative to a spread one
    target = torch.zeros(8, 8, 1)
    spike = target.clone()
    spike[3, 4, 0] = 1.0
    flat = frequency_loss(spike, target, patch_size=8, alpha=0.0).item()  # w = 1 for every frequency
    focal = frequency_loss(spike, target, patch_size=8, alpha=2.0).item()
    # a single pixel has a flat power spectrum: |F|^2 = (W[3,4])^2 / 64 everywhere, so the focal weights are all 1
    assert focal == pytest.approx(flat, rel=1e-6)
    window = hann_window_2d(8, dtype=torch.float64)
    assert flat == pytest.approx(window[3, 4].item() ** 2 / 64, rel=1e-6)
    sinus = target.clone()
    sinus[..., 0] = 0.5 * torch.cos(2 * math.pi * torch.arange(8.0) / 4)[None, :]
    assert frequency_loss(sinus, target, patch_size=8, alpha=2.0).item() < frequency_loss(sinus, target, patch_size=8, alpha=0.0).item()


def test_grayscale_and_bad_inputs():
    rendered, target = _images(8, 8, channels=1)
    assert frequency_loss(rendered[..., 0], target[..., 0], patch_size=4).item() == pytest.approx(
        frequency_loss(rendered, target, patch_size=4).item()
    )
    with pytest.raises(ValueError):
        frequency_loss(rendered, target[:4], patch_size=4)
    with pytest.raises(ValueError):
        frequency_loss(rendered, target, patch_size=1)


@pytest.mark.parametrize("shape,patch,alpha,dtype", [
    ((20, 27, 3), 4, 1.0, torch.float64),  # padded on both sides
    ((13, 11, 1), 5, 2.0, torch.float64),  # odd patch: the half spectrum has no Nyquist column
    ((13, 11), 6, 0.0, torch.float64),  # grayscale [H, W]
    ((48, 64, 3), 16, 1.0, torch.float32),  # the mapping setting
])
def test_half_spectrum_backward_equals_autograd_reference(shape, patch, alpha, dtype):
    """The fast loss (rfft2 and a closed-form backward) equals the full-spectrum autograd reference: values
    and gradients with respect to both images, with a mask."""
    generator = torch.Generator().manual_seed(sum(shape))
    rendered = torch.rand(*shape, generator=generator, dtype=dtype, requires_grad=True)
    target = torch.rand(*shape, generator=generator, dtype=dtype, requires_grad=True)
    mask = torch.rand(shape[:2], generator=generator) > 0.2
    fast = frequency_loss(rendered, target, patch_size=patch, alpha=alpha, mask=mask)
    reference = frequency_loss_reference(rendered, target, patch_size=patch, alpha=alpha, mask=mask)
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    assert fast.item() == pytest.approx(reference.item(), rel=tolerance)
    fast_grads = torch.autograd.grad(fast, (rendered, target))
    reference_grads = torch.autograd.grad(reference, (rendered, target))
    for got, want in zip(fast_grads, reference_grads):
        assert want.abs().max() > 0
        assert (got - want).abs().max() <= tolerance * want.abs().max()
        assert got[~mask].abs().max() == 0.0
