"""python -m nvs.stress [--out results/stress.md]: numerical stress report (geometry, gradcheck, precision, training
under adversarial batches, determinism), written atomically with a provenance header.

Every section returns rows; ``main`` renders them as Markdown tables. About 20 minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable

import torch

from nvs.core.atomic import write_text
from nvs.core.provenance import command_line, header, markdown
from nvs.run.compose import CONF_DIR
from nvs.stress.determinism import DETERMINISM_STEPS, determinism_section
from nvs.stress.geometry import geometry_section
from nvs.stress.gradcheck import gradcheck_section
from nvs.stress.harness import yes
from nvs.stress.precision import precision_section, warp_position_rows
from nvs.stress.training import training_section

SECTIONS = ("geometry", "gradcheck", "precision", "training", "determinism")
DEFAULT_OUT = CONF_DIR.parent / "results" / "stress.md"


def table(head: list[str], rows: list[list]) -> str:
    """A Markdown table; booleans become yes / **NO**."""
    def cell(v):
        return yes(v) if isinstance(v, bool) else str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


GEOMETRY = ("`inverse_warp` on a 16x16 random image (B=2, f=20 px unless stated) with gradients of a non-linear "
            "read-out w.r.t. image, depth, K and pose. *Masked*: every invalid pixel of the output is exactly 0. "
            "Non-finite depth is outside the batch contract (depth <= 0 means no data); it is listed to show "
            "what leaks.")
GRADCHECK = ("`torch.autograd.gradcheck` (eps 1e-6, atol 1e-5, rtol 1e-3) on float64 inputs. *As is*: the code "
             "unchanged. *float64 kept*: with `Tensor.float()` leaving float64 alone, which separates a wrong "
             "analytic gradient from a float64 -> float32 cast inside the function.")
PRECISION = ("One training forward and backward (train mode, B=2, 64x64, the option's losses, images of flat "
             "rectangles on white) in fp32 and under autocast, same weights and batch. Deviation = |x - x_fp32| / "
             "max |x_fp32|, max / mean over pixels; the max sits on rectangle edges that a slightly different "
             "depth moves by a fraction of a pixel. *Finite*: outputs, loss and every parameter gradient "
             "(fp32 / autocast).")
WARP_POSITIONS = ("Where the warp samples under bf16 autocast, against fp32 (objects camera, depth 2..2.3 from "
                  "the objects' depth head, 20° about the centre): pixel position error, max / mean. *Projection*: "
                  "`project_to_source` alone on fp32 inputs inside autocast; *warped skip*: the paper's code path, "
                  "bf16 raw depth -> depth head -> `WarpedSkips` on bf16 features -> the grid given to `grid_sample`.")
TRAINING = ("{total} Adam steps in all (lr 1e-3, 10x the paper's), B=2, 64x64, "
            "`torch.autograd.set_detect_anomaly(True)`; each module keeps training across its batch "
            "kinds in order; one runs under bf16 autocast. Counts are steps with a non-finite value; "
            "*error* is what anomaly detection raised, if anything.")
DETERMINISM = (f"Three short `nvs.run.training.run` runs of the paper's model ({DETERMINISM_STEPS} steps with "
               "`loss=[recon,warp]`, validation, test on 4 pairs) on a generated 4-model objects dataset, CPU: the "
               "same seed twice, then another seed as a control that the comparison can fail.")


def _geometry(work: str, steps: int) -> tuple[str, str, str]:
    return "1. Geometry under extremes", GEOMETRY, table(
        ["case", "finite out", "finite grad (image, depth)", "finite grad (K, pose)", "invalid masked",
         "valid fraction", "note"], geometry_section())


def _gradcheck(work: str, steps: int) -> tuple[str, str, str]:
    return "2. float64 gradcheck", GRADCHECK, table(["function", "as is", "float64 kept", "first failure line"],
                                                   gradcheck_section())


def _precision(work: str, steps: int) -> tuple[str, str, str]:
    body = table(["model option", "losses", "autocast", "rgb dev. max / mean", "depth dev. max / mean",
                  "loss rel. dev.", "finite (fp32 / autocast)", "note"], precision_section(work))
    body += "\n\n" + WARP_POSITIONS + "\n\n" + table(["size", "projection (px)", "warped skip (px)"],
                                                      warp_position_rows())
    return "3. Precision: autocast against fp32", PRECISION, body


def _training(work: str, steps: int) -> tuple[str, str, str]:
    rows, total = training_section(work, steps)
    return "4. Training under stress", TRAINING.format(total=total), table(
        ["module", "batches", "steps", "loss first → last", "max loss", "non-finite loss",
         "non-finite grad / weights", "error"], rows)


def _determinism(work: str, steps: int) -> tuple[str, str, str]:
    return "5. Determinism", DETERMINISM, table(["comparison", "test metrics", "example"], determinism_section(work))


# section name -> (scratch directory, steps per batch kind) -> (title, intro, body)
BODIES: dict[str, Callable[[str, int], tuple[str, str, str]]] = {
    "geometry": _geometry, "gradcheck": _gradcheck, "precision": _precision, "training": _training,
    "determinism": _determinism}


def main(argv: list[str] | None = None) -> str:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(prog="python -m nvs.stress", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="report path (Markdown)")
    ap.add_argument("--steps", type=int, default=12,
                    help="training steps of the paper's model per adversarial batch kind (baselines: a third)")
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {SECTIONS}")
    args = ap.parse_args(argv)
    wanted = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = sorted(set(wanted) - set(SECTIONS))
    if unknown:
        ap.error(f"unknown sections {unknown}; choose from {SECTIONS}")

    torch.manual_seed(0)
    parts = ["# Numerical stress report", "", "Generated by `nvs.stress`; do not edit by hand.", "",
             markdown(header(command_line("nvs.stress", argv)))]
    timings = []
    with tempfile.TemporaryDirectory(prefix="nvs-stress-") as work:
        for name in SECTIONS:
            if name not in wanted:
                continue
            t0 = time.perf_counter()
            print(f"[stress] {name} ...", flush=True)
            title, intro, body = BODIES[name](work, args.steps)
            timings.append((name, time.perf_counter() - t0))
            parts.extend(["", f"## {title}", "", intro, "", body])
    total_s = sum(t for _, t in timings)
    parts.extend(["", "## Runtime", "", table(["section", "seconds"], [[n, f"{t:.1f}"] for n, t in timings]
                                             + [["total", f"{total_s:.1f}"]])])
    text = "\n".join(parts) + "\n"
    write_text(args.out, text)
    print(f"wrote {args.out} ({total_s:.0f} s)")
    return text
