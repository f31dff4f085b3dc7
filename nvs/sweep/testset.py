"""Which test set a job was measured on, and whether this machine's data is the same one.

A job's key and config name its data by config (``data=chairs``, ``data.size=64``), not by content: two renders of
``chairs`` (the embedded 65-chair set and ``make objects-full``'s 77) compose the same config. Rows measured on
different test sets cannot share a table, and a job trained on one render must not be continued on another. The test
set is what identifies a render here: a job's ``test_per_image.csv`` lists the (source, target) ids it was tested on,
and this machine's data gives the ids it would test on; the signature of either is the count and a hash of the
sorted pairs.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.sweep.bootstrap import PER_IMAGE, read_per_image


@dataclass(frozen=True)
class TestSet:
    pairs: int
    sha: str

    def __str__(self) -> str:
        return f"{self.pairs} test pairs, signature {self.sha}"


def signature(pairs) -> TestSet:
    pairs = sorted((str(a), str(b)) for a, b in pairs)
    blob = "\n".join(f"{a} {b}" for a, b in pairs).encode()
    return TestSet(len(pairs), hashlib.sha256(blob).hexdigest()[:12])


def job_test_set(job_dir: str | Path) -> TestSet | None:
    """The test set a finished job was measured on, from its per-image CSV (None without one)."""
    if not (Path(job_dir) / PER_IMAGE).is_file():
        return None
    return signature(read_per_image(Path(job_dir) / PER_IMAGE))


def local_test_set(fingerprint: dict) -> TestSet | None:
    """The test set this machine's data gives a job (its resolved config); None when the data cannot be read here
    (not rendered yet, or a config this check cannot build: the job itself then fails with its own error, which
    says more than this check could)."""
    from nvs.run.build import build_data  # noqa: PLC0415 - the data stack only when a study launches

    try:
        return signature(build_data(OmegaConf.create(fingerprint)).test_pairs())
    except Exception:  # noqa: BLE001 - see above: never a reason to refuse a launch by itself
        return None


def check_launch(done: list, launching: list) -> None:
    """Refuse to launch a job on data whose test set differs from the one the study's finished jobs of the same
    dataset were measured on (``done``/``launching``: ``nvs.sweep.jobs.Job``). One error naming a finished job, both
    test sets and the data root."""
    local: dict[str, TestSet | None] = {}
    for job in launching:
        data = job.data
        if data in local:
            continue
        local[data] = here = local_test_set(job.fingerprint)
        if here is None:
            continue
        for other in done:
            if other.data != data:
                continue
            there = job_test_set(other.dir)
            if there is not None and there != here:
                root = job.fingerprint.get("data", {}).get("root", "?")
                raise UserError(
                    f"{other.dir}: measured on {there}, but {root} gives {here}: the finished jobs of '{data}' were "
                    "made from another render of the data; render that set (docs/datasets.md: the embedded one, or "
                    "`make objects-full`) or run this study elsewhere (--runs DIR --results DIR)")
