"""python -m nvs.demo: render the embedded chairs (if needed), train the full model, evaluate it next to copying
the source image, and print where the run directory is. The README's `make demo` runs this."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from nvs.core.metric_spec import IMAGE_METRICS, SPECS
from nvs.run.overrides import hydra_value



def root() -> Path:
    """Where data/ and runs/ go: the checkout the package runs from, or the current directory (an installed one)."""
    here = Path(__file__).resolve().parents[1]
    return here if (here / "pyproject.toml").is_file() else Path.cwd()


# The demo's steps are chosen by time, from this machine's measured step (at most the experiment's max_steps): the
# whole demo (render, training, evaluations) gets DEMO_MINUTES, and training what is left of it after the render
# took its time and the rest of the demo (the step's measurement, the processes' start, the test and copying's
# evaluation: EVAL_MINUTES, measured on the 2-core CPUs) is set aside. With `make setup`'s ~2-2.6 min on a fresh
# machine, `make demo` stays within 12 min where bf16 is native (or on a GPU) and within 15 min where it is emulated
# (fp32 there, at ~3x the step time: fewer steps). A slow render leaves less to training, not more to the total.
DEMO_MINUTES = {"native": 8.7, "emulated": 12.0}
EVAL_MINUTES = {"native": 1.3, "emulated": 2.0}
OVERHEAD = 1.15  # the loader, logging and two short validations on top of the bench's step (measured ~10%)
MIN_STEPS = 100


def train_minutes(machine: str, elapsed_s: float) -> float:
    """The training budget of a ``machine`` class ("native" or "emulated" bf16) after ``elapsed_s`` of rendering."""
    return max(0.0, DEMO_MINUTES[machine] - EVAL_MINUTES[machine] - elapsed_s / 60)


def _run(args: list[str]) -> None:
    print("$ " + " ".join(args), flush=True)
    subprocess.run(args, cwd=root(), check=True)


def planned_steps(experiment: str, size: int, minutes: float | None = None,
                  elapsed_s: float = 0.0) -> tuple[int, str]:
    """The steps that fit the training budget on this machine (``minutes``, or what the demo's budget leaves after
    ``elapsed_s``), and the line that says why."""
    import torch

    from nvs.bench.contenders import make_batches, nvs_contender
    from nvs.bench.measure import interleaved
    from nvs.run.compose import compose
    from nvs.run.precision import choose

    cfg = compose("train", [f"experiment={experiment}"])
    max_steps, batch = int(cfg.trainer.max_steps), int(cfg.data.loader.batch_size)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    choice = choose("auto", "auto", device.type)
    if minutes is None:
        machine = "native" if choice.mode.startswith("bf16") or device.type == "cuda" else "emulated"
        minutes = train_minutes(machine, elapsed_s)
    batches = make_batches(size, batch, 1, None, device)
    contender = nvs_contender([f"experiment={experiment}"], choice.mode, batches, device, str(root()), size)
    step_s = interleaved({"step": contender.train}, device, 1, 3)["step"]["median_ms"] / 1000 * OVERHEAD
    steps = max(MIN_STEPS, min(max_steps, int(60 * minutes / step_s)))
    return steps, (f"demo: a training step takes ~{step_s:.2f} s here ({choice.mode}, measured): {steps} steps "
                   f"fit the {minutes:.1f}-min training budget (the experiment's {max_steps} at most, "
                   f"{MIN_STEPS} at least)")


def main(size: int = 64, experiment: str = "demo") -> None:
    try:
        _demo(size, experiment)
    except subprocess.CalledProcessError as err:  # the child said why; keep its exit code (130, 143, 2)
        code = err.returncode if err.returncode > 0 else 128 - err.returncode
        print(f"demo stopped: {err.cmd[2] if len(err.cmd) > 2 else err.cmd} exited {code}", file=sys.stderr)
        sys.exit(code)
    except KeyboardInterrupt:
        sys.exit(130)


def _demo(size: int, experiment: str) -> None:
    t0 = time.perf_counter()
    data = root() / "data" / f"chairs_{size}"
    if not (data / "meta.json").is_file():
        _run([sys.executable, "-m", "nvs.data.render", "chairs", f"size={size}", f"out={data}"])
    t_render = time.perf_counter() - t0
    steps, why = planned_steps(experiment, size, elapsed_s=t_render)
    print(why, flush=True)
    runs = root() / "runs" / "demo"
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    run_dir = runs / stamp
    # Hydra-quoted: a checkout under a path with spaces or non-ASCII letters still parses
    _run([sys.executable, "-m", "nvs.train", f"experiment={experiment}", f"data.root={hydra_value(str(data))}",
          f"hydra.run.dir={hydra_value(str(run_dir))}", f"trainer.max_steps={steps}",
          f"trainer.val_check_interval={steps // 2}"])
    copy_dir = run_dir / "copy_source"
    _run([sys.executable, "-m", "nvs.evaluate", "model=copy_source", "data=chairs",
          f"data.root={hydra_value(str(data))}", f"data.size={size}", f"out_dir={hydra_value(str(copy_dir))}",
          f"hydra.run.dir={hydra_value(str(copy_dir))}"])
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
    print(verdict(ours["test"], copy["test"]))
    print(f"render {t_render / 60:.1f} min, total {(time.perf_counter() - t0) / 60:.1f} min")
    print(f"run directory: {run_dir}")


def verdict(ours: dict, copy: dict) -> str:
    """Whether the model beats copying the source on L1 or PSNR (the demo's claim), in one line."""
    l1, psnr = copy["l1"] - ours["l1"], ours["psnr"] - copy["psnr"]
    beats = [name for name, gain in (("L1", l1), ("PSNR", psnr)) if gain > 0]
    detail = f"L1 {-l1:+.4f}, PSNR {psnr:+.2f} dB against copying"
    return (f"the model beats copying the source on {' and '.join(beats)} ({detail})" if beats
            else f"the model does NOT beat copying the source on L1 or PSNR ({detail}): train longer")


if __name__ == "__main__":
    main()
