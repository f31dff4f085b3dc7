"""Report section 3: one training forward and backward under autocast against fp32, and where the warp samples."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch

from nvs.data.synthetic import about_point, intrinsics, rotation
from nvs.stress.batches import CENTRE, OBJECT_F, stress_batch
from nvs.stress.harness import all_finite, quiet, yes
from nvs.stress.options import model_options, train_config


def forward_backward(module, batch: dict, autocast: tuple[str, torch.dtype] | None):
    """One training step's forward and backward; -> (rgb, depth or None, loss, all finite incl. gradients)."""
    module.zero_grad(set_to_none=True)
    ctx = torch.autocast(autocast[0], dtype=autocast[1]) if autocast else contextlib.nullcontext()
    with ctx:
        out = module(batch, module.train_needs)
        loss, _ = module.loss(out, batch)
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
    from nvs.core.geometry import project_to_source
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
    from nvs.run.build import build_module

    rows = []
    for label, overrides, kind in model_options():
        try:
            torch.manual_seed(0)
            module = build_module(train_config(overrides, work))
            losses = ",".join(module.losses)
        except Exception as err:  # noqa: BLE001 - a model option that does not build is reported, not fatal
            rows.append([label, "-", "-", "-", "-", "-", "-", f"does not build: {err.__class__.__name__}: {err}"[:160]])
            continue
        module.train()
        for device, dtype in autocast_modes():
            try:
                m = module.to(device)
                batch = stress_batch(kind)
                batch = {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}
                with quiet():
                    rgb32, d32, l32, ok32 = forward_backward(m, batch, None)
                    rgb, d, loss, ok = forward_backward(m, batch, (device, dtype))
                loss_dev = f"{float((loss - l32).abs() / l32.abs()):.1e}"
                rows.append([label, losses, f"{device} {str(dtype).removeprefix('torch.')}", rel_dev(rgb, rgb32),
                             rel_dev(d, d32), loss_dev, f"{yes(ok32)} / {yes(ok)}", ""])
            except Exception as err:  # noqa: BLE001
                rows.append([label, losses, f"{device} {dtype}", "-", "-", "-", "-",
                             f"{err.__class__.__name__}: {err}"[:160]])
        module.to("cpu")
    return rows
