"""python -m nvs.convert <dir or files> [--data chairs|cars|kitti] [--epoch E] [--out F]: the authors' checkpoints
as an nvs checkpoint.

The authors' code saves one plain ``state_dict`` per network, ``<epoch>_net_enc.pth``, ``<epoch>_net_dec.pth`` and
``<epoch>_net_depthdec.pth`` (their networks at 256^2). The output holds the weights of ``model=nvs`` with every
fidelity switch at the code's setting and the resolved run config, so ``nvs.evaluate``, the viewer and the sweeps
load it like a checkpoint nvs trained. Every missing, unexpected or misshapen key is one error naming file and key.
"""

from __future__ import annotations

import argparse
import io
import re
import sys
from pathlib import Path

import torch

from nvs.core.errors import UserError

from nvs.run.cli import exits_cleanly

NETWORKS = ("enc", "dec", "depthdec")
PREFIX = {"enc": "net.encoder.", "dec": "net.pixel_decoder.", "depthdec": "net.depth.decoder."}
SIZE = 256  # the authors' networks are built for 256^2 (six encoder stages to 4x4)
_CONV = ("weight", "bias")
_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def _layers(net: str) -> list[tuple[str, str, tuple[str, ...]]]:
    """(authors' layer, nvs layer, parameter names) of one network at 256^2 with all four skip levels."""
    if net == "enc":
        pairs = [("conv0.0", "conv0.0.0"), ("conv0.3", "conv0.1.0")]
        pairs += [(f"conv{i}.0", f"conv{i}.0") for i in range(1, 5)]
        pairs += [("conv5.0", "extra.0.0"), ("conv6.0", "extra.1.0"), ("fc.0", "fc")]
        return [(a, b, _CONV) for a, b in pairs]
    if net == "dec":
        pairs = [("fc.0", "trunk.fc"), ("deconv1.0", "trunk.stages.0.conv"), ("deconv2.0", "trunk.stages.1.conv"),
                 ("deconv3.2", "trunk.stages.2.conv"), ("deconv4.2", "trunk.stages.3.conv"),
                 ("deconv5.2", "up8.conv"), ("deconv6.2", "up4.conv"), ("deconv7.2", "up2.conv"),
                 ("deconv8.2", "up1.conv"), ("deconv9.0", "fuse1.0"), ("pred1", "rgb8"), ("pred2", "rgb4"),
                 ("pred3", "rgb2"), ("finalup.0", "res1"), ("finalpred", "rgb1")]
        return [(a, b, _CONV) for a, b in pairs]
    # depthDecoder: one Sequential; transposed stages are [ConvT, BN, act], bilinear ones [Up, Pad, Conv, BN, act].
    out = [("fc.0", "trunk.fc", _CONV)]
    nvs_stages = [f"trunk.stages.{i}" for i in range(4)] + [f"stages.{i}" for i in range(4)]
    index = 0
    for i, name in enumerate(nvs_stages):
        conv = index if i < 2 else index + 2
        out += [(f"deconv.{conv}", f"{name}.conv", _CONV), (f"deconv.{conv + 1}", f"{name}.norm", _BN)]
        index += 3 if i < 2 else 5
    out.append((f"deconv.{index}", "out", _CONV))
    return out


def key_map(net: str) -> dict[str, str]:
    """Authors' state-dict key -> nvs module state-dict key, for one of ``NETWORKS``."""
    return {f"{a}.{p}": f"{PREFIX[net]}{b}.{p}" for a, b, params in _layers(net) for p in params}


def find_files(paths: list[str], epoch: str | None) -> dict[str, Path]:
    """The three per-network files from directories and/or files; one epoch, chosen or the only one there."""
    found: dict[str, dict[str, Path]] = {}
    pattern = re.compile(r"^(?P<epoch>.+)_net_(?P<net>enc|dec|depthdec)\.pth$")
    for raw in paths:
        p = Path(raw)
        if not p.exists():
            raise UserError(f"{p}: no such file or directory")
        for f in (sorted(p.iterdir()) if p.is_dir() else [p]):
            m = pattern.match(f.name)
            if m:
                found.setdefault(m["epoch"], {})[m["net"]] = f
            elif p.is_file():
                raise UserError(f"{f}: not an authors' checkpoint name (<epoch>_net_{{enc,dec,depthdec}}.pth)")
    if not found:
        raise UserError(f"{', '.join(paths)}: no <epoch>_net_{{enc,dec,depthdec}}.pth files")
    if epoch is None:
        if len(found) > 1:
            raise UserError(f"{', '.join(paths)}: several epochs ({', '.join(sorted(found))}); choose one with --epoch")
        epoch = next(iter(found))
    if epoch not in found:
        raise UserError(f"{', '.join(paths)}: no files of epoch {epoch!r} (found: {', '.join(sorted(found))})")
    files = found[epoch]
    missing = [n for n in NETWORKS if n not in files]
    if missing:
        raise UserError(f"{', '.join(paths)}: epoch {epoch!r} lacks {', '.join(f'{epoch}_net_{n}.pth' for n in missing)}")
    return files


