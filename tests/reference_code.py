"""The authors' code (../shared/reference/warped-skipconnection-nvs), imported for the fidelity tests only.

It runs on this CPU with the stubs its README describes, made at import time and undone afterwards:
``torchvision.models.vgg16`` returns a module of VGG16's ``features`` layers holding the ImageNet weights nvs
ships, ``cv2`` is an empty module (used only by visualisation helpers), and ``Tensor.cuda`` is the identity while
a KITTI model is built (its intrinsics call ``.cuda()``). Nothing of it is copied into nvs.
"""

from __future__ import annotations

import contextlib
import sys
import types
from pathlib import Path
from types import SimpleNamespace

import torch
import torch.nn as nn

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "warped-skipconnection-nvs"
_TOP_LEVEL = ("models", "util", "data", "options", "torchvision", "cv2")


def available() -> bool:
    return (REFERENCE / "models" / "base_model.py").is_file()


def _vgg16_features() -> nn.Sequential:
    """torchvision's VGG16 ``features`` layout (conv, ReLU ..., max-pool after each block) with nvs's weights."""
    from nvs.models.vgg import load_weights

    w = load_weights()
    layers, i = [], 0
    for n_convs in (2, 2, 3, 3, 3):
        for _ in range(n_convs):
            conv = nn.Conv2d(w["weight"][i].shape[1], w["weight"][i].shape[0], 3, padding=1)
            conv.weight.data.copy_(torch.from_numpy(w["weight"][i].copy()))
            conv.bias.data.copy_(torch.from_numpy(w["bias"][i].copy()))
            layers += [conv, nn.ReLU(inplace=True)]
            i += 1
        layers.append(nn.MaxPool2d(2, 2))
    return nn.Sequential(*layers)


@contextlib.contextmanager
def imported():
    """Yields (networks, base_model) modules of the reference code; sys.path and sys.modules are restored after."""
    saved = {k: v for k, v in sys.modules.items() if k.split(".")[0] in _TOP_LEVEL}
    for k in saved:
        del sys.modules[k]
    tv = types.ModuleType("torchvision")
    tv.models = types.SimpleNamespace(vgg16=lambda pretrained=True: SimpleNamespace(features=_vgg16_features()))
    sys.modules["torchvision"] = tv
    sys.modules["cv2"] = types.ModuleType("cv2")
    sys.path.insert(0, str(REFERENCE))
    try:
        import models.base_model as base_model  # noqa: PLC0415 - the reference's own package name
        import models.network_utils.networks as networks  # noqa: PLC0415

        yield networks, base_model
    finally:
        sys.path.remove(str(REFERENCE))
        for k in [k for k in sys.modules if k.split(".")[0] in _TOP_LEVEL]:
            del sys.modules[k]
        sys.modules.update(saved)


def options(category: str, checkpoints_dir: str, **over) -> SimpleNamespace:
    """The training options the authors' BaseModel reads (their defaults, CPU)."""
    opt = dict(gpu_ids=[], isTrain=True, checkpoints_dir=checkpoints_dir, name="ref", category=category, nz_geo=200,
               continue_train=False, which_epoch="latest", init_type="normal", lr=1e-4, beta1=0.5, lambda_recon=10.0,
               lambda_depth=10.0, lambda_smooth=10.0, lambda_vgg=1.0)
    opt.update(over)
    return SimpleNamespace(**opt)


@contextlib.contextmanager
def cuda_is_identity():
    orig = torch.Tensor.cuda
    torch.Tensor.cuda = lambda self, *a, **k: self
    try:
        yield
    finally:
        torch.Tensor.cuda = orig
