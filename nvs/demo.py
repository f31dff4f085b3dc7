"""python -m nvs.demo: render the embedded chairs (if needed), train the full model, evaluate it next to copying
the source image, and print where the run directory is. The README's `make demo` runs this."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from nvs.metric_spec import IMAGE_METRICS, SPECS

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str]) -> None:
    print("$ " + " ".join(args), flush=True)
    subprocess.run(args, cwd=ROOT, check=True)


def main(size: int = 64, experiment: str = "demo") -> None:
    t0 = time.perf_counter()
    data = ROOT / "data" / f"chairs_{size}"
    if not (data / "meta.json").is_file():
        _run([sys.executable, "-m", "nvs.data.render", "chairs", f"size={size}", f"out={data}"])
    t_render = time.perf_counter() - t0
    runs = ROOT / "runs" / "demo"
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    run_dir = runs / stamp
    _run([sys.executable, "-m", "nvs.train", f"experiment={experiment}", f"data.root={data}",
          f"hydra.run.dir={run_dir}"])
    copy_dir = run_dir / "copy_source"
    _run([sys.executable, "-m", "nvs.evaluate", "model=copy_source", "data=chairs", f"data.root={data}",
          f"data.size={size}", f"out_dir={copy_dir}", f"hydra.run.dir={copy_dir}"])
    ours = json.loads((run_dir / "metrics.json").read_text())
    copy = json.loads((copy_dir / "metrics.json").read_text())
    print()
    print(f"chairs {size}x{size}, {ours['test']['n_pairs']} test pairs, {ours['steps']} training steps "
          f"({ours['train_wall_s'] / 60:.1f} min train, {ours['train_samples_per_s']:.1f} samples/s)")
    print(f"{'model':<14}" + "".join(f"{SPECS[k].label + ' ' + SPECS[k].arrow:>15}" for k in IMAGE_METRICS))
    for name, m in (("copy source", copy), ("nvs (ours)", ours)):
        print(f"{name:<14}" + "".join(f"{SPECS[k].format(m['test'][k]):>15}" for k in IMAGE_METRICS))
    ratio = ours["test"]["l1"] / copy["test"]["l1"]
    print(f"\nL1 of ours / copy source = {ratio:.2f}  (lower is better; paper's L1 is on [-1,1])")
    print(f"render {t_render / 60:.1f} min, total {(time.perf_counter() - t0) / 60:.1f} min")
    print(f"run directory: {run_dir}")


if __name__ == "__main__":
    main()
