"""Evaluation rows (``evaluates: <trained row>``): each of a trained row's jobs evaluated again by ``nvs.evaluate``.

An evaluation row holds ``nvs.evaluate`` overrides (``[route=fit, "time_sizes=[64,256]"]``: docs/skipping.md) and
nothing the evaluated row owns: its seeds, its data and its checkpoints are that row's.

Jobs. One per seed of the evaluated row, in ``<runs>/<size>px_<steps>steps/<run>_s<seed>``, launched one at a time
(each has its own checkpoint; ``nvs.sweep.launch``) as
``python -m nvs.evaluate -m ckpt_path=<checkpoint> <row overrides> seed=<s> hydra.sweep.dir=<runs>/<scale>
hydra.sweep.subdir=<run>_s${seed}``, the multirun form of the reference rows. The checkpoint is the evaluated job's
tested one: the ``checkpoint`` of its ``metrics.json``, a path on the machine that trained it. A committed job
(``results/jobs``) carries no weights, so where the evaluated job is not done or that file is not here, the
evaluation job *waits*: it is not launched and not failed, the plan and the tables show it missing with the line
``WAITING``. In one sweep the trained and reference rows run first, then the evaluation rows whose sources are
ready (``nvs.sweep.__main__``).

Identity. The key (``nvs.sweep.jobs.job_key``) hashes the kind "evaluate", the row's overrides, the seed and the
evaluated job's key: a change of the evaluated row's overrides (a new trained job) is a new evaluation.

Staleness. The fingerprint is ``conf/evaluate.yaml`` composed with the row's overrides and the seed (``ckpt_path``
is a neutral key: it names a file of one machine), plus ``evaluates`` = {``key``: the evaluated job's key,
``trained``: the digest its ``sweep_job.json`` holds}. A finished evaluation goes stale by the rule of every job
(``nvs.sweep.jobs``): an evaluate setting that changed, or an evaluated job trained again under another config
(its record rewritten). An evaluation whose ``trained`` is instead the digest of the evaluated job's config as
composed today stays done while that job is done under a config that behaves the same (``accepted_stamp``): a
committed record in an older spelling stands for a retrain here, whose evaluation stamped the retrain's digest.
One trained again under the same config (``--force``) is not seen: re-run the evaluation row with
``--rows <name> --force``.
"""

from __future__ import annotations

import json
from pathlib import Path

EVALUATES = "evaluates"  # the fingerprint's entry naming the evaluated job
WAITING = "waiting: needs {}'s checkpoint (train that row here; committed jobs carry no weights)"


def tested_checkpoint(job_dir: str | Path) -> Path | None:
    """The checkpoint a finished trained job was tested with (its metrics.json's ``checkpoint``), where that file
    exists on this machine; None otherwise (not done, not named, or a committed job's files only)."""
    try:
        named = json.loads((Path(job_dir) / "metrics.json").read_text()).get("checkpoint")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(named, str) or not named:
        return None
    path = Path(named)
    return path if path.is_file() else None


def waiting_reason(source_dir: Path, source_done: bool) -> str:
    """Why an evaluation job cannot be launched now ('' when it can): its evaluated job is not done here, or that
    job's tested checkpoint is not a file on this machine."""
    if source_done and tested_checkpoint(source_dir) is not None:
        return ""
    return WAITING.format(source_dir)


def source_stamp(source_key: str, source_record: dict | None) -> dict:
    """The fingerprint's ``evaluates`` entry: the evaluated job's key and the config digest its record holds."""
    return {"key": source_key, "trained": (source_record or {}).get("digest")}


def accepted_stamp(stamp: dict, today: str | None, record: dict | None) -> dict:
    """The ``evaluates`` entry to check an evaluation's ``record`` against: ``stamp`` (the evaluated job's record
    digest), or the same with ``today`` -- the digest of the evaluated job's config composed now, given only where
    that job is done (its record behaves as today's config) -- where the record holds that one."""
    held = ((record or {}).get("config") or {}).get(EVALUATES)
    if today and isinstance(held, dict) and held.get("key") == stamp["key"] and held.get("trained") == today:
        return {**stamp, "trained": today}
    return stamp
