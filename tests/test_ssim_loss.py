"""The compiled SSIM loss (mipslam/render/cpu/ssim_loss.h through :func:`mipslam.losses.structural.ssim_loss`)
against its torch reference :func:`mipslam.losses.structural.ssim`: the value to float rounding, the analytic
gradient against autograd through the reference in float64, the target-moment cache, and the fallback to the
reference where the kernel cannot run."""
from __future__ import annotations

import gc

import pytest
import torch

from mipslam.errors import BackendUnavailableError
from mipslam.losses.structural import COMPILED_MAX_WINDOW, SSIMTargetCache, gaussian_window_1d, ssim, ssim_loss
from mipslam.render.cpu import build as cpu_build, library as cpu_library, profile_kernels

COMPILED = "_CompiledSSIMLossBackward"
C1, C2 = 0.01 ** 2, 0.03 ** 2


def _built_isas() -> list[str]:
    return [isa for isa in cpu_build.isas() if cpu_build.is_current(isa)]


@pytest.fixture(params=_built_isas() or [None], ids=lambda isa: isa or "unbuilt")
def compiled(request):
    """Each built library of this platform (baseline, avx2) in turn, as the one ssim_loss uses."""
    if request.param is None or cpu_library._disabled():
        pytest.skip("the compiled CPU library is not built here (python -m mipslam.render.cpu.build)")
    with cpu_library.using(cpu_library.load_library(request.param)) as library:
        yield library


@pytest.fixture
def disabled_library(monkeypatch):
    """The compiled library switched off (MIPSLAM_CPU_BACKEND=0); the loaded one is restored afterwards."""
    saved = dict(cpu_library._state)
    cpu_library._reset_for_tests()
    monkeypatch.setenv("MIPSLAM_CPU_BACKEND", "0")
    yield
    cpu_library._state.clear()
    cpu_library._state.update(saved)


def _images(height: int, width: int, channels: int, seed: int, dtype=torch.float32):
    """A target in [0, 1] and an image near it (noise, clamped, a few equal values)."""
    generator = torch.Generator().manual_seed(seed)
    target = torch.rand(height, width, channels, generator=generator)
    image = (target + 0.15 * torch.randn(target.shape, generator=generator)).clamp(0, 1)
    same = torch.rand(target.shape, generator=generator) < 0.1
    image[same] = target[same]
    return image.to(dtype), target.to(dtype)


def _reference(image: torch.Tensor, target: torch.Tensor, **window) -> tuple[float, torch.Tensor]:
    """1 - SSIM and its gradient with respect to the image, by autograd through the reference in float64."""
    x = image.detach().double().requires_grad_()
    loss = 1.0 - ssim(x, target.detach().double(), **window)
    loss.backward()
    return loss.item(), x.grad


def _assert_gradient_close(grad: torch.Tensor, reference: torch.Tensor) -> None:
    assert grad.shape == reference.shape and grad.dtype == torch.float32
    scale = reference.abs().max().item()
    assert (grad.double() - reference).abs().max().item() <= 2e-5 * scale + 1e-12


# sizes: smaller than the window (1x1, 3x5, 7x4), odd, no multiple of the 8 lanes, tall enough for several bands
@pytest.mark.parametrize("height,width,channels", [
    (1, 1, 1), (3, 5, 2), (7, 4, 3), (11, 11, 4), (16, 16, 3), (37, 29, 3), (29, 37, 1), (64, 23, 2), (53, 41, 4),
])
def test_compiled_loss_has_the_references_value_and_gradient(compiled, height, width, channels):
    image, target = _images(height, width, channels, seed=height * 100 + width + channels)
    x = image.clone().requires_grad_()
    loss = ssim_loss(x, target)
    assert type(loss.grad_fn).__name__ == COMPILED
    assert loss.shape == () and loss.dtype == torch.float32
    loss.backward()
    value, reference_grad = _reference(image, target)
    assert loss.item() == pytest.approx(value, abs=2e-6)
    assert loss.item() == pytest.approx((1.0 - ssim(image, target)).item(), abs=2e-6)  # the float32 reference
    _assert_gradient_close(x.grad, reference_grad)


@pytest.mark.parametrize("window_size,sigma,max_value", [(3, 0.8, 1.0), (7, 1.0, 1.0), (11, 1.5, 255.0), (31, 5.0, 1.0)])
def test_compiled_loss_with_other_windows_and_ranges(compiled, window_size, sigma, max_value):
    image, target = _images(26, 35, 3, seed=window_size)
    image, target = image * max_value, target * max_value
    settings = dict(window_size=window_size, sigma=sigma, max_value=max_value)
    x = image.clone().requires_grad_()
    loss = ssim_loss(x, target, **settings)
    assert type(loss.grad_fn).__name__ == COMPILED
    loss.backward()
    value, reference_grad = _reference(image, target, **settings)
    assert loss.item() == pytest.approx(value, abs=2e-6)
    _assert_gradient_close(x.grad, reference_grad)


