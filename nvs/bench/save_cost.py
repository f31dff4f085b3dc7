"""python -m nvs.bench.save_cost [--model nvs] [--size 64] [--dir runs/bench] [--repeats 5]: what one ``last.ckpt``
costs, and what the per-step non-finite guard costs, for a model at a size.

A checkpoint here is what Lightning writes for the run: the module's state_dict (frozen loss networks left out, as
``NVSModule.on_save_checkpoint`` does) and Adam's state after one step. Each save is timed as training pays it: the
content hash, ``torch.save`` to memory, then the atomic write (temp file, fsync, rename). Medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import io
import statistics
import time
from pathlib import Path

import torch

from nvs.core.atomic import write_bytes
from nvs.core.weights_digest import digest
from nvs.data.synthetic import synthetic_batch
from nvs.module.lightning_module import all_finite
from nvs.run.build import build_module
from nvs.run.cli import exits_cleanly
from nvs.run.compose import compose


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def measure(model: str, size: int, directory: Path, repeats: int) -> dict:
    """Milliseconds per part of one save, the checkpoint's MB, and the guard's ms per step."""
    cfg = compose("train", [f"model={model}", f"data.size={size}", "paths.output_dir=.", "loss=[recon_final]"])
    module = build_module(cfg)
    optimizer = torch.optim.Adam(module.net.parameters(), lr=1e-4)
    batch = synthetic_batch(2, size, "objects", "random", 0)
    total, _ = module.loss(module(batch, module.train_needs), batch)
    total.backward()
    optimizer.step()  # Adam's moments exist: the checkpoint holds them
    ckpt = {"state_dict": {k: v for k, v in module.state_dict().items() if not k.startswith("losses.")},
            "optimizer_states": [optimizer.state_dict()], "global_step": 1}
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "save_cost.ckpt"
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    data = buf.getvalue()
    params = [p.detach() for p in module.net.parameters()]
    grads = [p.grad for p in module.net.parameters() if p.grad is not None]
    out = {
        "model": model, "size": size, "checkpoint_mb": len(data) / 2**20,
        "hash_ms": _median_ms(lambda: digest(ckpt["state_dict"]), repeats),
        "serialize_ms": _median_ms(lambda: torch.save(ckpt, io.BytesIO()), repeats),
        "write_fsync_rename_ms": _median_ms(lambda: write_bytes(path, data), repeats),
        "guard_ms_per_step": _median_ms(lambda: (all_finite(grads), all_finite(params)), max(repeats, 20)),
    }
    out["save_ms"] = out["hash_ms"] + out["serialize_ms"] + out["write_fsync_rename_ms"]
    path.unlink(missing_ok=True)
    return out


@exits_cleanly
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m nvs.bench.save_cost", description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="nvs")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--dir", default="runs/bench", help="where the checkpoint is written (the run's disk)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    r = measure(args.model, args.size, Path(args.dir), args.repeats)
    print(f"{r['model']} {r['size']}x{r['size']}: checkpoint {r['checkpoint_mb']:.1f} MB; "
          f"one save {r['save_ms']:.0f} ms "
          f"(hash {r['hash_ms']:.0f}, serialize {r['serialize_ms']:.0f}, write+fsync+rename "
          f"{r['write_fsync_rename_ms']:.0f}); non-finite guard {r['guard_ms_per_step']:.2f} ms per step "
          f"({torch.get_num_threads()} CPU threads)")


if __name__ == "__main__":
    main()
