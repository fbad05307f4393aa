"""The appearance colour image (``appearance_color``): the colour again, whose gradient reaches the Gaussians'
colours alone, on both backends; and the mapping loss that scores it with the frequency loss
(``mapping.freq_moves_geometry``)."""
from __future__ import annotations

import pytest
import torch

from mipslam.mapping import MappingOptions
from mipslam.config import RenderConfig
from mipslam.render import cpu as cpu_backend
from mipslam.render import rasterize
from test_render_cpu import camera, mixed_scene

W, H, FOCAL = 40, 30, 36.0
BACKENDS = ["torch", pytest.param("cpu", marks=pytest.mark.skipif(
    not cpu_backend.is_available(), reason="the cpu backend is not built here"))]


def _inputs(dtype):
    scene = [t.to(dtype) for t in mixed_scene(150, W, H, FOCAL, seed=3)]
    viewmat, K = camera(W, H, FOCAL, dtype)
    return [t.clone().requires_grad_() for t in scene] + [viewmat.clone().requires_grad_()], K


def _weights(shape, seed, dtype):
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)).to(dtype)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", ["eaa", "mip"])
def test_appearance_image_equals_the_colour_and_moves_only_the_colours(backend, mode):
    dtype = torch.float32 if backend == "cpu" else torch.float64
    inputs, K = _inputs(dtype)
    out = rasterize(*inputs, K, W, H, mode=mode, backend=backend, appearance_color=True)
    assert torch.equal(out.color_appearance, out.color)
    (out.color_appearance * _weights(out.color.shape, 1, dtype)).sum().backward()
    for name, t in zip(("means", "quats", "scales", "opacities"), inputs[:4]):
        assert t.grad is None or not t.grad.any(), name
    assert inputs[5].grad is None or not inputs[5].grad.any(), "viewmat"
    assert inputs[4].grad.abs().sum() > 0

    # the colours' gradient is that of the colour image rendered with the geometry and the camera held fixed
    fixed = [t.detach() for t in inputs[:4]] + [inputs[4].detach().clone().requires_grad_(), inputs[5].detach()]
    reference = rasterize(*fixed, K, W, H, mode=mode, backend=backend)
    (reference.color * _weights(reference.color.shape, 1, dtype)).sum().backward()
    torch.testing.assert_close(inputs[4].grad, fixed[4].grad, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_loss_on_both_images_splits_its_gradient(backend):
    """Geometry and camera take the loss on ``color`` alone; the colours take both."""
    dtype = torch.float32 if backend == "cpu" else torch.float64
    inputs, K = _inputs(dtype)
    out = rasterize(*inputs, K, W, H, mode="eaa", backend=backend, appearance_color=True)
    loss = ((out.color * _weights(out.color.shape, 1, dtype)).sum() + (out.depth ** 2).sum()
            + 3.0 * (out.color_appearance * _weights(out.color.shape, 2, dtype)).sum())
    loss.backward()

    plain, _ = _inputs(dtype)
    out_p = rasterize(*plain, K, W, H, mode="eaa", backend=backend)
    ((out_p.color * _weights(out_p.color.shape, 1, dtype)).sum() + (out_p.depth ** 2).sum()).backward()
    for name, a, b in zip(("means", "quats", "scales", "opacities", "viewmat"), inputs[:4] + inputs[5:],
                          plain[:4] + plain[5:]):
        assert torch.equal(a.grad, b.grad), name  # the same arithmetic: the appearance image adds nothing here
    colours_only, _ = _inputs(dtype)
    out_c = rasterize(*[t.detach() for t in colours_only[:4]], colours_only[4], colours_only[5].detach(), K, W, H,
                      mode="eaa", backend=backend)
    (3.0 * (out_c.color * _weights(out_c.color.shape, 2, dtype)).sum()).backward()
    torch.testing.assert_close(inputs[4].grad, plain[4].grad + colours_only[4].grad, rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not cpu_backend.is_available(), reason="the cpu backend is not built here")
def test_cpu_and_torch_appearance_gradients_agree():
    grads = {}
    for backend in ("torch", "cpu"):
        inputs, K = _inputs(torch.float32)
        out = rasterize(*inputs, K, W, H, mode="eaa", backend=backend, appearance_color=True)
        ((out.color * _weights(out.color.shape, 1, torch.float32)).sum()
         + (out.color_appearance * _weights(out.color.shape, 2, torch.float32)).sum()).backward()
        grads[backend] = [t.grad for t in inputs]
    for a, b in zip(grads["torch"], grads["cpu"]):
        torch.testing.assert_close(a, b, rtol=2e-3, atol=2e-4)


def test_without_the_option_there_is_no_appearance_image():
    inputs, K = _inputs(torch.float64)
    assert rasterize(*inputs, K, W, H, backend="torch").color_appearance is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_frequency_loss_moves_the_geometry_only_when_configured(backend, tiny_mapping_view):
    """Where ``mapping.freq_moves_geometry`` keeps it to the colours, the means, shapes, opacities and the keyframe
    pose get exactly the gradient of the loss without the frequency term; where it lets it move them, more."""
    from mipslam.mapping import Mapper

    gmap, view, T_cw = tiny_mapping_view
    render = RenderConfig(backend=backend)

    def gradients(lambda_freq, when):
        mapper = Mapper(MappingOptions(lambda_freq=lambda_freq, freq_moves_geometry=when), render)
        for t in gmap.parameters().values():
            t.grad = None
        pose = T_cw.clone().requires_grad_()
        mapper.view_loss(gmap, view, pose).backward()
        return {name: t.grad.clone() for name, t in gmap.parameters().items()}, pose.grad.clone()

    base = gradients(0.0, "final")
    kept = [gradients(1000.0, "final")]
    moved = [gradients(1000.0, "always")]
    for grads, pose in kept:
        for name in ("means", "quats_wxyz", "log_scales", "opacity_logits"):
            assert torch.equal(grads[name], base[0][name]), name
        assert torch.equal(pose, base[1])
        assert not torch.equal(grads["colors_raw"], base[0]["colors_raw"])
    for grads, pose in moved:
        for name in ("means", "quats_wxyz", "log_scales", "opacity_logits"):
            assert not torch.equal(grads[name], base[0][name]), name
        assert not torch.equal(pose, base[1])
    torch.testing.assert_close(kept[0][0]["colors_raw"], moved[0][0]["colors_raw"], rtol=1e-5, atol=1e-7)


@pytest.fixture
def tiny_mapping_view():
    """A 40x30 view of 150 Gaussians with a target that differs from the render (so every term has a gradient)."""
    from mipslam.gaussians import GaussianMap, GaussianParameters
    from mipslam.mapping import MappingView
    from mipslam.types import Intrinsics

    means, quats, scales, opacities, colors = mixed_scene(150, W, H, FOCAL, seed=5)
    gmap = GaussianMap(GaussianParameters.from_activated(means, quats, scales, opacities, colors))
    g = torch.Generator().manual_seed(9)
    intrinsics = Intrinsics(fx=FOCAL, fy=FOCAL, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
    view = MappingView(keyframe_id=1, color=torch.rand(H, W, 3, generator=g), depth=1.5 + torch.rand(H, W, generator=g),
                       T_wc=torch.eye(4, dtype=torch.float64), exposure=torch.tensor([1.0, 0.0]),
                       intrinsics=intrinsics, optimize_pose=True)
    return gmap, view, torch.eye(4)


def test_the_config_refuses_an_unknown_target():
    from mipslam.config import config_from_dict
    from mipslam.errors import ConfigError

    with pytest.raises(ConfigError, match="freq_moves_geometry"):
        config_from_dict({"mapping": {"freq_moves_geometry": "sometimes"}})


def test_the_frequency_loss_moves_the_geometry_by_default_and_on_real_cameras_only_at_the_end():
    from mipslam.config import load_config

    assert MappingOptions().freq_moves_geometry == "always"
    assert load_config("tum", preset="balanced").mapping.freq_moves_geometry == "final"


def test_the_torch_reference_gives_the_same_appearance_gradient_when_it_recomputes_its_batches():
    grads = []
    for checkpoint in (False, True):
        inputs, K = _inputs(torch.float64)
        out = rasterize(*inputs, K, W, H, mode="eaa", backend="torch", appearance_color=True, checkpoint=checkpoint)
        ((out.color * _weights(out.color.shape, 1, torch.float64)).sum()
         + (out.color_appearance * _weights(out.color.shape, 2, torch.float64)).sum()).backward()
        grads.append([t.grad for t in inputs])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