def test_compiled_result_does_not_depend_on_the_thread_count(compiled):
    """The rows are cut into one band per thread, each recomputing its neighbours' border rows; the value adds the
    rows in order: the same bits on 1, 2 and 3 threads."""
    image, target = _images(97, 30, 3, seed=5)
    saved = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            x = image.clone().requires_grad_()
            loss = ssim_loss(x, target)
            loss.backward()
            results.append((loss.detach(), x.grad))
    finally:
        torch.set_num_threads(saved)
    for loss, grad in results[1:]:
        assert torch.equal(loss, results[0][0]) and torch.equal(grad, results[0][1])


def test_compiled_loss_of_non_contiguous_inputs(compiled):
    """Views (a channel slice of an RGBA render, a transposed target) give the contiguous copies' loss, and the
    gradient reaches the tensor they view."""
    base, target_t = _images(30, 21, 4, seed=11)
    rgba = base.clone().requires_grad_()
    target = target_t[..., :3].transpose(0, 1).contiguous().transpose(0, 1)  # [30, 21, 3] with swapped strides
    assert not target.is_contiguous()
    loss = ssim_loss(rgba[..., :3], target)
    assert type(loss.grad_fn).__name__ == COMPILED
    loss.backward()
    value, reference_grad = _reference(base[..., :3].contiguous(), target.contiguous())
    assert loss.item() == pytest.approx(value, abs=2e-6)
    _assert_gradient_close(rgba.grad[..., :3], reference_grad)
    assert torch.equal(rgba.grad[..., 3], torch.zeros(30, 21))


def test_compiled_loss_backward_scales_with_the_upstream_gradient_and_without_grad_gives_the_value(compiled):
    image, target = _images(20, 24, 3, seed=3)
    x = image.clone().requires_grad_()
    loss = ssim_loss(x, target)
    (0.25 * loss).backward(retain_graph=True)
    quarter = x.grad.clone()
    x.grad = None
    loss.backward()  # a second backward of the same graph: the saved gradient was not changed in place
    assert torch.allclose(quarter, 0.25 * x.grad, rtol=1e-6, atol=0)
    with torch.no_grad():
        value = ssim_loss(x, target)
    assert value.grad_fn is None and torch.equal(value, loss.detach())
    assert torch.equal(ssim_loss(image, target), loss.detach())  # an image that needs no gradient
    target_grad = target.clone().requires_grad_()
    assert torch.equal(ssim_loss(image, target_grad), loss.detach())  # the target is a constant
    assert ssim_loss(image, target_grad).grad_fn is None


def test_identical_images_have_zero_loss_and_a_nan_is_not_hidden(compiled):
    image, target = _images(18, 13, 3, seed=9)
    assert abs(ssim_loss(target, target).item()) < 1e-6
    image[4, 5, 1] = float("nan")
    assert torch.isnan(ssim_loss(image, target))


def test_target_moments_are_the_blurred_target_and_its_square(compiled):
    _, target = _images(19, 26, 2, seed=4)
    window = gaussian_window_1d(11, 1.5, dtype=torch.float32)
    moments = compiled.ssim_moments(target, window, threads=2)
    assert moments.shape == (2, 19, 26, 2)
    g = gaussian_window_1d(11, 1.5)
    kernel = (g[:, None] * g[None, :]).expand(2, 1, 11, 11)

    def blur(z):  # [H, W, C] float64 -> [H, W, C], zero padding
        return torch.nn.functional.conv2d(z.permute(2, 0, 1)[None], kernel, padding=5, groups=2)[0].permute(1, 2, 0)

    y = target.double()
    assert torch.allclose(moments[0].double(), blur(y), atol=2e-7, rtol=0)
    assert torch.allclose(moments[1].double(), blur(y * y), atol=2e-7, rtol=0)


