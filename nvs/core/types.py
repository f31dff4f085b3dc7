"""The one data contract: the batch every dataset yields and the outputs every network returns, read by models,
losses and metrics alike.

Convention: images (B,3,H,W) in [0,1] in a batch and in ``rgb``; the networks and the image-space losses work on
[-1,1] (``to_model_range``), as the paper's code does. ``K`` in pixels at the batch's resolution (OpenCV camera: x
right, y down, z forward; pixel centres at integer coordinates). ``T_tgt_src`` maps source-camera points into the
target camera. Depth is z along the optical axis in pose units; 0 in a ground truth means "no data".
"""

# No ``from __future__ import annotations``: TypedDict reads NotRequired only from evaluated annotations.
from typing import NotRequired, TypedDict

from torch import Tensor

Image = Tensor  # (B,3,H,W) float in [0,1]
Depth = Tensor  # (B,1,H,W) float, z along the optical axis (pose units)
Intrinsics = Tensor  # (B,3,3) float, pixels
Pose = Tensor  # (B,4,4) float, rigid transform between cameras
Point = Tensor  # (B,3) float, camera coordinates


class Batch(TypedDict):
    """What a data loader yields (a plain dict at run time, so Lightning moves it between devices)."""

    src: Image  # source image
    tgt: Image  # target image
    K: Intrinsics  # intrinsics of both views
    T_tgt_src: Pose  # maps source-camera points into the target camera
    pivot: Point  # the point the latent is rotated about: the object centre (0,0,2) for objects, 0 for scenes
    depth_src: NotRequired[Depth]  # ground-truth source depth, 0 = no data (data.loader.with_depth)
    depth_tgt: NotRequired[Depth]  # the same for the target view
    id_src: NotRequired[list[str]]  # pair ids (image stems)
    id_tgt: NotRequired[list[str]]
    index: NotRequired[Tensor]  # (B,) long: each pair's position in its split (evaluation rows are gathered by it)


class Extras:
    """Names of outputs that only some losses read (``LossTerm.needs``); a forward computes only those requested."""

    DEPTH_FROM_TGT = "depth_from_tgt"  # psi_d(z_t), z_t encoded from the target image (depth consistency)
    DEPTH_SRC = "depth_src"  # psi_d(z_s), the source view's own depth (edge smoothness on the source)
    WARPED_SRC = "warped_src"  # source image warped by the predicted target depth (warp loss)


# Output of models that blend several full-resolution predictions (Sun et al.): {branch name: (B,3,H,W) in [0,1]}.
RGB_BRANCHES = "rgb_branches"

# What a routed network (nvs.models.route) did per pair: copied the source, warped it by the predicted depth, or ran
# the full pixel decoder. ``Outputs["route"]`` holds indices into this tuple.
ROUTES = ("copy", "warp", "full")


class Outputs(TypedDict):
    """What a network's ``forward(batch, needs) -> outputs`` returns: ``rgb`` and ``rgb_scales`` always, the rest when
    the model has them (``depth``) or a loss asked for them (the ``Extras``)."""

    rgb: Image  # final prediction
    rgb_scales: list[Tensor]  # (B,3,h,w) in [-1,1], coarse to fine, last = full resolution; the network's n_scales
    depth: NotRequired[Depth]  # predicted target depth, > 0
    depth_from_tgt: NotRequired[Depth]  # Extras.DEPTH_FROM_TGT
    depth_src: NotRequired[Depth]  # Extras.DEPTH_SRC
    warped_src: NotRequired[Image]  # Extras.WARPED_SRC
    warp_valid: NotRequired[Tensor]  # (B,1,H,W) in {0,1}: the warped pixel's source point is in front, in the image
    rgb_branches: NotRequired[dict[str, Image]]  # RGB_BRANCHES
    confidence: NotRequired[Tensor]  # (B,2,H,W) softmax blending weights (flow, pixel) of Sun et al.'s model
    route: NotRequired[Tensor]  # (B,) long: the route each pair took, an index into ROUTES (a routed network)
    route_features: NotRequired[dict[str, Tensor]]  # {feature: (B,)} the routing rule read (NaN: not computed)


def to_model_range(img: Tensor) -> Tensor:
    """[0,1] -> [-1,1], any shape."""
    return img * 2.0 - 1.0


def to_image_range(x: Tensor) -> Tensor:
    """[-1,1] -> [0,1], any shape."""
    return (x + 1.0) * 0.5

