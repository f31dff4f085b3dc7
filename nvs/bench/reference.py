"""The authors' code, imported from a checkout the user names, timed as their train.py and eval.py run it.

Nothing of it is copied here: their ``models`` package is imported from ``reference=<path>`` with the stand-ins its
README (``../shared/reference/README.md``) lists for this CPU, made at import time and undone afterwards:
``torchvision.models.vgg16`` returns a module of VGG16's ``features`` layers holding the ImageNet weights nvs ships
(their VGG loss takes ``.features``), ``cv2`` is an empty module (only their visualisation helpers use it), and
``Tensor.cuda`` is the identity (their KITTI intrinsics call it). Their network is built for 256² only (the
encoder's last linear layer reads a 4×4 map of six stride-2 stages).
"""

from __future__ import annotations

import contextlib
import functools
import io
import sys
import types
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.core.errors import UserError
from nvs.core.geometry import invert_pose

SIZE = 256  # the only image size the authors' networks take
_TOP_LEVEL = ("models", "util", "data", "options", "torchvision", "cv2")


def check_path(path: str | Path) -> Path:
    root = Path(path).expanduser().resolve()
    if not (root / "models" / "base_model.py").is_file():
        raise UserError(f"reference={path}: not a checkout of the authors' code (no models/base_model.py there)")
    return root


def _vgg16_features() -> nn.Sequential:
    """torchvision's VGG16 ``features`` layout (conv, ReLU ..., max-pool after each block) with nvs's weights."""
    from nvs.models.perceptual import load_weights

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
def imported(path: str | Path) -> Iterator[types.ModuleType]:
    """Yields the authors' ``models.base_model`` from ``path``; sys.path, sys.modules and Tensor.cuda are restored."""
    root = check_path(path)
    saved = {k: v for k, v in sys.modules.items() if k.split(".")[0] in _TOP_LEVEL}
    for k in saved:
        del sys.modules[k]
    tv = types.ModuleType("torchvision")
    tv.models = SimpleNamespace(vgg16=lambda pretrained=True: SimpleNamespace(features=_vgg16_features()))
    sys.modules["torchvision"] = tv
    sys.modules["cv2"] = types.ModuleType("cv2")
    sys.path.insert(0, str(root))
    cuda = torch.Tensor.cuda
    torch.Tensor.cuda = lambda self, *a, **k: self
    try:
        import models.base_model as base_model  # noqa: PLC0415 - the reference's own package name

        yield base_model
    finally:
        torch.Tensor.cuda = cuda
        sys.path.remove(str(root))
        for k in [k for k in sys.modules if k.split(".")[0] in _TOP_LEVEL]:
            del sys.modules[k]
        sys.modules.update(saved)


def _options(category: str) -> SimpleNamespace:
    """What their BaseModel reads: train_options.py's defaults, the README's lr, CPU, nothing saved or loaded."""
    return SimpleNamespace(gpu_ids=[], isTrain=True, checkpoints_dir="/nonexistent", name="bench", category=category,
                           nz_geo=200, continue_train=False, which_epoch="latest", init_type="normal", lr=1e-4,
                           beta1=0.5, lambda_recon=10.0, lambda_depth=10.0, lambda_smooth=10.0, lambda_vgg=1.0)


def _quiet(method):
    """Their deprecated calls (F.upsample, the old torch.add overload) warn on every step: silenced in their calls."""
    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return method(*args, **kwargs)
    return wrapper


class Reference:
    """The authors' BaseModel (chairs) on one nvs batch: ``train_step``, ``novel_view`` and ``eval_path``."""

    def __init__(self, path: str | Path, device: torch.device, category: str = "chair"):
        if device.type != "cpu":
            raise UserError("reference=...: the authors' code is timed on the CPU here (their BaseModel takes "
                            "gpu_ids from options; run the bench without a GPU or without reference=)")
        with imported(path) as base_model, contextlib.redirect_stdout(io.StringIO()):  # it prints every network
            self.model = base_model.BaseModel(_options(category))
            self._inverse_warp = base_model.inverse_warp
        self.device = device

    @staticmethod
    def inputs(batch: dict) -> dict:
        """Their input dict: images in [-1,1], RT = T_src_tgt (target-camera points into the source camera)."""
        return {"A": batch["src"] * 2 - 1, "B": batch["tgt"] * 2 - 1, "RT": invert_pose(batch["T_tgt_src"])}

    def networks(self) -> list[nn.Module]:
        m = self.model
        return [m.enc, m.dec, m.depthdec, m.vgg]

    def parameter_count(self) -> int:
        return sum(p.numel() for n in self.networks()[:3] for p in n.parameters())

    @_quiet
    def train_step(self, data: dict) -> None:
        """One iteration of their train.py: set_input, forward, optimize_parameters (zero_grad, backward_G, step)."""
        self.model.switch_mode("train")
        self.model.set_input(data)
        self.model.forward()
        self.model.optimize_parameters()

    @_quiet
    def eval_path(self, data: dict) -> None:
        """Their eval.py's forward: eval mode, no grad, the whole training forward."""
        self.model.switch_mode("eval")
        with torch.no_grad():
            self.model.set_input(data)
            self.model.forward()

    @_quiet
    def novel_view(self, data: dict) -> torch.Tensor:
        """Only what the target view needs, through their own methods: encode, transform, depthdecode, the four
        skip warps (their inverse_warp, depth resized by F.upsample as their forward does) and decode."""
        m = self.model
        m.switch_mode("eval")
        with torch.no_grad():
            A, RT = data["A"].to(self.device), data["RT"].to(self.device)
            z, conv0, conv2, conv3, conv4 = m.encode(A)
            z_tf = m.transform(z, RT)
            depth = m.depthdecode(z_tf)
            skips = []
            for feat, scale in ((conv0, 1.0), (conv2, 0.25), (conv3, 0.125), (conv4, 0.0625)):
                d = depth if scale == 1.0 else F.interpolate(depth, scale_factor=scale)  # F.upsample's default
                K = m.intrinsics if scale == 1.0 else m.get_K(m.intrinsics, scale)
                skips.append(self._inverse_warp(feat, d, RT, K)[0])
            return m.decode(z_tf, *skips)[0]