def test_target_cache_gives_the_uncached_result_and_follows_its_targets(compiled):
    image, target = _images(33, 27, 3, seed=8)
    cache = SSIMTargetCache(max_entries=2)
    x = image.clone().requires_grad_()
    uncached = ssim_loss(x, target)
    uncached.backward()
    grad = x.grad.clone()
    for _ in range(3):
        x.grad = None
        cached = ssim_loss(x, target, cache=cache)
        cached.backward()
        assert torch.equal(cached.detach(), uncached.detach()) and torch.equal(x.grad, grad)
    assert (cache.misses, cache.hits, len(cache)) == (1, 2, 1)
    # an in-place change of the target recomputes its moments
    target[:5] = 0.5
    changed = ssim_loss(image, target, cache=cache)
    assert cache.misses == 2 and torch.equal(changed, ssim_loss(image, target))
    # another window is another entry's worth of moments; least recently used entries go first
    assert torch.equal(ssim_loss(image, target, window_size=7, cache=cache), ssim_loss(image, target, window_size=7))
    assert cache.misses == 3
    others = [_images(33, 27, 3, seed=20 + k)[1] for k in range(3)]
    for other in others:
        ssim_loss(image, other, cache=cache)
    assert len(cache) == 2
    # an entry goes with its target
    del others, other
    gc.collect()
    assert len(cache) == 0


def test_kernel_profiling_sees_the_calls(compiled):
    image, target = _images(12, 10, 3, seed=12)
    cache = SSIMTargetCache()
    with profile_kernels() as kernels:
        ssim_loss(image.clone().requires_grad_(), target, cache=cache).backward()
        ssim_loss(image, target, cache=cache)
    assert kernels.calls == {"ssim_moments": 1, "ssim": 2}


def test_reference_loss_passes_gradcheck_in_float64():
    image, target = _images(6, 5, 2, seed=1, dtype=torch.float64)
    x = image.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda z: ssim_loss(z, target), (x,), eps=1e-6, atol=1e-7)
    y = target.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: ssim(a, b), (x, y), eps=1e-6, atol=1e-7)


def test_torch_fallback_where_the_kernel_cannot_run():
    """float64, a batch, a window over the kernel's limit and backend="torch" take the reference."""
    image, target = _images(12, 15, 3, seed=2)
    for x, y, settings in ((image.double(), target.double(), {}), (torch.stack([image, target]), torch.stack([target, image]), {}),
                           (image, target, {"window_size": COMPILED_MAX_WINDOW + 2, "sigma": 6.0}),
                           (image, target, {"backend": "torch"})):
        x = x.clone().requires_grad_()
        loss = ssim_loss(x, y, **settings)
        assert type(loss.grad_fn).__name__ != COMPILED and loss.shape == ()
        window = {k: v for k, v in settings.items() if k != "backend"}
        assert torch.equal(loss, 1.0 - ssim(x, y, **window).mean())
    if torch.cuda.is_available():
        loss = ssim_loss(image.cuda().requires_grad_(), target.cuda())
        assert loss.device.type == "cuda" and type(loss.grad_fn).__name__ != COMPILED


def test_torch_fallback_when_the_library_is_disabled(disabled_library):
    image, target = _images(16, 20, 3, seed=6)
    x = image.clone().requires_grad_()
    loss = ssim_loss(x, target, cache=SSIMTargetCache())
    assert type(loss.grad_fn).__name__ != COMPILED
    loss.backward()
    value, reference_grad = _reference(image, target)
    assert loss.item() == pytest.approx(value, abs=2e-6)
    _assert_gradient_close(x.grad, reference_grad)
    with pytest.raises(BackendUnavailableError, match="compiled"):
        ssim_loss(image, target, backend="cpu")


def test_bad_arguments_are_refused():
    image, target = _images(8, 9, 3, seed=0)
    with pytest.raises(ValueError, match="share a shape"):
        ssim_loss(image, target[:, :8])
    with pytest.raises(ValueError, match="odd"):
        ssim_loss(image, target, window_size=10)
    with pytest.raises(ValueError, match="backend"):
        ssim_loss(image, target, backend="gpu")
    with pytest.raises(ValueError, match="max_entries"):
        SSIMTargetCache(max_entries=0)


def test_library_checks_what_the_kernel_trusts(compiled):
    image, target = _images(8, 9, 3, seed=0)
    window = gaussian_window_1d(11, 1.5, dtype=torch.float32)
    with pytest.raises(RuntimeError, match="image"):
        compiled.ssim(image.double(), target, None, window, C1, C2, gradients=False)
    with pytest.raises(RuntimeError, match="target_moments"):
        compiled.ssim(image, target, torch.zeros(2, 8, 9, 2), window, C1, C2, gradients=False)
    with pytest.raises(RuntimeError, match="window taps"):
        compiled.ssim(image, target, None, torch.ones(4) / 4, C1, C2, gradients=False)
    with pytest.raises(RuntimeError, match="not symmetric"):
        compiled.ssim(image, target, None, torch.tensor([0.2, 0.5, 0.3]), C1, C2, gradients=False)
    with pytest.raises(RuntimeError, match="not symmetric"):
        compiled.ssim_moments(target, torch.tensor([0.2, 0.5, 0.3]))
