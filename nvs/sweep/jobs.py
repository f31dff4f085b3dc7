"""A sweep's jobs: one per (row, seed), in a fixed directory ``<runs>/<size>px_<steps>steps/<run>_s<seed>``.

Identity. A job is named by its *key*: a hash of what defines the row -- the job kind, the Hydra overrides that make
its config (experiment, the study's and the row's overrides, the scale ``data.size``/``trainer.max_steps``, extra
config overrides from the command line; placement-only ones such as ``hydra.*`` or the progress bar left out) and
the seed. The key does not depend on ``conf/``: adding a key to a config file leaves every key as it was.

Staleness. ``sweep_job.json`` also stores the job's composed config (resolved; placement-only keys left out) and its
digest. A finished job stays valid while its stored config is compatible with the one composed now
(``config_changes`` is empty):
  - a value of a key present in both that differs -> stale (an experiment or a default in ``conf/`` changed);
  - a key present then and absent now -> stale (a loss term or a component left the defaults);
  - a key absent then and present now -> still valid: a new setting is assumed to default to the behaviour the
    job was trained with (the rule every new config key must follow; a default that changes results needs
    ``--force``, as a code change does) -- unless the new node is or holds a component (a mapping with
    ``_target_``, e.g. a loss term or a callback added to the defaults), which is a change.
A job whose key differs from its record's (the row's overrides changed) is stale too; a record from before keys were
override-based (no ``version``) is judged by its stored config alone. The fingerprint and the comparison are
``nvs.sweep.fingerprint``'s; an evaluation row's jobs (``evaluates:``) add the evaluated job to both
(``nvs.sweep.eval_rows``).
"""

from __future__ import annotations

import datetime as dt
import enum
import hashlib
import json
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig

from nvs.core.atomic import write_json
from nvs.run.compose import compose
# the fingerprint's functions are also reachable here, where the sweep's other modules and the tests name them
from nvs.sweep.fingerprint import (NEUTRAL_KEYS, SAME_BEHAVIOUR, config_changes, config_digest,  # noqa: F401
                                   config_fingerprint)
from nvs.sweep.eval_rows import EVALUATES, accepted_stamp, source_stamp, waiting_reason
from nvs.sweep.recorded import as_today
from nvs.sweep.recorder import FAILED, STDERR
from nvs.sweep.study import Row, Study, row_seeds

JOB_RECORD = "sweep_job.json"
RECORD_VERSION = 2  # 2: the key is made of the row's overrides; the config is checked with config_changes


class Status(str, enum.Enum):
    DONE = "done"                  # metrics.json and a valid record: never relaunched
    FAILED = "failed"              # failed.txt holds the error line; retried unless --skip-failed
    INCOMPLETE = "incomplete"      # started, no metrics.json: relaunched into the same directory (resumes)
    STALE = "stale"                # the record does not match the job as defined now: moved aside, re-run
    MISSING = "missing"            # never started

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


@dataclass
class Job:
    study: str
    row: Row
    seed: int
    dir: Path
    overrides: list[str]           # without the seed
    key: str = ""
    fingerprint: dict = field(default_factory=dict)
    data: str | None = None
    status: Status = Status.MISSING
    error: str = ""
    source: Job | None = None      # an evaluation row's job: the trained job it evaluates (nvs.sweep.eval_rows)
    waiting: str = ""              # why such a job cannot be launched now (eval_rows.WAITING); '' when it can

    @property
    def kind(self) -> str:
        return self.row.kind

    @property
    def digest(self) -> str:
        return config_digest(self.fingerprint)


# -- the overrides of a row ----------------------------------------------------------------------------------------
def _key_of(override: str) -> str:
    return override.lstrip("+~").split("=", 1)[0]


def is_hydra(override: str) -> bool:
    key = _key_of(override)
    return key.startswith("hydra.") or key.startswith("hydra/")


def _is_data(override: str) -> bool:
    return _key_of(override).startswith("data.")


# Data keys a reference row (tested on the test split, its mean over the training split) never reads: not in its key.
VALIDATION_ONLY_KEYS = ("data.loader.val_pairs_per_model",)


