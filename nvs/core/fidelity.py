"""The fidelity switches: every place where the authors' code differs from the paper's text or from exact geometry.

The values live in the ``fidelity`` config node (``conf/fidelity/code.yaml``, the default, and ``corrected.yaml``)
and reach the components through interpolations in their configs; ``check`` validates the node once, at build
time, so that an unknown key or value is one error naming ``fidelity.<key>``. docs/fidelity.md is the table.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class Switch:
    code: object  # the authors' code (the default)
    corrected: object  # exact geometry / the paper's text / nvs's former choice
    choices: tuple | None = None  # allowed values; None: any number >= 0 (a factor), with null allowed when listed
    what: str = ""


SWITCHES: dict[str, Switch] = {
    "latent_rotation": Switch("code", "exact", ("code", "exact"), "latent rotated by z.bmm(R) (R^T) or R z"),
    "warp_align": Switch("code", "exact", ("code", "exact"), "grid_sample align_corners vs the normalisation"),
    "warp_padding": Switch("border", "zeros", ("border", "zeros"), "out-of-view samples: border, or masked"),
    "skip_intrinsics": Switch("code", "exact", ("code", "exact"), "K scaled with c*s, or pixel centres kept"),
    "skip_depth": Switch("nearest", "area", ("nearest", "area"), "depth brought to the skip levels"),
    "conv0_padding": Switch("zeros", "reflect", ("zeros", "reflect"), "padding of the encoder's conv0"),
    "conv0_norm": Switch("instance", "instance", ("instance", "batch", "none"), "norm of the encoder's conv0"),
    "decoder_norm": Switch("instance", "batch", ("instance", "batch", "none"), "norm of the pixel decoder"),
    "side_upsample": Switch("nearest", "bilinear", ("nearest", "bilinear"), "side predictions upsampled"),
    "depth_norm_batches": Switch("separate", "joint", ("separate", "joint"), "BatchNorm batches of psi_d"),
    "init": Switch("normal", "default", ("normal", "default"), "N(0, 0.02) or PyTorch's initialisation"),
    "vgg_range": Switch("model", "image", ("model", "image"), "VGG input [-1,1] or [0,1]"),
    "vgg_size": Switch(224, None, (224, None), "VGG input resized to 224 or native"),
    "smooth_factor": Switch(10.0, 1.0, None, "edge weight exp(-factor |dI|)"),
    "smooth_range": Switch("model", "image", ("model", "image"), "image range of the edge weight"),
    "smooth_on_source": Switch(True, False, (True, False), "smoothness on the source depth too"),
    "warp_loss_pixels": Switch("all", "valid", ("all", "valid"), "pixels the warp loss averages"),
    "adam_beta1": Switch(0.5, 0.9, None, "Adam's beta1"),
}


class FidelityError(ValueError):
    """A fidelity key or value nvs does not know."""


def check(node: Mapping | None) -> None:
    """Validate a resolved ``fidelity`` node: every key known, every value one of its switch's choices."""
    if node is None:
        return
    for key, value in node.items():
        if key not in SWITCHES:
            raise FidelityError(f"fidelity.{key}: no such switch; the switches are {sorted(SWITCHES)}")
        sw = SWITCHES[key]
        if sw.choices is None:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise FidelityError(f"fidelity.{key}={value!r}: a number >= 0 (code {sw.code}, corrected "
                                    f"{sw.corrected})")
        elif value not in sw.choices or isinstance(value, bool) != isinstance(sw.code, bool):
            raise FidelityError(f"fidelity.{key}={value!r}: choose one of {list(sw.choices)}")
