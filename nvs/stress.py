"""python -m nvs.stress [--out results/stress.md]: numerical stress report (geometry, gradcheck, precision, training
under adversarial batches, determinism), written atomically with a provenance header.

Every section returns rows; ``main`` renders them as Markdown tables. A few minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import math
import shlex
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from nvs.atomic import write_text
from nvs.geometry import MIN_DEPTH, inverse_warp, pose_matrix

ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = ROOT / "conf"
# Reference rows evaluated without training; they have no parameters to stress.
NO_TRAINING_MODELS = ("copy_source", "gt_warp")
# The data configs' cameras at 64^2: objects (f = 480 at 256^2, centre at distance 2) and scenes (f = 160).
OBJECT_F, SCENE_F, CENTRE = 120.0, 40.0, (0.0, 0.0, 2.0)


# -- shared helpers -------------------------------------------------------------------------------------------------
def rotation(axis: str, degrees: float, dtype=torch.float32) -> torch.Tensor:
    """(3,3) rotation about a camera axis."""
    return torch.from_numpy(Rotation.from_euler(axis, degrees, degrees=True).as_matrix()).to(dtype)


def about_point(R: torch.Tensor, c) -> torch.Tensor:
    """T (4,4) rotating by R about the point c (camera coordinates): [R | c - R c]."""
    c = torch.as_tensor(c, dtype=R.dtype)
    return pose_matrix(R[None], (c - R @ c)[None])[0]


def intrinsics(f: float, size: int, B: int, dtype=torch.float32) -> torch.Tensor:
    """K (B,3,3) with focal f px and the principal point at the image centre (integer pixel centres)."""
    c = (size - 1) / 2
    return torch.tensor([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]], dtype=dtype).expand(B, 3, 3).clone()


def make_batch(src: torch.Tensor, tgt: torch.Tensor, T: torch.Tensor, f: float = OBJECT_F, pivot=CENTRE,
               depth: float = 2.0) -> dict:
    """The batch contract from images (B,3,S,S), one pose T (4,4) (or (B,4,4)), focal f and pivot."""
    B, _, S, _ = src.shape
    T = T.expand(B, 4, 4).clone() if T.dim() == 2 else T
    return {"src": src, "tgt": tgt, "K": intrinsics(f, S, B), "T_tgt_src": T.float(),
            "pivot": torch.tensor(pivot, dtype=torch.float32).expand(B, 3).clone(),
            "depth_src": torch.full((B, 1, S, S), float(depth)), "depth_tgt": torch.full((B, 1, S, S), float(depth)),
            "id_src": [f"s{i}" for i in range(B)], "id_tgt": [f"t{i}" for i in range(B)]}


def _yes(flag: bool) -> str:
    return "yes" if flag else "**NO**"


def all_finite(*tensors) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors if t is not None)


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Silence Lightning's and Python's warnings and info logs (the report carries what matters)."""
    loggers = [logging.getLogger(n) for n in ("lightning", "lightning.pytorch", "lightning.fabric")]
    levels = [lg.level for lg in loggers]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for lg, lv in zip(loggers, levels):
                lg.setLevel(lv)


# -- 1. geometry under extremes -------------------------------------------------------------------------------------
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