def _is_neutral(override: str) -> bool:
    key = _key_of(override)
    return any(key == n or key.startswith(n + ".") or key.startswith(n + "/") for n in NEUTRAL_KEYS)


def row_overrides(study: Study, row: Row, extra: tuple[str, ...] = ()) -> list[str]:
    """The Hydra overrides that define a row's jobs (seed excluded), in the order they are applied."""
    config_extra = [o for o in extra if not is_hydra(o)]
    if row.evaluates:  # nvs.evaluate's settings alone: the data and the config come with the checkpoint
        return list(row.overrides)
    if row.reference:
        # Reference rows take the study's data settings (the same test pairs), but not the validation-only ones.
        shared = [o for o in list(study.overrides) + config_extra
                  if _is_data(o) and _key_of(o) not in VALIDATION_ONLY_KEYS]
        return [f"model={row.reference}", f"data={row.data}", *shared, f"data.size={study.size}",
                *row.overrides]
    head = [f"experiment={row.experiment}"] if row.experiment else []
    return [*head, *study.overrides, f"data.size={study.size}", f"trainer.max_steps={study.steps}",
            *row.overrides, *config_extra]


def compose_job(kind: str, overrides: list[str]) -> DictConfig:
    """The job's config as Hydra composes it (hydra node excluded): conf/evaluate.yaml or conf/train.yaml."""
    return compose("train" if kind == "train" else "evaluate", overrides)


# -- identity and staleness ------------------------------------------------------------------------------------------
def job_key(kind: str, overrides: list[str], seed: int, source: str | None = None) -> str:
    """The job's stable name: a hash of its kind, its non-neutral overrides (in order), its seed and, for an
    evaluation job, the key of the job it evaluates (``source``)."""
    fields = {"kind": kind, "overrides": [o for o in overrides if not _is_neutral(o)], "seed": seed}
    blob = json.dumps(fields if source is None else {**fields, "source": source})
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def stale_reason(record: dict | None, key: str, fingerprint: dict | None) -> str:
    """Why a job directory's record does not stand for the job as defined now; '' when it does.

    Without ``fingerprint`` only the key is compared (a legacy record's key never matches).
    """
    if record is None:
        return f"no {JOB_RECORD}"
    if fingerprint is None:
        return "" if record.get("key") == key else "the row's overrides changed"
    same = record.get("digest") == config_digest(fingerprint)
    changed = [] if same else config_changes(as_today(record.get("config")), fingerprint)
    if changed:
        return f"config changed: {', '.join(changed[:6])}"
    if record.get("version") is not None and record.get("key") != key:
        return "the row's overrides changed"
    return ""


def job_status(job_dir: Path, key: str, fingerprint: dict | None = None) -> tuple[Status, str]:
    """(status, error line) of a job directory against the job's key (and composed config, when given)."""
    if not job_dir.exists() or not any(job_dir.iterdir()):
        return Status.MISSING, ""
    if stale_reason(read_json(job_dir / JOB_RECORD), key, fingerprint):
        return Status.STALE, ""
    if read_json(job_dir / "metrics.json") is not None:
        return Status.DONE, ""
    failed = job_dir / FAILED
    if failed.is_file():
        text = failed.read_text().strip()
        return Status.FAILED, text.splitlines()[0] if text else "failed"
    started = (job_dir / STDERR).exists() or (job_dir / "checkpoints").exists()
    return (Status.INCOMPLETE if started else Status.MISSING), ""


def refresh(job: Job) -> Job:
    """Re-read ``job.status`` and ``job.error`` from its directory."""
    job.status, job.error = job_status(job.dir, job.key, job.fingerprint)
    return job


