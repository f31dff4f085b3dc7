"""python -m nvs.bench.rerender <report.json> [...]: each bench report's Markdown written again from its JSON with
this checkout's report code (its goal lines and what bounds them, and the profiles that lie beside it now); the
measurements and their header stay those of the bench run that made them."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from omegaconf import OmegaConf

from nvs.bench.contenders import MODES
from nvs.bench.goals import profile_shares
from nvs.bench.report import markdown
from nvs.bench.run import REFERENCE
from nvs.bench.viewer_goal import viewer_reports
from nvs.core.atomic import write_text
from nvs.core.errors import UserError
from nvs.core.provenance import git_sha
from nvs.run.compose import CONF_DIR


def _run_order(command: str):
    """-> key(row): a row's place in the bench run that timed it: its model in ``only=[...]`` (else conf/bench.yaml's
    models), the authors' code last; its mode in MODES' order."""
    only = re.search(r"only=\[([^\]]*)\]", command)
    models = ([m.strip() for m in only.group(1).split(",")] if only else
              list(OmegaConf.load(CONF_DIR / "bench.yaml").models))
    modes = list(MODES)

    def key(row: dict) -> tuple[int, int]:
        model = models.index(row["model"]) if row["model"] in models else len(models) + (row["model"] == REFERENCE)
        return model, modes.index(row["mode"]) if row["mode"] in modes else len(modes)

    return key


def rerender(json_path: Path) -> Path:
    """Write ``<report>.md`` again from ``<report>.json`` with this checkout's report code (its goal lines, and the
    profiles that lie beside it now); the measurements and their header stay those of the bench run."""
    try:
        report = json.loads(json_path.read_text())
        report["header"], report["sizes"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise UserError(f"{json_path}: not a bench report ({err.__class__.__name__}: {err})") from None
    first = ("command", "git_sha", "date", "device", "torch", "threads")  # the header's order as the bench wrote it
    h = report["header"]
    report["header"] = {**{k: h[k] for k in first if k in h}, **{k: v for k, v in h.items() if k not in first}}
    report["profiles"] = {**report.get("profiles", {}), **profile_shares(str(json_path.parent), json_path.stem)}
    report["viewer"] = viewer_reports(json_path.parent, json_path.stem) or report.get("viewer") or []
    order = _run_order(h.get("command", ""))
    for block in report["sizes"]:  # the JSON keeps its keys sorted: the rows again in the run's order
        block["rows"] = dict(sorted(block["rows"].items(), key=lambda kv: order(kv[1])))
    out = json_path.with_suffix(".md")
    line = (f"Text rendered again from `{json_path.name}` by `python -m nvs.bench.rerender` at `{git_sha()}`; the "
            "numbers are the run's above.")
    write_text(out, markdown(report, rendered=line))
    return out


def main() -> None:
    if len(sys.argv) < 2 or any(a.startswith("-") for a in sys.argv[1:]):
        print("usage: python -m nvs.bench.rerender <report.json> [...]: writes each <report>.md again",
              file=sys.stderr)
        sys.exit(2)
    try:
        for arg in sys.argv[1:]:
            print(f"wrote {rerender(Path(arg))}")
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