# -- 2. float64 gradcheck -------------------------------------------------------------------------------------------
@contextlib.contextmanager
def float64_kept() -> Iterator[None]:
    """Make ``Tensor.float()`` leave float64 tensors alone while active.

    The loss terms and the disparity head upcast bf16 with ``.float()``, which also turns float64 into float32; under
    this context a gradcheck failure can only come from a wrong analytic gradient, not from that cast.
    """
    original = torch.Tensor.float

    def keep(self, *args, **kwargs):
        return self if self.dtype == torch.float64 else original(self, *args, **kwargs)

    torch.Tensor.float = keep
    try:
        yield
    finally:
        torch.Tensor.float = original


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
    from nvs.losses import DepthConsistencyLoss, EdgeSmoothLoss, ReconLoss, VGGLoss, WarpLoss
    from nvs.models.depth_head import BoundedDepth, DisparityDepth
    from nvs.models.net import Extras

    g = torch.Generator().manual_seed(seed)
    dt, S = torch.float64, size
    K = intrinsics(6.0, S, 1, dt)
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
    try:
        from nvs.losses_branches import BranchReconLoss
    except ImportError:
        BranchReconLoss = None
    if BranchReconLoss is not None:
        cases.append(GradcheckCase("BranchReconLoss (per-branch L1)", lambda a, b: BranchReconLoss()(
            {"rgb_branches": {"flow": a, "pixel": b}}, batch), (_rand(1, 3, S, S, g=g), _rand(1, 3, S, S, g=g))))
    vgg = VGGLoss().double()
    big = {"tgt": torch.rand(1, 3, 16, 16, generator=g, dtype=dt)}
    cases.append(GradcheckCase("VGGLoss (16x16, random projection)", lambda p: vgg({"rgb": p}, big),
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


# -- 3. precision ---------------------------------------------------------------------------------------------------
def compose(overrides: list[str], out_dir: str):
    """The real train.yaml with overrides, resolved outside a Hydra run."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(config_name="train", overrides=[*overrides, f"paths.root_dir={out_dir}"])
    cfg.paths.output_dir = out_dir
    OmegaConf.resolve(cfg)
    return cfg


def model_options() -> list[tuple[str, list[str], str]]:
    """(label, overrides, data kind) for every model option: nvs with each skip and depth option and the scenes'
    disparity head, and every other conf/model option (with its chairs experiment's losses when there is one)."""
    opts = []
    for skips in sorted(p.stem for p in (CONF_DIR / "model" / "skips").glob("*.yaml")):
        opts.append((f"nvs, skips={skips}", ["model=nvs", f"model/skips={skips}"], "objects"))
    for depth in sorted(p.stem for p in (CONF_DIR / "model" / "depth").glob("*.yaml")):
        if depth != "predicted":
            opts.append((f"nvs, depth={depth}", ["model=nvs", f"model/depth={depth}"], "objects"))
    opts.append(("nvs, data=drive (disparity head)", ["experiment=nvs_drive"], "scenes"))
    for name in sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml")):
        if name in NO_TRAINING_MODELS or name == "nvs":
            continue
        exp = f"{name}_chairs"
        ov = [f"experiment={exp}"] if (CONF_DIR / "experiment" / f"{exp}.yaml").is_file() else [f"model={name}"]
        opts.append((name, ov, "objects"))
    return opts


def blob_images(B: int, S: int, seed: int = 0) -> torch.Tensor:
    """(B,3,S,S) in [0,1]: a few flat coloured rectangles on white, like the rendered objects (not pixel noise, whose
    every sub-pixel shift is a full-range change)."""
    g = torch.Generator().manual_seed(seed)
    img = torch.ones(B, 3, S, S)
    for b in range(B):
        for _ in range(4):
            x0, y0 = torch.randint(0, S // 2, (2,), generator=g).tolist()
            w, h = torch.randint(S // 8, S // 2, (2,), generator=g).tolist()
            img[b, :, y0:y0 + h, x0:x0 + w] = 0.8 * torch.rand(3, 1, 1, generator=g)
    return img


def stress_batch(kind: str, B: int = 2, S: int = 64, seed: int = 0) -> dict:
    """A plausible batch of the data kind ('objects': 20° about the centre, 'scenes': forward motion and yaw)."""
    src, tgt = blob_images(B, S, seed), blob_images(B, S, seed + 1)
    if kind == "scenes":
        T = pose_matrix(rotation("y", 2)[None], torch.tensor([[0.0, 0.0, -0.02]]))[0]
        return make_batch(src, tgt, T, f=SCENE_F, pivot=(0.0, 0.0, 0.0), depth=0.4)
    return make_batch(src, tgt, about_point(rotation("y", 20), CENTRE))


def _forward_backward(module, batch: dict, autocast: tuple[str, torch.dtype] | None):
    """One training step's forward and backward; -> (rgb, depth or None, loss, all finite incl. gradients)."""
    module.zero_grad(set_to_none=True)
    ctx = torch.autocast(autocast[0], dtype=autocast[1]) if autocast else contextlib.nullcontext()
    with ctx:
        out = module(batch, module.train_needs)
        loss = sum(term.weight * term(out, batch) for term in module.losses.values())
    loss.backward()
    grads = [p.grad for p in module.parameters() if p.grad is not None]
    rgb, depth = out["rgb"].detach().float(), out.get("depth")
    depth = depth.detach().float() if depth is not None else None
    finite = all_finite(rgb, depth, loss, *grads) and bool(grads)
    return rgb, depth, loss.detach().float(), finite


def rel_dev(x: torch.Tensor | None, ref: torch.Tensor | None) -> str:
    """'max / mean' of |x - ref| / max |ref| (deviation relative to the output's range); '-' when there is no output."""
    if x is None or ref is None:
        return "-"
    d = (x - ref).abs() / ref.abs().max().clamp_min(1e-12)
    return f"{float(d.max()):.1e} / {float(d.mean()):.1e}"


def _sampled_positions(run: Callable[[], object], size: int) -> torch.Tensor:
    """Pixel positions (B,h,w,2) at which ``run()`` calls ``grid_sample`` (its last call), in float32."""
    from unittest import mock

    from kornia.geometry.conversions import denormalize_pixel_coordinates

    real, seen = torch.nn.functional.grid_sample, {}

    def spy(inp, grid, *args, **kwargs):
        seen["grid"] = grid.detach().float()
        return real(inp, grid, *args, **kwargs)

    with mock.patch.object(torch.nn.functional, "grid_sample", spy):
        run()
    return denormalize_pixel_coordinates(seen["grid"], size, size)


def warp_position_rows(sizes=(64, 256)) -> list[list]:
    """Where the warp samples under bf16 autocast against fp32: max / mean pixel position error.

    Objects camera, 20° about the centre, depth 2..2.3 from the objects' depth head. *projection*:
    ``project_to_source`` alone; *warped skip*: the paper's model's code path, depth head -> ``WarpedSkips`` (conv0)
    -> ``grid_sample``.
    """
    from nvs.geometry import project_to_source
    from nvs.models.depth_head import BoundedDepth
    from nvs.models.skips import WarpedSkips

    rows = []
    for S in sizes:
        g = torch.Generator().manual_seed(0)
        raw = torch.atanh(0.3 * torch.rand(1, 1, S, S, generator=g)).bfloat16().float()  # depth 2..2.3
        K = intrinsics(OBJECT_F * S / 64, S, 1)
        T = about_point(rotation("y", 20), CENTRE)[None]
        head, skips = BoundedDepth(1.0, 3.0), WarpedSkips(levels=("conv0",))
        feats = torch.rand(1, 8, S, S, generator=g)

        uv, _, ok = project_to_source(head(raw), K, T)
        ref = _sampled_positions(lambda: skips({"conv0": feats}, head(raw), K, T), S)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            uv_ac, _, ok_ac = project_to_source(head(raw), K, T)
            # Under autocast the decoder hands over bf16 raw values and bf16 features.
            got = _sampled_positions(lambda: skips({"conv0": feats.bfloat16()}, head(raw.bfloat16()), K, T), S)
        m = ok & ok_ac
        # Pixels invalid in either run sample far outside on purpose (at -(S-1)/2): not a position error.
        inside = m & (ref[..., 0] > -1) & (got[..., 0] > -1)

        def err(x, y, mask):
            d = (x - y)[mask].abs()
            return f"{float(d.max()):.3f} / {float(d.mean()):.3f}"
        rows.append([f"{S}x{S}", err(uv_ac.float(), uv, m), err(got, ref, inside)])
    return rows


def autocast_modes() -> list[tuple[str, torch.dtype]]:
    """bf16 autocast on CPU; fp16 and bf16 on the GPU when one is present."""
    modes = [("cpu", torch.bfloat16)]
    if torch.cuda.is_available():
        modes += [("cuda", torch.float16), ("cuda", torch.bfloat16)]
    return modes


def precision_section(work: str) -> list[list]:
    from nvs.build import build_module

    rows = []
    for label, overrides, kind in model_options():
        try:
            torch.manual_seed(0)
            module = build_module(compose(overrides, work))
            losses = ",".join(module.losses)
        except Exception as err:  # noqa: BLE001 - a model option that does not build is reported, not fatal
            rows.append([label, "-", "-", "-", "-", "-", "-", f"does not build: {err.__class__.__name__}: {err}"[:160]])
            continue
        module.train()
        for device, dtype in autocast_modes():
            try:
                m = module.to(device)
                batch = {k: v.to(device) if torch.is_tensor(v) else v for k, v in stress_batch(kind).items()}
                with quiet():
                    rgb32, d32, l32, ok32 = _forward_backward(m, batch, None)
                    rgb, d, loss, ok = _forward_backward(m, batch, (device, dtype))
                loss_dev = f"{float((loss - l32).abs() / l32.abs()):.1e}"
                rows.append([label, losses, f"{device} {str(dtype).removeprefix('torch.')}", rel_dev(rgb, rgb32),
                             rel_dev(d, d32), loss_dev, f"{_yes(ok32)} / {_yes(ok)}", ""])
            except Exception as err:  # noqa: BLE001
                rows.append([label, losses, f"{device} {dtype}", "-", "-", "-", "-",
                             f"{err.__class__.__name__}: {err}"[:160]])
        module.to("cpu")
    return rows


# -- 4. training under stress ---------------------------------------------------------------------------------------
def adversarial_batches(S: int = 64, B: int = 2, seed: int = 0) -> dict[str, Callable[[int], dict]]:
    """name -> step -> batch: constant and textureless images, extreme poses and focal lengths."""

    def rand(step, k):
        return torch.rand(B, 3, S, S, generator=torch.Generator().manual_seed(seed + 7919 * step + k))

    def random_rotation(step):
        rv = Rotation.random(random_state=seed + step).as_rotvec()
        rv *= math.pi / max(np.linalg.norm(rv), 1e-9) * ((step % 4 + 1) / 4)  # angles up to 180°
        return torch.from_numpy(Rotation.from_rotvec(rv).as_matrix()).float()

    obj20 = about_point(rotation("y", 20), CENTRE)
    zeros, ones = torch.zeros(B, 3, S, S), torch.ones(B, 3, S, S)
    return {
        "constant black images": lambda i: make_batch(zeros, zeros, obj20),
        "constant white images": lambda i: make_batch(ones, ones, obj20),
        "textureless grey source, random target": lambda i: make_batch(0.5 * ones, rand(i, 1), obj20),
        "180° rotation about the object": lambda i: make_batch(rand(i, 0), rand(i, 1),
                                                               about_point(rotation("y", 180), CENTRE)),
        "random rotations up to 180°": lambda i: make_batch(rand(i, 0), rand(i, 1),
                                                            about_point(random_rotation(i), CENTRE)),
        "translation 1e3 (no valid warp)": lambda i: make_batch(rand(i, 0), rand(i, 1),
                                                                pose_matrix(torch.eye(3)[None],
                                                                            torch.tensor([[1e3, 0.0, 1e3]]))[0]),
        "near-singular pose (R scaled 1e-6)": lambda i: make_batch(rand(i, 0), rand(i, 1), pose_matrix(
            (rotation("y", 30) * 1e-6)[None], torch.tensor([[0.0, 0.0, 1.0]]))[0]),
        "focal 1 px": lambda i: make_batch(rand(i, 0), rand(i, 1), obj20, f=1.0),
        "focal 1e5 px": lambda i: make_batch(rand(i, 0), rand(i, 1), obj20, f=1e5),
    }


@dataclass
class StressRun:
    """What a stress training run saw: losses per step and the first non-finite event."""

    losses: list[float] = field(default_factory=list)
    nonfinite_loss: int = 0
    nonfinite_grad: int = 0
    nonfinite_param: int = 0
    error: str = ""


def train_under_stress(module, batches: Callable[[int], dict], steps: int, lr: float = 1e-3,
                       autocast: torch.dtype | None = None) -> StressRun:
    """Adam steps on ``batches(step)`` with anomaly detection (and CPU autocast to ``autocast`` if given); counts steps
    with a non-finite loss, gradient or weight."""
    opt = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=lr)
    run = StressRun()
    module.train()
    for step in range(steps):
        batch = batches(step)
        opt.zero_grad(set_to_none=True)
        amp = torch.autocast("cpu", dtype=autocast) if autocast else contextlib.nullcontext()
        try:
            with torch.autograd.set_detect_anomaly(True), quiet():
                with amp:
                    out = module(batch, module.train_needs)
                    loss = sum(term.weight * term(out, batch) for term in module.losses.values())
                loss.backward()
        except RuntimeError as err:  # anomaly detection names the backward op that produced NaN
            run.error = f"step {step}: {str(err).splitlines()[0][:150]}"
            break
        value = float(loss.detach())
        run.losses.append(value)
        run.nonfinite_loss += not math.isfinite(value)
        run.nonfinite_grad += not all_finite(*(p.grad for p in module.parameters() if p.grad is not None))
        opt.step()
        run.nonfinite_param += not all_finite(*module.parameters())
    return run


def stress_configs(steps: int) -> list[tuple[str, list[str], str, int, torch.dtype | None]]:
    """(label, overrides, batch family, steps per batch kind, autocast dtype) of the modules trained under stress.

    The paper's model gets ``steps`` per kind (half under bf16 autocast), its one-kind families three times that, the
    baselines a third.
    """
    no_vgg = "loss=[recon,depth_consistency,edge_smooth,warp]"
    opts = [
        ("nvs (depth 1..3)", ["model=nvs", no_vgg], "all", steps, None),
        ("nvs under bf16 autocast (depth 1..3)", ["model=nvs", no_vgg], "all", max(1, steps // 2), torch.bfloat16),
        ("nvs + vgg (depth 1..3)", ["model=nvs"], "constant", steps, None),
        ("nvs, tiny depth range 1e-4..2e-4", ["model=nvs", no_vgg, "data.depth_head.min_depth=1e-4",
                                              "data.depth_head.max_depth=2e-4"],
         "tiny", 3 * steps, None),
        ("nvs, huge depth range 1e-4..1e4 (disparity)", ["experiment=nvs_drive", no_vgg,
                                                         "data.depth_head.max_disparity=1e4",
                                                         "data.depth_head.min_disparity=1e-4"], "huge", 3 * steps,
         None),
    ]
    for name in sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml")):
        if name in NO_TRAINING_MODELS or name == "nvs":
            continue
        exp = f"{name}_chairs"
        ov = [f"experiment={exp}"] if (CONF_DIR / "experiment" / f"{exp}.yaml").is_file() else [f"model={name}"]
        opts.append((name, ov, "all", max(1, steps // 3), None))
    return opts


def batch_family(family: str) -> list[tuple[str, Callable[[int], dict]]]:
    """(name, step -> batch) for 'all' adversarial kinds, the 'constant' images, or the depth-range families
    ('tiny': an object 1.5e-4 from the camera; 'huge': scene motion from 1e-3 to 1e3)."""
    adv = adversarial_batches()
    if family == "all":
        return list(adv.items())
    if family == "constant":
        return [(k, adv[k]) for k in ("constant black images", "constant white images")]
    if family == "tiny":
        def tiny(i):
            b = adv["random rotations up to 180°"](i)
            c = torch.tensor([0.0, 0.0, 1.5e-4])
            R = b["T_tgt_src"][0, :3, :3]
            b["T_tgt_src"] = about_point(R, c).expand_as(b["T_tgt_src"]).clone()
            b["pivot"] = c.expand_as(b["pivot"]).clone()
            return b
        return [("rotations up to 180° about a centre at 1.5e-4", tiny)]

    def huge(i):
        g = torch.Generator().manual_seed(i)
        t = torch.tensor([[0.0, 0.0, -float(10 ** (i % 7 - 3))]])  # 1e-3 .. 1e3 forward motion
        return make_batch(torch.rand(2, 3, 64, 64, generator=g), torch.rand(2, 3, 64, 64, generator=g),
                          pose_matrix(rotation("y", 3 * (i % 5))[None], t)[0], f=SCENE_F, pivot=(0.0, 0.0, 0.0))
    return [("scene motion 1e-3..1e3 with yaw", huge)]


def training_section(work: str, steps_per_kind: int) -> tuple[list[list], int]:
    from nvs.build import build_module

    rows, total = [], 0
    for label, overrides, family, n, autocast in stress_configs(steps_per_kind):
        try:
            torch.manual_seed(0)
            module = build_module(compose(overrides, work))
        except Exception as err:  # noqa: BLE001
            rows.append([label, "-", 0, "-", "-", "-", "-", f"does not build: {err.__class__.__name__}: {err}"[:160]])
            continue
        for kind, batches in batch_family(family):
            run = train_under_stress(module, batches, n, autocast=autocast)
            total += len(run.losses)
            finite_losses = [v for v in run.losses if math.isfinite(v)]
            span = f"{run.losses[0]:.3g} → {run.losses[-1]:.3g}" if run.losses else "-"
            rows.append([label, kind, len(run.losses), span,
                         f"{max(finite_losses):.3g}" if finite_losses else "-",
                         run.nonfinite_loss, f"{run.nonfinite_grad} / {run.nonfinite_param}", run.error])
    return rows, total


# -- 5. determinism -------------------------------------------------------------------------------------------------
def write_objects_dataset(root: Path, models=("m0", "m1", "m2", "m3"), size: int = 64, seed: int = 0) -> Path:
    """A tiny dataset in the objects format: coloured rectangles on white, constant depth 2, last model = test."""
    from PIL import Image

    from nvs.data.shapenet import AZIMUTHS, ELEVATIONS

    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    for m in models:
        for a in AZIMUTHS:
            for e in ELEVATIONS:
                img = np.full((size, size, 3), 255, np.uint8)
                for _ in range(3):
                    x0, y0 = rng.integers(0, size // 2, 2)
                    w, h = rng.integers(size // 8, size // 2, 2)
                    img[y0:y0 + h, x0:x0 + w] = rng.integers(0, 200, 3)
                Image.fromarray(img).save(root / "images" / f"{m}_{a}_{e}.png")
                np.save(root / "depth" / f"{m}_{a}_{e}.npy", np.full((size, size), 2.0, np.float32))
    (root / "id_train.txt").write_text("\n".join(models[:-1]) + "\n")
    test = models[-1]
    pairs = [f"{test}_{a}_0 {test}_{(a + 20) % 360}_10" for a in (0, 40, 80, 120)]
    (root / "eval_chair_40.txt").write_text("\n".join(pairs) + "\n")
    return root


DETERMINISM_STEPS = 4


def determinism_run(data_root: Path, out_dir: Path, seed: int, steps: int = DETERMINISM_STEPS) -> dict:
    """A short nvs.train run (train, validate, test) on the fixture dataset -> its test metrics."""
    from nvs.train import run

    cfg = compose([f"data.root={data_root}", f"seed={seed}", f"trainer.max_steps={steps}",
                   f"trainer.val_check_interval={steps // 2}", "data.loader.batch_size=2",
                   "loss=[recon,warp]", "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1"],
                  str(out_dir))
    with quiet(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return run(cfg, out_dir)["test"]


def determinism_section(work: str) -> list[list]:
    root = write_objects_dataset(Path(work) / "chairs_64")
    a = determinism_run(root, Path(work) / "det_a", seed=0)
    b = determinism_run(root, Path(work) / "det_b", seed=0)
    c = determinism_run(root, Path(work) / "det_c", seed=1)
    keys = [k for k in a if k != "n_pairs"]
    same = [k for k in keys if a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k]))]
    differ = [k for k in keys if a[k] != c[k]]
    return [["seed 0 vs seed 0", f"{len(same)}/{len(keys)} bitwise equal", f"l1 {a['l1']:.6f} vs {b['l1']:.6f}"],
            ["seed 0 vs seed 1 (control)", f"{len(differ)}/{len(keys)} differ", f"l1 {a['l1']:.6f} vs {c['l1']:.6f}"]]


# -- report ---------------------------------------------------------------------------------------------------------
def table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        return _yes(v) if isinstance(v, bool) else str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def provenance(argv: list[str]) -> str:
    from nvs.build import device_name, git_sha

    cmd = " ".join(shlex.quote(a) for a in ["python", "-m", "nvs.stress", *argv])
    date = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f"Command: `{cmd}`  \nGit SHA: `{git_sha()}`  \nDate: {date}  \nDevice: {device_name()}  \n"
            f"torch {torch.__version__}")


SECTIONS = ("geometry", "gradcheck", "precision", "training", "determinism")


def main(argv: list[str] | None = None) -> str:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(prog="python -m nvs.stress", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "results" / "stress.md"), help="report path (Markdown)")
    ap.add_argument("--steps", type=int, default=12,
                    help="training steps of the paper's model per adversarial batch kind (baselines: a third)")
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {SECTIONS}")
    args = ap.parse_args(argv)
    wanted = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = sorted(set(wanted) - set(SECTIONS))
    if unknown:
        ap.error(f"unknown sections {unknown}; choose from {SECTIONS}")

    torch.manual_seed(0)
    parts = ["# Numerical stress report", "", "Generated by `nvs.stress`; do not edit by hand.", "", provenance(argv)]
    timings = []
    with tempfile.TemporaryDirectory(prefix="nvs-stress-") as work:
        def section(name: str, title: str, intro: str, body: Callable[[], str]) -> None:
            if name not in wanted:
                return
            t0 = time.perf_counter()
            print(f"[stress] {name} ...", flush=True)
            text = body()
            timings.append((name, time.perf_counter() - t0))
            parts.extend(["", f"## {title}", "", intro, "", text])

        section("geometry", "1. Geometry under extremes",
                "`inverse_warp` on a 16x16 random image (B=2, f=20 px unless stated) with gradients of a non-linear "
                "read-out w.r.t. image, depth, K and pose. *Masked*: every invalid pixel of the output is exactly 0. "
                "Non-finite depth is outside the batch contract (depth <= 0 means no data); it is listed to show "
                "what leaks.",
                lambda: table(["case", "finite out", "finite grad (image, depth)", "finite grad (K, pose)",
                               "invalid masked", "valid fraction", "note"], geometry_section()))
        section("gradcheck", "2. float64 gradcheck",
                "`torch.autograd.gradcheck` (eps 1e-6, atol 1e-5, rtol 1e-3) on float64 inputs. *As is*: the code "
                "unchanged. *float64 kept*: with `Tensor.float()` leaving float64 alone, which separates a wrong "
                "analytic gradient from a float64 -> float32 cast inside the function.",
                lambda: table(["function", "as is", "float64 kept", "first failure line"], gradcheck_section()))
        section("precision", "3. Precision: autocast against fp32",
                "One training forward and backward (train mode, B=2, 64x64, the option's losses, images of flat "
                "rectangles on white) in fp32 and under autocast, same weights and batch. Deviation = |x - x_fp32| / "
                "max |x_fp32|, max / mean over pixels; the max sits on rectangle edges that a slightly different "
                "depth moves by a fraction of a pixel. *Finite*: outputs, loss and every parameter gradient "
                "(fp32 / autocast).",
                lambda: table(["model option", "losses", "autocast", "rgb dev. max / mean", "depth dev. max / mean",
                               "loss rel. dev.", "finite (fp32 / autocast)", "note"], precision_section(work))
                + "\n\nWhere the warp samples under bf16 autocast, against fp32 (objects camera, depth 2..2.3 from "
                "the objects' depth head, 20° about the centre): pixel position error, max / mean. *Projection*: "
                "`project_to_source` alone on fp32 inputs inside autocast; *warped skip*: the paper's code path, "
                "bf16 raw depth -> depth head -> `WarpedSkips` on bf16 features -> the grid given to `grid_sample`."
                "\n\n" + table(["size", "projection (px)", "warped skip (px)"], warp_position_rows()))
        if "training" in wanted:
            t0 = time.perf_counter()
            print("[stress] training ...", flush=True)
            rows, total = training_section(work, args.steps)
            timings.append(("training", time.perf_counter() - t0))
            parts.extend(["", "## 4. Training under stress", "",
                          f"{total} Adam steps in all (lr 1e-3, 10x the paper's), B=2, 64x64, "
                          "`torch.autograd.set_detect_anomaly(True)`; each module keeps training across its batch "
                          "kinds in order; one runs under bf16 autocast. Counts are steps with a non-finite value; "
                          "*error* is what anomaly detection raised, if anything.", "",
                          table(["module", "batches", "steps", "loss first → last", "max loss", "non-finite loss",
                                 "non-finite grad / weights", "error"], rows)])
        section("determinism", "5. Determinism",
                f"Three short `nvs.train.run` runs of the paper's model ({DETERMINISM_STEPS} steps with "
                "`loss=[recon,warp]`, validation, test on 4 pairs) on a generated 4-model objects dataset, CPU: the "
                "same seed twice, then another seed as a control that the comparison can fail.",
                lambda: table(["comparison", "test metrics", "example"], determinism_section(work)))
    total_s = sum(t for _, t in timings)
    parts.extend(["", "## Runtime", "", table(["section", "seconds"], [[n, f"{t:.1f}"] for n, t in timings]
                                             + [["total", f"{total_s:.1f}"]])])
    text = "\n".join(parts) + "\n"
    write_text(args.out, text)
    print(f"wrote {args.out} ({total_s:.0f} s)")
    return text


if __name__ == "__main__":
    main()