def plan(study: Study, root: str | Path, extra: tuple[str, ...] = (), exported: str | Path | None = None) -> list[Job]:
    """Every job of the study with its status in ``root``; reads the disk, writes nothing.

    ``exported``: a directory of committed job files (``nvs.sweep.export``). A job that is not done in ``root`` but
    done there (the same key and staleness rule) is done, read from there.
    """
    root = Path(root)
    by_row: dict[str, list[Job]] = {}
    # evaluation rows last: their jobs are made from the jobs of the rows they evaluate
    for row in sorted(study.rows, key=lambda r: r.evaluates is not None):
        overrides = row_overrides(study, row, extra)
        sources = by_row[row.evaluates] if row.evaluates else None
        seeds = [j.seed for j in sources] if sources is not None else row_seeds(study, row)
        # One composition per row: setting the seed on a copy gives what composing with seed=<n> gives.
        composed = compose_job(row.kind, [*overrides, f"seed={seeds[0]}"]) if seeds else None
        by_row[row.name] = []
        for i, seed in enumerate(seeds):
            cfg = composed.copy()
            cfg.seed = seed
            src = sources[i] if sources is not None else None
            job = Job(study=study.name, row=row, seed=seed, dir=root / f"{row.run}_s{seed}", overrides=overrides,
                      key=job_key(row.kind, overrides, seed, src and src.key), fingerprint=config_fingerprint(cfg),
                      data=str(cfg.data.get("name") or (src.data if src else row.data)), source=src)
            stamp = today = None
            if src is not None:
                stamp = source_stamp(src.key, read_json(src.dir / JOB_RECORD))
                today = config_digest(src.fingerprint) if src.status == Status.DONE else None
                job.fingerprint[EVALUATES] = accepted_stamp(stamp, today, read_json(job.dir / JOB_RECORD))
                job.waiting = waiting_reason(src.dir, src.status == Status.DONE)
            refresh(job)
            if job.status != Status.DONE and exported is not None:
                there = Path(exported) / job.dir.name
                fingerprint = job.fingerprint if stamp is None else {
                    **job.fingerprint, EVALUATES: accepted_stamp(stamp, today, read_json(there / JOB_RECORD))}
                if job_status(there, job.key, fingerprint)[0] == Status.DONE:
                    job.dir, job.status, job.error, job.fingerprint = there, Status.DONE, "", fingerprint
            by_row[row.name].append(job)
    return [j for row in study.rows for j in by_row[row.name]]


def to_launch(jobs: list[Job], retry_failed: bool = True, force: bool = False) -> list[Job]:
    """The jobs a run must (re)launch: everything without a matching result (failed ones unless told not to); never
    an evaluation job that waits for its evaluated job's checkpoint."""
    jobs = [j for j in jobs if not j.waiting]
    if force:
        return list(jobs)
    skip = {Status.DONE} | (set() if retry_failed else {Status.FAILED})
    return [j for j in jobs if j.status not in skip]


def stale_error(job: Job) -> str:
    """The error column of a stale job: what changed."""
    reason = stale_reason(read_json(job.dir / JOB_RECORD), job.key, job.fingerprint) or "the record changed"
    return f"result is from a different config ({reason.removeprefix('config changed: ')}); re-run the study"


def prepare_job_dir(job: Job, root: Path, force: bool = False) -> None:
    """Make ``job.dir`` ready to (re)launch: move a stale or forced result aside, record the job, clear old marks."""
    if job.dir.exists() and (job.status == Status.STALE or (force and job.status != Status.MISSING)):
        old = read_json(job.dir / JOB_RECORD)
        stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        dest = root / ".stale" / f"{job.dir.name}.{(old or {}).get('key', 'unknown')}.{stamp}"
        dest.parent.mkdir(parents=True, exist_ok=True)
        reason = ("forced" if force and job.status != Status.STALE
                  else stale_reason(old, job.key, job.fingerprint) or "stale")
        shutil.move(str(job.dir), dest)
        print(f"[sweep] {job.dir.name}: {reason}; moved the old directory to {dest}", file=sys.stderr)
    job.dir.mkdir(parents=True, exist_ok=True)
    for name in (FAILED, STDERR):
        (job.dir / name).unlink(missing_ok=True)
    write_json(job.dir / JOB_RECORD, {
        "version": RECORD_VERSION, "key": job.key, "digest": job.digest, "study": job.study, "row": job.row.name,
        "seed": job.seed, "kind": job.kind, "overrides": [*job.overrides, f"seed={job.seed}"],
        "config": job.fingerprint})
