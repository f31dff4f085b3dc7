"""``nvs.evaluate time_sizes=[64,256]``: the forward time per image of the evaluated configuration at image sizes
other than the one it was trained at, and for a routed network (``route=...``) the time of each route there and of
their mix at the test pairs' shares (docs/skipping.md).

The speed of a network does not depend on its weights, so a size other than the checkpoint's is timed on the same
configuration built at that size (``data.size`` and ``model.image_size`` replaced) with fresh weights; the
checkpoint's own size is timed on the trained network itself. The input is one test batch resized to each size
(images bilinear, depths nearest, K scaled under the pixel-centre convention; the poses unchanged).

Per size S, ``metrics.json``'s ``timing_by_size[str(S)]``:
    network_ms_per_image   the network's own forward (every pair through the pixel decoder, as with route=off)
    routes_ms_per_image    with a route: {copy, warp, full}: every pair of the batch sent down that route (the
                           routed network's forward with the rule forced), features included
    routed_ms_per_image    with a route: sum over routes of the test pairs' share x that route's time
    speedup                with a route: network_ms_per_image / routed_ms_per_image
Each time is the median of ``time_repeats`` forwards (after two warm-up forwards) divided by the batch size, on the
device, thread count and precision of the test. These are measured in one process, one after the other: compare them
as ratios within one job, not across machines.
"""

from __future__ import annotations

import contextlib
import statistics
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf

from nvs.core.errors import UserError
from nvs.core.geometry import scale_intrinsics
from nvs.core.types import ROUTES, Batch
from nvs.models.route import RoutedNet
from nvs.models.route_rule import RouteRule
from nvs.module.lightning_module import NVSModule

WARMUP = 2
# Every pair of a batch down one route: the routed network with its rule forced (inf thresholds always pass).
FORCED = {"copy": RouteRule(copy_pose_px=float("inf")),
          "warp": RouteRule(warp_disocclusion=float("inf"), warp_displacement_px=float("inf")),
          "full": RouteRule()}


def sizes_option(value, repeats) -> tuple[list[int], int]:
    """``time_sizes`` (null or a list of image sizes) and ``time_repeats`` checked -> (sizes, repeats)."""
    if value is None:
        return [], int(repeats or 1)
    items = list(value) if not isinstance(value, (str, int)) else None
    if items is None or any(isinstance(s, bool) or not isinstance(s, int) or s < 8 for s in items):
        raise UserError(f"time_sizes={value}: expected a list of image sizes in pixels (>= 8), e.g. [64,256]")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise UserError(f"time_repeats={repeats}: expected a positive number of timed forwards")
    return sorted(dict.fromkeys(items)), repeats


def resized_batch(batch: Batch, size: int) -> Batch:
    """``batch`` at ``size``²: every (B,C,H,W) tensor of the batch's image size resized, K scaled, the rest kept."""
    H, W = batch["src"].shape[-2:]
    out: Batch = {}
    for key, value in batch.items():
        if torch.is_tensor(value) and value.dim() == 4 and value.shape[-2:] == (H, W):
            nearest = key.startswith("depth") or not value.is_floating_point()
            out[key] = (F.interpolate(value.float(), size=(size, size), mode="nearest").to(value.dtype) if nearest
                        else F.interpolate(value, size=(size, size), mode="bilinear", align_corners=False,
                                           antialias=size < H))
        elif torch.is_tensor(value) and key.startswith("K") and value.shape[-2:] == (3, 3):
            out[key] = scale_intrinsics(value, size / W, size / H)
        else:
            out[key] = value
    return out


def config_at(run: DictConfig, size: int) -> DictConfig:
    """The run's resolved config with its image size replaced (``data.size``, ``model.image_size``)."""
    cfg = OmegaConf.create(OmegaConf.to_container(run, resolve=True))
    cfg.data.size = size
    if "image_size" in cfg.model:
        cfg.model.image_size = size
    return cfg


def autocast_for(precision, device: torch.device):
    """The autocast context of a Lightning precision string (fp32: none)."""
    text = str(precision)
    if "bf16" in text:
        return torch.autocast(device.type, dtype=torch.bfloat16)
    if text.startswith("16"):
        return torch.autocast(device.type, dtype=torch.float16)
    return contextlib.nullcontext()


def median_ms_per_image(forward: Callable[[], object], batch_size: int, repeats: int, device: torch.device,
                        precision) -> float:
    """The median over ``repeats`` timed calls of ``forward`` (after ``WARMUP`` untimed ones), per image, in ms."""
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    times = []
    with torch.no_grad(), autocast_for(precision, device):
        for i in range(WARMUP + repeats):
            sync()
            t0 = time.perf_counter()
            forward()
            sync()
            if i >= WARMUP:
                times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times) / batch_size


def _network_at(module: NVSModule, run: DictConfig, size: int) -> torch.nn.Module:
    """The (unrouted) network at ``size``: the trained one at its own size, else the configuration built there."""
    inner = module.net.net if isinstance(module.net, RoutedNet) else module.net
    if size == int(run.data.size):
        return inner
    from nvs.run.build import build_module  # the build layer: only when another size is asked for

    try:
        net = build_module(config_at(run, size), channels_last=module.channels_last).net
    except (UserError, ValueError, RuntimeError, TypeError) as err:
        raise UserError(f"time_sizes: the network of this checkpoint cannot be built at {size}x{size} ({err})") from None
    device = next(inner.parameters()).device
    return net.to(device).eval()


def timing_by_size(module: NVSModule, run: DictConfig, batch: Batch, sizes: list[int], repeats: int,
                   precision, shares: dict[str, float] | None) -> dict[str, dict]:
    """``metrics.json``'s ``timing_by_size`` (see the module docstring); ``shares``: the test pairs' route shares
    (None: the network is not routed)."""
    device = next(module.parameters()).device
    result: dict[str, dict] = {}
    for size in sizes:
        net = _network_at(module, run, size)
        was_training = net.training
        net.eval()
        data = module._prepare({k: v.to(device) if torch.is_tensor(v) else v
                                for k, v in resized_batch(batch, size).items()})
        B = data["src"].shape[0]
        try:
            entry = {"network_ms_per_image": median_ms_per_image(lambda: net(data), B, repeats, device, precision)}
            if shares is not None:
                routes = {r: median_ms_per_image(lambda r=r: RoutedNet(net, FORCED[r])(data), B, repeats, device,
                                                 precision) for r in ROUTES}
                routed = sum(shares[r] * routes[r] for r in ROUTES)
                entry.update(routes_ms_per_image=routes, routed_ms_per_image=routed,
                             speedup=entry["network_ms_per_image"] / routed if routed > 0 else None)
        except RuntimeError as err:
            raise UserError(f"time_sizes: the forward at {size}x{size} failed ({err})") from None
        finally:
            net.train(was_training)
        result[str(size)] = entry
    return result
