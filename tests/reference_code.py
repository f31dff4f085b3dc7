"""The authors' code (../shared/reference/warped-skipconnection-nvs), imported for the fidelity tests only.

The importer is the bench's (``nvs.bench.reference.imported``): ``torchvision.models.vgg16`` returns VGG16's
``features`` layers holding the ImageNet weights nvs ships, ``cv2`` is an empty module (used only by visualisation
helpers) and ``Tensor.cuda`` is the identity, all undone afterwards. Nothing of the authors' code is copied into nvs.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import SimpleNamespace

import torch

import nvs.bench.reference as bench_reference

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "warped-skipconnection-nvs"


def available() -> bool:
    return (REFERENCE / "models" / "base_model.py").is_file()


@contextlib.contextmanager
def imported():
    """Yields (networks, base_model) modules of the reference code; sys.path and sys.modules are restored after."""
    with bench_reference.imported(REFERENCE) as base_model:
        import models.network_utils.networks as networks  # noqa: PLC0415 - the reference's own package name

        yield networks, base_model


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


@contextlib.contextmanager
def losses_only():
    """The code's training step without its gradients: its forward under no_grad (train-mode BatchNorm still uses and
    updates the batch statistics) and ``backward()`` a no-op, for a test that compares outputs and loss terms only
    (the backward at 256² is most of the step's time)."""
    orig = torch.Tensor.backward
    torch.Tensor.backward = lambda self, *a, **k: None
    try:
        with torch.no_grad():
            yield
    finally:
        torch.Tensor.backward = orig
