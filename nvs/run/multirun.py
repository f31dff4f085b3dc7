"""Hydra callback of every run (conf/hydra/default.yaml): a multirun keeps going after a failed job and reports the
failed jobs at its end, one line each, then exits 2 (all failures were user errors) or 1.

Failures are appended to ``<sweep dir>/multirun_failures.jsonl`` by the job's own process, so the report is the same
whatever the launcher (basic, joblib workers, submitit).
"""

from __future__ import annotations

import json
import sys
import traceback
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig

FAILURES = "multirun_failures.jsonl"


def record_failure(line: str, user_error: bool) -> None:
    """Inside a multirun job: append this job's failure (one line) to the sweep's failure list."""
    hc = HydraConfig.get()
    record = {"job": hc.job.num, "overrides": list(hc.overrides.task), "dir": hc.runtime.output_dir,
              "user_error": user_error, "line": line}
    path = Path(hc.sweep.dir) / FAILURES
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")


class MultirunReport(Callback):
    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        (Path(config.hydra.sweep.dir) / FAILURES).unlink(missing_ok=True)  # a re-run of the same sweep dir

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        from hydra.core.utils import JobStatus

        hc = HydraConfig.get()
        if hc.mode != RunMode.MULTIRUN or job_return.status != JobStatus.FAILED:
            return
        # A bug (user errors never get here: nvs.run.cli.exits_cleanly records them and returns): its traceback, a
        # one-line summary for the report, and the job marked done so that the sweeper goes on and ends normally.
        err = job_return._return_value
        traceback.print_exception(type(err), err, err.__traceback__, file=sys.stderr)
        first = next((ln for ln in str(err).splitlines() if ln.strip()), "")
        record_failure(f"{type(err).__name__}: {first}".rstrip(": "), user_error=False)
        job_return.status = JobStatus.COMPLETED
        job_return.return_value = None

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        path = Path(config.hydra.sweep.dir) / FAILURES
        if not path.is_file():
            return
        records = [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]
        if not records:
            return
        print(f"multirun: {len(records)} job(s) failed (listed in {path}):", file=sys.stderr)
        for r in sorted(records, key=lambda r: r["job"]):
            print(f"  job {r['job']} ({' '.join(r['overrides'])}): {r['line']}", file=sys.stderr)
        sys.exit(2 if all(r["user_error"] for r in records) else 1)
