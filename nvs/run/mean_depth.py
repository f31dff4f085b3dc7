"""The mean ground-truth depth of a dataset's training views, and the constant-depth reference built from it.

``model=mean_depth`` (``conf/model/mean_depth.yaml``) is built by :func:`mean_depth_warp`: it reads the depth of every
view the training split uses (objects: every view of the training models, ``data.train_fraction`` applied; scenes:
every frame of the training pairs), averages the valid pixels (> 0) and returns a ``ConstantDepthWarp`` at that
depth. No validation or test view is read, so the row is a floor that uses no test ground truth.
"""

from __future__ import annotations

import sys

import torch

from nvs.core.errors import UserError
from nvs.data.datamodule import build_datamodule
from nvs.models.reference_planes import ConstantDepthWarp
from nvs.run.build import datamodule_arguments


def training_mean_depth(data: dict, seed: int = 0) -> float:
    """Mean of the valid (> 0) ground-truth depths of the training views, in the data's units (scenes: scaled).

    ``data``: the run's data config, resolved (``conf/model/mean_depth.yaml`` passes ``${data}``).
    """
    try:
        dm = build_datamodule(seed=seed, **datamodule_arguments(data))
    except (TypeError, KeyError) as err:
        raise UserError(f"config 'model.data' (model=mean_depth): {err}") from None
    if not dm.fmt.has_depth:
        raise UserError(f"model=mean_depth: {data['root']} has no depth/ files to take the training mean from")
    train = dm.dataset("train")
    ids = list(dict.fromkeys(train.sources if train.sources is not None else [i for p in train.pairs for i in p]))
    total, count = 0.0, 0
    for fid in ids:
        _, depth = dm.fmt.read(fid, dm.size, True)
        valid = depth[(depth > 0) & torch.isfinite(depth)].double()
        total, count = total + float(valid.sum()), count + valid.numel()
    if count == 0:
        raise UserError(f"model=mean_depth: the {len(ids)} training views under {data['root']} hold no valid depth")
    return total / count


def mean_depth_warp(data: dict, seed: int = 0, image_size: int | None = None, fill: float = 1.0,
                    sky_disparity: float | None = None) -> ConstantDepthWarp:
    """The constant-depth reference at the training views' mean depth (see the module doc)."""
    depth = training_mean_depth(data, seed)
    print(f"[mean_depth] the training views' mean depth under {data.get('root')}: {depth:.6g}", file=sys.stderr)
    return ConstantDepthWarp(depth, image_size=image_size, fill=fill, sky_disparity=sky_disparity)
