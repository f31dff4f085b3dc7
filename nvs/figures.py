"""python -m nvs.figures <study.yaml | run dirs | a directory of runs>: the paper's figures from trained runs.

Writes into ``--out`` (default ``results/``), prefixed with the study name (or ``--name``):
  ``<name>_qualitative_<data>.png``  input, target and each method's prediction on fixed test pairs (Fig. 3/4;
                                     for the ablation study this is the ablation grid, Fig. 5)
  ``<name>_depth_points.png``        predicted target depth unprojected with K, ground truth and each depth-predicting
                                     method, seen from two angles (Fig. 6)
  ``<name>_curves.png``              training loss and validation L1 of each run from its ``csv/metrics.csv``
Models are rebuilt from each run's best checkpoint the way ``nvs.evaluate`` does; reference runs from their overrides.
The drawing lives in ``nvs.report.figures``; this module reads the command line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nvs.core.errors import UserError
from nvs.report.figures import make_figures
from nvs.run.finished import Run, run_from_dir
from nvs.sweep.jobs import Status, plan
from nvs.sweep.study import load_study


def runs_from_args(paths: list[str], root: str | None = None) -> tuple[list[Run], str]:
    """Finished runs named by a study file, run directories, or directories holding runs; and a figure prefix."""
    runs, name = [], "figures"
    for arg in paths:
        p = Path(arg)
        if p.suffix in (".yaml", ".yml") and p.is_file():
            study = load_study(p)
            name = study.name
            base = Path(root) if root else Path("runs/sweeps") / study.scale
            for job in plan(study, base):
                if job.status == Status.DONE:
                    runs.append(Run(job.dir, job.row.label, job.data or "", bool(job.row.reference)))
        elif (p / "metrics.json").is_file():
            runs.append(run_from_dir(p))
        elif p.is_dir():
            found = sorted(d for d in p.iterdir() if (d / "metrics.json").is_file())
            if not found:
                raise UserError(f"{p}: no run directories (with metrics.json) inside")
            runs += [run_from_dir(d) for d in found]
        else:
            raise UserError(f"{p}: not a study file, a run directory or a directory of runs")
    if not runs:
        raise UserError("no finished runs to draw")
    return runs, name


def run(argv: list[str] | None = None) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    p = argparse.ArgumentParser(prog="python -m nvs.figures", description=__doc__.splitlines()[0])
    p.add_argument("inputs", nargs="+", help="a study file (sweeps/<study>.yaml), run directories, or a directory "
                   "of runs (e.g. runs/sweeps/64px_1500steps)")
    p.add_argument("--root", help="for a study file: the directory holding its jobs (default runs/sweeps/<scale>)")
    p.add_argument("--out", default="results", help="where the PNGs go")
    p.add_argument("--name", help="file-name prefix (default: the study name, else 'figures')")
    p.add_argument("--pairs", type=int, default=4, help="test pairs in the qualitative grids")
    args = p.parse_args(argv)
    runs, name = runs_from_args(args.inputs, args.root)
    return make_figures(runs, Path(args.out), args.name or name, args.pairs)


def main(argv: list[str] | None = None) -> None:
    try:
        written = run(argv)
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    for w in written:
        print(f"wrote {w}")


if __name__ == "__main__":
    main()
