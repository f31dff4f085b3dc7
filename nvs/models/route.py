"""Routing at inference on a trained network, no retraining: per pair, copy the source, warp it into the target view
by the predicted depth, or run the full pixel decoder, as a fitted ``RouteRule`` says (docs/skipping.md).

Per pair, cheapest first (each stage runs only for the pairs the one before did not settle):
    1. ``pose_px``: the closed-form bound on how far the warp can move any pixel, from K, the pose and the depth head's
       range alone (``nvs.core.geometry.max_warp_displacement``); no network runs. ``copy`` pairs stop here.
    2. The encoder and the depth decoder (``predict_depth``), then, from the predicted target depth and the exact
       geometry (``nvs.core.geometry.project_to_source``): ``disp_mean_px`` / ``disp_max_px``, the mean / max pixel
       displacement over the target pixels whose source point is in front of the source camera and inside the source
       image, and ``disocclusion``, the fraction of target pixels that are not (outside, behind) or are occluded in
       the source: a z-buffer on the source pixel each one lands on (rounded) keeps only the nearest, within
       ``OCCLUSION_TOLERANCE`` of its depth. ``warp`` pairs stop here: the source bilinearly sampled at the visible
       pixels, every other pixel the source pixel at the same position (what ``copy`` shows there).
    3. The skips and the pixel decoder (``decode_pixels``) on the subset routed ``full`` only.
Convention: K, poses and pixel centres as ``nvs.core.geometry``; the warp is the exact one (an identity pose is an
identity warp), whatever the network's ``warp_align`` fidelity switch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn as nn
from torch.utils.flop_counter import FlopCounterMode

from nvs.core.geometry import BORDER_TOLERANCE, max_warp_displacement, project_to_source, sample_at
from nvs.core.protocols import DepthBeforePixels, DepthRange
from nvs.core.types import ROUTES, Batch, Outputs, to_image_range, to_model_range
from nvs.models.route_rule import FEATURES, RouteRule

# A target pixel is occluded when its source depth exceeds the nearest one landing on the same source pixel by more
# than this fraction (foreshortened surfaces put neighbours on one source pixel at nearly equal depth).
OCCLUSION_TOLERANCE = 0.01
COPY, WARP, FULL = (ROUTES.index(r) for r in ROUTES)


def take(x: Any, idx: torch.Tensor, n: int) -> Any:
    """The rows ``idx`` of every tensor with ``n`` rows in a tensor / tuple / list / dict tree (others unchanged)."""
    if torch.is_tensor(x):
        return x[idx] if x.dim() and x.shape[0] == n else x
    if isinstance(x, dict):
        return {k: take(v, idx, n) for k, v in x.items()}
    if isinstance(x, (tuple, list)) and not (isinstance(x, list) and x and isinstance(x[0], str)):
        return type(x)(take(v, idx, n) for v in x)
    return x


def depth_range_of(net: nn.Module) -> tuple[float, float] | None:
    """The range every predicted depth lies in: the network's depth heads' (their union), None without one."""
    heads = [m for m in net.modules() if isinstance(m, DepthRange)]
    if not heads:
        return None
    return min(float(h.min_depth) for h in heads), max(float(h.max_depth) for h in heads)


def pose_bound(K: torch.Tensor, T_tgt_src: torch.Tensor, depth_range: tuple[float, float] | None,
               size: tuple[int, int]) -> torch.Tensor:
    """(B,) float64 px: the bound on any pixel's displacement over the depth range (inf without a range)."""
    B = K.shape[0]
    if depth_range is None:
        return torch.full((B,), float("inf"), dtype=torch.float64, device=K.device)
    lo, hi = (torch.full((B,), v, dtype=torch.float64, device=K.device) for v in depth_range)
    return max_warp_displacement(K, T_tgt_src, lo, hi, size)


