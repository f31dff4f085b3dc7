"""python -m nvs.pareto [results/<study>.csv ...]: run time against error from the sweep results.

Writes ``results/pareto.md`` and ``results/pareto.png``: L1 and SSIM (paper) of every trained row against its train
wall time and against its evaluation forward time per image, one colour per dataset, the Pareto front of each dataset
marked, and under each dataset's table the pick: the cheapest row at evaluation whose L1 is within 1% of the best,
decided by the interval of its L1 against the best (``nvs.sweep.pick``). Reference rows (no training) are left out;
a job shared by several studies counts once. Rows trained at different scales (image size, steps) are never
compared: each scale of a dataset is its own series and front.
By default the paper's studies (ablation, comparison_*) and the skip study in ``--results`` are read.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nvs.core.atomic import write_bytes, write_text
from nvs.core.errors import UserError
from nvs.report.pareto import default_csvs, load_rows, plot, render_markdown
from nvs.sweep.pick import PICK_COST, pareto_pick_line


def run(argv: list[str] | None = None) -> tuple[Path, Path]:
    p = argparse.ArgumentParser(prog="python -m nvs.pareto", description=__doc__.splitlines()[0])
    p.add_argument("csv", nargs="*", help="sweep CSVs (default: the paper studies' CSVs in --results)")
    p.add_argument("--results", default="results", help="where pareto.md and pareto.png go")
    args = p.parse_args(argv)
    results = Path(args.results)
    sources = [Path(c) for c in args.csv] or default_csvs(results)
    agg = load_rows(sources)
    command = "python -m nvs.pareto " + " ".join(sys.argv[1:] if argv is None else argv)
    md, png = results / "pareto.md", results / "pareto.png"
    picks = {data: pareto_pick_line(g.to_dict("records")) for data, g in agg.groupby("data", sort=False)
             if PICK_COST in g}
    write_text(md, render_markdown(agg, sources, command.strip(), picks))
    write_bytes(png, plot(agg))
    return md, png


def main(argv: list[str] | None = None) -> None:
    try:
        md, png = run(argv)
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    print(f"wrote {md} and {png}")


if __name__ == "__main__":
    main()
