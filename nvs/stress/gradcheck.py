"""Report section 2: float64 gradcheck of the warp, the depth heads and every loss term."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.overrides import TorchFunctionMode

from nvs.core.geometry import inverse_warp, pose_matrix
from nvs.data.synthetic import about_point, intrinsics, rotation
from nvs.stress.batches import CENTRE


class float64_kept(TorchFunctionMode):  # noqa: N801 - used as a context manager, named like one
    """While active, ``Tensor.float()`` leaves float64 tensors alone (on this thread, within the ``with`` block).

    The bf16 upcasts ``x.float()`` in loss terms and heads also turn float64 into float32; under this mode a gradcheck
    failure can only come from a wrong analytic gradient, not from that cast. A torch function mode intercepts the
    call inside the block only; ``torch.Tensor`` itself is never patched.
    """

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is torch.Tensor.float and args[0].dtype == torch.float64:
            return args[0]
        return func(*args, **(kwargs or {}))


@dataclass
class GradcheckCase:
    """A float64 function of some float64 inputs; ``fast`` uses gradcheck's random-projection mode (big inputs)."""

    name: str
    fn: Callable[..., torch.Tensor]
    inputs: tuple[torch.Tensor, ...]
    fast: bool = False


def _rand(*shape, low=0.0, high=1.0, g=None) -> torch.Tensor:
    return (low + (high - low) * torch.rand(*shape, generator=g, dtype=torch.float64)).requires_grad_(True)