def warp_source(src: torch.Tensor, depth: torch.Tensor, K: torch.Tensor,
                T_tgt_src: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The ``warp`` route and its features: src (B,3,H,W), predicted target depth (B,1,H,W), K (B,3,3), T (B,4,4)
    -> warped (B,3,H,W) (disoccluded pixels: the source pixel there), {disp_mean_px, disp_max_px, disocclusion: (B,)}
    (displacements inf where no pixel lands in the source)."""
    B, _, H, W = src.shape
    uv, z, in_front = project_to_source(depth, K, T_tgt_src)
    u, v = uv[..., 0], uv[..., 1]
    tol = BORDER_TOLERANCE
    valid = in_front & (u >= -tol) & (u <= W - 1 + tol) & (v >= -tol) & (v <= H - 1 + tol)
    # z-buffer over the source pixels: the nearest target point landing on each one is the one the source shows
    cell = (v.round().clamp(0, H - 1) * W + u.round().clamp(0, W - 1)).long().flatten(1)
    zz = torch.where(valid, z, torch.full_like(z, float("inf"))).flatten(1)
    nearest = torch.full_like(zz, float("inf")).scatter_reduce(1, cell, zz, "amin").gather(1, cell)
    visible = valid & (zz <= nearest * (1 + OCCLUSION_TOLERANCE)).view(B, H, W)
    vv, uu = torch.meshgrid(torch.arange(H, device=src.device, dtype=uv.dtype),
                            torch.arange(W, device=src.device, dtype=uv.dtype), indexing="ij")
    disp = torch.hypot(u - uu, v - vv)
    count = valid.flatten(1).sum(1)
    inf = torch.full((B,), float("inf"), dtype=disp.dtype, device=disp.device)
    mean = torch.where(count > 0, torch.where(valid, disp, 0).flatten(1).sum(1) / count.clamp(min=1), inf)
    peak = torch.where(count > 0, torch.where(valid, disp, -1).flatten(1).amax(1), inf)
    warped = torch.where(visible[:, None], sample_at(src, uv, visible), src)
    feats = {"disp_mean_px": mean, "disp_max_px": peak, "disocclusion": 1 - visible.flatten(1).float().mean(1)}
    return warped, feats


class RoutedNet(nn.Module):
    """A ``DepthBeforePixels`` network (``NVSNet``) behind a ``RouteRule``: forward(batch) -> outputs with ``rgb``,
    ``rgb_scales`` (the final one only), ``depth`` (NaN for copied pairs: never predicted), ``route`` (B,) indices
    into ``ROUTES`` and ``route_features`` {FEATURES: (B,)} (NaN where not computed: the warp's features of copied
    pairs, and of every pair under a rule that never warps, which skips the warp).

    ``forward`` runs the encoder for the pairs not copied only; ``encode`` / ``render`` (the viewer's split) encode
    every source. The parameters are the network's: a checkpoint's weights load into ``net``.
    """

    def __init__(self, net: nn.Module, rule: RouteRule):
        super().__init__()
        if not isinstance(net, DepthBeforePixels):
            raise TypeError(f"{type(net).__name__} predicts no depth apart from its pixel decoder: it cannot be routed")
        self.net, self.rule = net, rule
        self.depth_range = depth_range_of(net)

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        src = batch["src"]
        return self._route(src, batch, lambda idx: self.net.encode(src[idx]))

    def encode(self, src: torch.Tensor) -> tuple[torch.Tensor, Any]:
        return src, self.net.encode(src)

    def render(self, encoded: tuple[torch.Tensor, Any], batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        src, inner = encoded
        return self._route(src, batch, lambda idx: take(inner, idx, src.shape[0]))

    def _route(self, src: torch.Tensor, batch: Batch, encode: Callable[[torch.Tensor], Any]) -> Outputs:
        B, _, H, W = src.shape
        pose = pose_bound(batch["K"], batch["T_tgt_src"], self.depth_range, (H, W))
        nan = torch.full((B,), float("nan"), device=src.device)
        feats = {k: nan.clone() for k in FEATURES}
        feats["pose_px"] = pose.float()
        copy = self.rule.copies(pose)
        route = torch.where(copy, COPY, FULL)
        rgb = src.float().clone()
        depth_out = torch.full((B, 1, H, W), float("nan"), device=src.device)
        rest = (~copy).nonzero()[:, 0]
        if rest.numel():
            sub = take(batch, rest, B)
            encoded = encode(rest)
            z_t, depth = self.net.predict_depth(encoded, sub)
            if self.rule.warp_disocclusion is None or self.rule.warp_displacement_px is None:
                warp = torch.zeros(rest.numel(), dtype=torch.bool, device=src.device)  # never: no warp to measure
            else:
                warped, f = warp_source(src[rest], depth, sub["K"], sub["T_tgt_src"])
                for k, v in f.items():
                    feats[k][rest] = v.float()
                warp = self.rule.warps(f["disocclusion"], f["disp_mean_px"])
                rgb[rest[warp]] = warped[warp].float()
            route[rest[warp]] = WARP
            full = (~warp).nonzero()[:, 0]
            if full.numel():
                n = rest.numel()
                scales = self.net.decode_pixels(take(encoded, full, n), z_t[full], depth[full], take(sub, full, n))
                rgb[rest[full]] = to_image_range(scales[-1]).float()
            depth_out[rest] = depth.float()
        return {"rgb": rgb, "rgb_scales": [to_model_range(rgb)], "depth": depth_out, "route": route,
                "route_features": feats}

    def all_routes(self, batch: Batch) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Every route of every pair (what the rule is fitted on): -> ({FEATURES: (B,)}, {route: rgb (B,3,S,S)})."""
        src = batch["src"]
        encoded = self.net.encode(src)
        z_t, depth = self.net.predict_depth(encoded, batch)
        warped, feats = warp_source(src, depth, batch["K"], batch["T_tgt_src"])
        full = to_image_range(self.net.decode_pixels(encoded, z_t, depth, batch)[-1])
        feats["pose_px"] = pose_bound(batch["K"], batch["T_tgt_src"], self.depth_range, tuple(src.shape[-2:]))
        # pose_px stays float64: the rule compares it in float64 (forward), so the fit must see the same values
        return {k: feats[k] for k in FEATURES}, {"copy": src.float(), "warp": warped.float(), "full": full.float()}


def route_costs(net: nn.Module, batch: Batch) -> dict[str, float]:
    """Each route's cost per pair in units of the full network's: its floating-point operations on one pair of
    ``batch`` (``torch.utils.flop_counter``: convolutions and matrix products), deterministic. ``copy`` runs no
    network (0); ``warp`` the encoder and the depth decoder; ``full`` all of it (1)."""
    one = take(batch, torch.arange(1, device=batch["src"].device), batch["src"].shape[0])
    with torch.no_grad():
        with FlopCounterMode(display=False) as depth_part:
            encoded = net.encode(one["src"])
            z_t, depth = net.predict_depth(encoded, one)
        with FlopCounterMode(display=False) as pixel_part:
            net.decode_pixels(encoded, z_t, depth, one)
    first, second = depth_part.get_total_flops(), pixel_part.get_total_flops()
    return {"copy": 0.0, "warp": first / max(first + second, 1), "full": 1.0}
