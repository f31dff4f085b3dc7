"""The one data contract every dataset yields and every model and loss reads.

Batch (a plain dict, so Lightning moves it between devices):
    src        (B,3,H,W) float in [0,1]   source image
    tgt        (B,3,H,W) float in [0,1]   target image
    K          (B,3,3)   float            intrinsics in pixels at the batch's resolution
                                           (OpenCV: x right, y down, pixel centres at integer coordinates)
    T_tgt_src  (B,4,4)   float            maps source-camera points into the target camera
    pivot      (B,3)     float            point (in camera coordinates) the latent is rotated about:
                                           the object centre (0,0,2) for objects, 0 for scenes
    depth_src  (B,1,H,W) float, optional  ground-truth depth (z along the optical axis, pose units), 0 = no data
    depth_tgt  (B,1,H,W) float, optional  same for the target view
    id_src, id_tgt  list[str]             pair ids (image stems)

Outputs of a network forward (dict):
    rgb        (B,3,H,W) in [0,1]                  final prediction
    rgb_scales list of (B,3,h,w) in [-1,1]         multi-scale predictions, coarse to fine, last = full resolution
    depth      (B,1,H,W) > 0                       predicted target depth (when the model has one)
    warped_src (B,3,H,W) in [0,1]                  source image warped by the predicted depth (when requested)
    ...extras requested by losses (see nvs.models.net.Extras)
"""

from __future__ import annotations

from typing import Any

Batch = dict[str, Any]
Outputs = dict[str, Any]

REQUIRED_KEYS = ("src", "tgt", "K", "T_tgt_src", "pivot")