def gradcheck_cases(size: int = 8, seed: int = 0) -> list[GradcheckCase]:
    """The warp (w.r.t. image, depth, K, pose), the depth heads and every loss term, on float64 inputs."""
    from nvs.core.types import Extras
    from nvs.losses.branches import BranchReconLoss
    from nvs.losses.terms import DepthConsistencyLoss, EdgeSmoothLoss, ReconLoss, VGGLoss, WarpLoss
    from nvs.models.depth_head import BoundedDepth, DisparityDepth

    g = torch.Generator().manual_seed(seed)
    dt, S = torch.float64, size
    K = intrinsics(6.0, S, 1, dtype=dt)
    T_obj = about_point(rotation("y", 3, dt), CENTRE)[None]
    T_scene = pose_matrix(rotation("y", 1, dt)[None], torch.tensor([[0.02, 0.0, -0.3]], dtype=dt))
    T_behind = pose_matrix(torch.eye(3, dtype=dt)[None], torch.tensor([[0.0, 0.0, 1.9]], dtype=dt))
    depth_behind = torch.cat([torch.full((1, 1, S // 2, S), 1.5), torch.full((1, 1, S - S // 2, S), 2.5)], 2).to(dt)
    tgt, src = torch.rand(1, 3, S, S, generator=g, dtype=dt), torch.rand(1, 3, S, S, generator=g, dtype=dt)
    batch = {"tgt": tgt, "src": src}

    def warp_of(K_, T_):
        return lambda s, d: inverse_warp(s, d, K_, T_)[0]

    cases = [
        GradcheckCase("inverse_warp w.r.t. image, depth (object, 3° about the centre)", warp_of(K, T_obj),
                      (_rand(1, 2, S, S, g=g), _rand(1, 1, S, S, low=1.8, high=2.2, g=g))),
        GradcheckCase("inverse_warp w.r.t. image, depth (scene, forward motion)", warp_of(K, T_scene),
                      (_rand(1, 2, S, S, g=g), _rand(1, 1, S, S, low=5.0, high=20.0, g=g))),
        GradcheckCase("inverse_warp w.r.t. image, depth (half the points behind the camera)", warp_of(K, T_behind),
                      (_rand(1, 2, S, S, g=g), (depth_behind + 0.01 * torch.rand(1, 1, S, S, generator=g,
                                                                                 dtype=dt)).requires_grad_(True))),
        GradcheckCase("inverse_warp w.r.t. K and pose", lambda K_, T_: inverse_warp(src[:, :2], torch.full(
            (1, 1, S, S), 2.0, dtype=dt) + 0.1 * tgt[:, :1], K_, T_)[0],
            (K.clone().requires_grad_(True), T_obj.clone().requires_grad_(True))),
        GradcheckCase("BoundedDepth head (1, 3)", BoundedDepth(1.0, 3.0), (_rand(1, 1, S, S, low=-3, high=3, g=g),)),
        GradcheckCase("DisparityDepth head (10, 0.01)", DisparityDepth(10.0, 0.01),
                      (_rand(1, 1, S, S, low=-8, high=8, g=g),)),
    ]
    scales = tuple(_rand(1, 3, S // s, S // s, low=-1, high=1, g=g) for s in (8, 4, 2, 1) if S // s >= 1)
    recon = ReconLoss(scale_weights=[1.0, 0.5, 0.2, 0.1][: len(scales)])
    cases.append(GradcheckCase("ReconLoss (multi-scale L1)", lambda *sc: recon({"rgb_scales": list(sc)}, batch),
                               scales))

    def depths():
        return _rand(1, 1, S, S, low=1, high=3, g=g), _rand(1, 1, S, S, low=1, high=3, g=g)

    cases.append(GradcheckCase("DepthConsistencyLoss", lambda a, b: DepthConsistencyLoss()(
        {"depth": a, Extras.DEPTH_FROM_TGT: b}, batch), depths()))
    cases.append(GradcheckCase("EdgeSmoothLoss (target and source depth)", lambda a, b: EdgeSmoothLoss()(
        {"depth": a, Extras.DEPTH_SRC: b}, batch), depths()))
    valid = (torch.rand(1, 1, S, S, generator=g) > 0.3).to(dt)
    cases.append(GradcheckCase("WarpLoss (masked L1)", lambda w: WarpLoss()(
        {Extras.WARPED_SRC: w, "warp_valid": valid}, batch), (_rand(1, 3, S, S, g=g),)))
    cases.append(GradcheckCase("BranchReconLoss (per-branch L1)", lambda a, b: BranchReconLoss()(
        {"rgb_branches": {"flow": a, "pixel": b}}, batch), (_rand(1, 3, S, S, g=g), _rand(1, 3, S, S, g=g))))
    # Resized to 32² rather than the loss's default 224²: the same layers and resize, ~50x fewer float64 FLOPs.
    vgg = VGGLoss(size=32).double()
    big = {"tgt": torch.rand(1, 3, 16, 16, generator=g, dtype=dt)}
    cases.append(GradcheckCase("VGGLoss (16x16 resized to 32x32, random projection)", lambda p: vgg({"rgb": p}, big),
                               (_rand(1, 3, 16, 16, g=g),), fast=True))
    return cases


def run_gradcheck(case: GradcheckCase) -> tuple[bool, str]:
    """(passed, first line of the failure)."""
    try:
        ok = torch.autograd.gradcheck(case.fn, case.inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=case.fast)
        return bool(ok), ""
    except Exception as err:  # noqa: BLE001 - gradcheck raises GradcheckError or the function's own error
        return False, str(err).strip().splitlines()[0][:120]


def float32_inside(case: GradcheckCase) -> str:
    """Why the function does not compute in float64 ('' if it does): its output differs from the float64-kept one."""
    with torch.no_grad():
        a = case.fn(*case.inputs)
        with float64_kept():
            b = case.fn(*case.inputs)
    if a.dtype != torch.float64:
        return f"returns {str(a.dtype).removeprefix('torch.')} for float64 inputs"
    if not torch.equal(a, b):
        return f"computes in float32 inside (differs from float64 by {float((a - b).abs().max()):.1e})"
    return ""


def gradcheck_section() -> list[list]:
    rows = []
    for case in gradcheck_cases():
        # A function that drops to float32 cannot pass a float64 gradcheck; say so instead of running it (a failing
        # fast-mode gradcheck recomputes the full Jacobian for its message, minutes for VGG).
        cast = float32_inside(case)
        as_is, why = (False, cast) if cast else run_gradcheck(case)
        with float64_kept():
            kept, why_kept = run_gradcheck(case)
        rows.append([case.name, "pass" if as_is else "FAIL", "pass" if kept else "FAIL", why or why_kept])
    return rows