def _read(path: Path) -> dict[str, torch.Tensor]:
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure is a bad file for the user
        # torch's message spans several lines (with terminal colour codes): keep what names the cause.
        text = re.sub(r"\x1b\[[0-9;]*m", "", str(err))
        pickled = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
        if pickled:
            raise UserError(f"{path}: not a plain state_dict: it pickles the Python object {pickled[1]} (a whole "
                            "network?); save net.state_dict() instead") from None
        first = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
        raise UserError(f"{path}: not a readable state_dict ({err.__class__.__name__}: {first})") from None
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise UserError(f"{path}: not a plain state_dict of tensors")
    return sd


def convert_state(files: dict[str, Path], target: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The nvs network weights from the three files; ``target`` is the nvs module's own state_dict (shapes)."""
    out = {}
    for net in NETWORKS:
        path, mapping = files[net], key_map(net)
        sd = _read(path)
        for key in sd:
            if key not in mapping:
                raise UserError(f"{path}: unexpected key '{key}' (not in the authors' {net} network at 256x256)")
        for key, nvs_key in mapping.items():
            if key not in sd:
                raise UserError(f"{path}: missing key '{key}'")
            want = target[nvs_key].shape
            if sd[key].shape != want:
                raise UserError(f"{path}: key '{key}' has shape {tuple(sd[key].shape)}, nvs expects {tuple(want)}")
            out[nvs_key] = sd[key].to(target[nvs_key].dtype)
    return out


def convert(paths: list[str], data: str = "chairs", epoch: str | None = None, out: str | None = None,
            overrides: tuple[str, ...] = ()) -> Path:
    """Write the nvs checkpoint; returns its path (default: beside the inputs, ``<epoch>_nvs.ckpt``)."""
    from nvs.core.atomic import reason, write_bytes
    from nvs.core.weights_digest import stamp
    from nvs.run.build import build_module
    from nvs.run.compose import compose

    if out:  # before minutes of building and converting: the output must have somewhere to go
        _check_out(Path(out))
    files = find_files(paths, epoch)
    epoch = files["enc"].name.split("_net_")[0]
    cfg = compose("train", [f"data={data}", "model=nvs", "fidelity=code", f"data.size={SIZE}", "paths.output_dir=.",
                            *overrides])
    module = build_module(cfg)
    own = {k: v for k, v in module.state_dict().items() if not k.startswith("losses.")}
    weights = convert_state(files, own)
    left = sorted(set(own) - set(weights))
    if left:  # nvs holds weights the authors' network has not: the overrides changed the architecture
        raise UserError(f"model=nvs with {list(overrides)} has weights the authors' network lacks (e.g. {left[0]})")
    dest = Path(out) if out else files["enc"].parent / f"{epoch}_nvs.ckpt"
    ckpt = {"state_dict": weights, "nvs_config": module.run_config,
            "converted_from": {n: str(files[n]) for n in NETWORKS}, "epoch": 0, "global_step": 0}
    stamp(ckpt)  # checked on every load, like a checkpoint nvs trained
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    try:
        write_bytes(dest, buf.getvalue())
    except OSError as err:
        raise UserError(f"--out {dest}: cannot write ({reason(err)})") from None
    return dest


def _check_out(out: Path) -> None:
    """``--out`` names a file in an existing folder (no folder is created for it)."""
    if out.is_dir():
        raise UserError(f"--out {out}: is a directory; give the checkpoint's file name (e.g. {out / 'nvs.ckpt'})")
    if not out.parent.is_dir():
        raise UserError(f"--out {out}: the folder {out.parent} does not exist (create it first)")


@exits_cleanly
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m nvs.convert", description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="a directory holding <epoch>_net_*.pth, or the three files")
    ap.add_argument("--data", default="chairs", help="data config the network was trained for: chairs|cars|kitti")
    ap.add_argument("--epoch", default=None, help="which <epoch> to read when the directory holds several")
    ap.add_argument("--out", default=None, help="output checkpoint (default: <dir>/<epoch>_nvs.ckpt)")
    args = ap.parse_args(argv)
    dest = convert(args.paths, data=args.data, epoch=args.epoch, out=args.out)
    print(f"wrote {dest} (model=nvs, data={args.data}, fidelity=code, {SIZE}x{SIZE}); evaluate it with "
          f"python -m nvs.evaluate ckpt_path={dest}")


if __name__ == "__main__":
    main(sys.argv[1:])
