"""Report section 1: ``inverse_warp`` under extreme rotations, translations, depths, focal lengths and poses."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nvs.core.geometry import MIN_DEPTH, inverse_warp, pose_matrix
from nvs.data.synthetic import about_point, intrinsics, rotation
from nvs.stress.batches import CENTRE
from nvs.stress.harness import all_finite


@dataclass
class WarpCase:
    """One input to ``inverse_warp``: depth (B,1,S,S), K (B,3,3), T (B,4,4); ``expect``: 'all' | 'none' | None valid."""

    name: str
    depth: torch.Tensor
    K: torch.Tensor
    T: torch.Tensor
    expect: str | None = None


def geometry_cases(size: int = 16, B: int = 2, seed: int = 0) -> list[WarpCase]:
    """Extreme rotations, translations, depths, focal lengths, points behind the camera and near-singular poses."""
    g = torch.Generator().manual_seed(seed)

    def depth(value: float) -> torch.Tensor:
        # +-10 % texture so that pixels do not all project to the same place.
        return value * (1 + 0.1 * (2 * torch.rand(B, 1, size, size, generator=g) - 1))

    def T_of(R=None, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
        R = torch.eye(3) if R is None else R
        return pose_matrix(R.expand(B, 3, 3), torch.tensor(t, dtype=torch.float32).expand(B, 3))

    def obj(deg: float, axis: str = "y") -> torch.Tensor:
        return about_point(rotation(axis, deg), CENTRE).expand(B, 4, 4).clone()

    f = 20.0
    K = intrinsics(f, size, B)
    small = T_of(rotation("y", 5), (0.1, 0.0, 0.0))
    cases = [WarpCase("identity pose", depth(2.0), K, T_of(), "all")]
    for deg in (30, 90, 135, 179.9, 180):
        cases.append(WarpCase(f"rotation {deg}° about y through the object centre", depth(2.0), K, obj(deg)))
    cases.append(WarpCase("rotation 180° about x through the object centre", depth(2.0), K, obj(180, "x")))
    cases.append(WarpCase("rotation 180° about y through the camera (all behind)", depth(2.0), K,
                          T_of(rotation("y", 180)), "none"))
    for t in (1e-6, 1e-3, 1.0, 1e3):
        cases.append(WarpCase(f"translation x = {t:g}", depth(2.0), K, T_of(t=(t, 0.0, 0.0))))
    for t in (1e-6, 1.0, 1e3):
        cases.append(WarpCase(f"translation z = -{t:g} (points recede)", depth(2.0), K, T_of(t=(0.0, 0.0, -t))))
    cases.append(WarpCase("translation z = +1e3 (all behind)", depth(2.0), K, T_of(t=(0.0, 0.0, 1e3)), "none"))
    for d in (1e-4, 1e-2, 1.0, 1e2, 1e4):
        cases.append(WarpCase(f"depth {d:g} (5° + 0.1 motion)", depth(d), K, small))
    log_depth = 10 ** (8 * torch.rand(B, 1, size, size, generator=g) - 4)
    cases.append(WarpCase("depth log-uniform 1e-4..1e4 in one map", log_depth, K, small))
    for fk in (1.0, 10.0, 1e3, 1e5):
        cases.append(WarpCase(f"focal {fk:g} px", depth(2.0), intrinsics(fk, size, B), small))
    cases.append(WarpCase("all points behind the source camera (t_z = +5)", depth(1.0), K, T_of(t=(0.0, 0.0, 5.0)),
                          "none"))
    cases.append(WarpCase("source depth at the camera plane (z_src ~ MIN_DEPTH)", depth(0.0) + 2.0, K,
                          T_of(t=(0.0, 0.0, 2.0 - MIN_DEPTH))))
    cases.append(WarpCase("depth 0 everywhere (no data)", torch.zeros(B, 1, size, size), K, small, "none"))
    cases.append(WarpCase("negative depth", -depth(1.0), K, small, "none"))
    R30 = rotation("y", 30)
    cases.append(WarpCase("near-singular pose: R scaled by 1e-6", depth(2.0), K, T_of(R30 * 1e-6, (0.0, 0.0, 1.0))))
    cases.append(WarpCase("near-singular pose: R = diag(1, 1, 1e-8)", depth(2.0), K,
                          T_of(torch.diag(torch.tensor([1.0, 1.0, 1e-8])))))
    cases.append(WarpCase("singular pose: rank-1 R", depth(2.0), K,
                          T_of(torch.tensor([[1.0, 0, 0], [1, 0, 0], [1, 0, 0]]), (0.0, 0.0, 1.0))))
    cases.append(WarpCase("rotation with 1e-7 noise (not orthonormal)", depth(2.0), K,
                          T_of(R30 + 1e-7 * torch.randn(3, 3, generator=g))))
    bad = depth(2.0)
    bad[:, :, 0, 0] = float("inf")
    cases.append(WarpCase("one +inf depth pixel (outside the contract)", bad, K, small))
    bad = depth(2.0)
    bad[:, :, 0, 0] = float("nan")
    cases.append(WarpCase("one NaN depth pixel (outside the contract)", bad, K, small))
    return cases


@dataclass
class WarpCheck:
    finite_out: bool
    finite_grad_src_depth: bool
    finite_grad_K_T: bool
    masked: bool
    valid_fraction: float
    expectation_met: bool


def check_warp(case: WarpCase, channels: int = 3, seed: int = 0) -> WarpCheck:
    """Warp a random image through the case; outputs and gradients (w.r.t. src, depth, K, T) must stay finite."""
    g = torch.Generator().manual_seed(seed)
    B, _, H, W = case.depth.shape
    src = torch.rand(B, channels, H, W, generator=g).requires_grad_(True)
    depth = case.depth.clone().requires_grad_(True)
    K, T = case.K.clone().requires_grad_(True), case.T.clone().requires_grad_(True)
    warped, valid = inverse_warp(src, depth, K, T)
    # A non-linear read-out so that every gradient path is exercised with non-constant upstream gradients.
    (warped.sum() + (warped ** 2).sum()).backward()
    frac = float(valid.mean())
    expect = {"all": frac == 1.0, "none": frac == 0.0}.get(case.expect, True)
    return WarpCheck(all_finite(warped, valid), all_finite(src.grad, depth.grad), all_finite(K.grad, T.grad),
                     bool((warped * (1 - valid)).abs().max() == 0), frac, expect)


def geometry_section() -> list[list]:
    rows = []
    for case in geometry_cases():
        c = check_warp(case)
        note = "" if c.expectation_met else f"expected {case.expect} valid"
        rows.append([case.name, c.finite_out, c.finite_grad_src_depth, c.finite_grad_K_T, c.masked,
                     f"{c.valid_fraction:.3f}", note])
    return rows
