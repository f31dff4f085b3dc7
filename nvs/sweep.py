"""python -m nvs.sweep sweeps/<study>.yaml: run a study's jobs through Hydra multirun, then tabulate them.

A study file (schema in ``sweeps/README.md``) names rows, seeds, a scale (image size, steps) and the paper's numbers.
Each (row, seed) is one job with a fixed run directory ``<runs>/<size>px_<steps>steps/<run>_s<seed>``, launched by
``python -m nvs.train -m`` (or ``python -m nvs.evaluate -m`` for reference rows) with
``hydra.sweep.dir=<runs>/<scale>`` and ``hydra.sweep.subdir=<run>_s${seed}`` -- one multirun per row over the seeds
it still needs, through whatever Hydra launcher is selected (basic, joblib, submitit).

Resumability: before launching, the runner writes ``sweep_job.json`` (a hash of the job's composed config) into the
job directory. A job whose directory holds ``metrics.json`` and the same hash is done and never relaunched; an
interrupted job (same hash, no metrics) resumes from ``checkpoints/last.ckpt`` via train.yaml's ``ckpt_path=auto``;
a directory whose hash differs (the study or a config file changed) is moved to ``<runs>/<scale>/.stale/`` first,
so a stale checkpoint is never resumed. A failed job leaves ``failed.txt`` (its last error line) and is shown as
failed in the tables.

Collection writes ``results/<study>.csv`` (one line per job) and ``results/<study>.md`` (mean ± std over seeds
per row, the paper's numbers beside ours; or, with ``table: cost``, cost against error with the cheapest row within
1% of the best L1 marked), both atomically.
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import hashlib
import io
import json
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from nvs.atomic import write_json, write_text
from nvs.errors import UserError

REPO = Path(__file__).resolve().parents[1]
CONF_DIR = REPO / "conf"
REFERENCE_MODELS = ("copy_source", "gt_warp")
IMAGE_METRICS = ("l1", "ssim_paper", "ssim", "psnr", "lpips")
DEPTH_METRICS = ("depth_l1", "depth_l1_rel", "depth_l1_inv", "depth_sc_inv")
METRICS = IMAGE_METRICS + DEPTH_METRICS
# Column title, arrow (which way is better), decimals.
METRIC_FORMAT = {
    "l1": ("L1", "↓", 4), "ssim_paper": ("SSIM (paper)", "↑", 4), "ssim": ("SSIM", "↑", 4),
    "psnr": ("PSNR", "↑", 2), "lpips": ("LPIPS", "↓", 4), "depth_l1": ("depth L1-all", "↓", 4),
    "depth_l1_rel": ("depth L1-rel", "↓", 4), "depth_l1_inv": ("depth L1-inv", "↓", 4),
    "depth_sc_inv": ("depth sc-inv", "↓", 4),
}
SKIP_LEVELS = ("conv0", "conv2", "conv3", "conv4")
# Fraction of (sample, level) warps an adaptive-skips model skipped at test time, overall and per level.
SKIP_FRACTIONS = ("warp_skipped", *(f"warp_skipped_{lv}" for lv in SKIP_LEVELS))
# Costs read from metrics.json: eval forward time per test image (no metrics), median train step time.
COSTS = ("eval_ms_per_image", "eval_forward_ms_per_image", "train_step_ms")
# Table layouts: 'metrics' (the paper's tables: metrics, params, costs, paper numbers) or 'cost' (cost against error,
# the cheapest row within PICK_L1_TOLERANCE of the best non-oracle L1 marked).
TABLES = ("metrics", "cost")
PICK_L1_TOLERANCE = 0.01
# Orderings: two of our means closer than this fraction of the larger are a tie (one seed gives no spread).
ORDER_TIE = 0.005
JOB_RECORD = "sweep_job.json"
FAILED = "failed.txt"
STDERR = "stderr.log"
# Keys that place or display a run but do not change its result; left out of the job hash.
NEUTRAL_KEYS = ("paths", "hydra", "ckpt_path", "out_dir", "task_name", "tags",
                "trainer.enable_progress_bar", "trainer.enable_model_summary")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_STUDY_KEYS = {"name", "title", "description", "paper_source", "seeds", "size", "steps", "paper_scale", "overrides",
               "metrics", "group_by", "table", "rows"}
_ROW_KEYS = {"name", "label", "run", "experiment", "overrides", "reference", "data", "paper", "oracle"}


# -- study files ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Row:
    """One table row: a trained configuration (experiment + overrides) or a reference model (no training)."""

    name: str
    label: str
    run: str                       # run-directory stem; rows with the same run in different studies share jobs
    experiment: str | None = None
    overrides: tuple[str, ...] = ()
    reference: str | None = None   # copy_source | gt_warp: evaluated by nvs.evaluate, one seed
    data: str | None = None        # required for reference rows; for trained rows read from the composed config
    paper: dict[str, float] = field(default_factory=dict)
    oracle: bool = False           # uses ground truth at test time: shown, never the best or the pick of a cost table

    @property
    def kind(self) -> str:
        return "reference" if self.reference else "train"


@dataclass(frozen=True)
class Study:
    name: str
    path: Path
    title: str
    description: str
    paper_source: str
    seeds: tuple[int, ...]
    size: int
    steps: int
    default_size: int
    default_steps: int
    overrides: tuple[str, ...]
    metrics: tuple[str, ...]
    group_by: str | None
    rows: tuple[Row, ...]
    table: str = "metrics"

    @property
    def scale(self) -> str:
        return f"{self.size}px_{self.steps}steps"

    @property
    def results_stem(self) -> str:
        """``<study>`` at the study's own scale; other scales get their own files instead of overwriting it."""
        default = self.size == self.default_size and self.steps == self.default_steps
        return self.name if default else f"{self.name}_{self.scale}"


def _check_overrides(where: str, overrides: list[Any]) -> tuple[str, ...]:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise UserError(f"{where}: 'overrides' must be a list of key=value strings")
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except Exception as err:  # noqa: BLE001 - Hydra's parser raises several types; all mean a malformed override
        raise UserError(f"{where}: {err}") from None
    for o in parsed:
        if o.is_sweep_override():
            raise UserError(f"{where}: override '{o.input_line}' is a sweep; make each value its own row")
        # The seed names the job directory and the size names the scale: both belong to the study, not a row.
        if o.key_or_group in ("seed", "data.size"):
            raise UserError(f"{where}: '{o.input_line}' is set by the study ('seeds:' / 'size:', --seeds / --size)")
    return tuple(overrides)


def load_study(path: str | Path, seeds: list[int] | None = None, size: int | None = None,
               steps: int | None = None) -> Study:
    """Read and validate a study file; ``seeds``/``size``/``steps`` replace the file's values."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such study file")
    raw = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    if not isinstance(raw, dict):
        raise UserError(f"{path}: a study file is a mapping (name, seeds, size, steps, rows, ...)")
    unknown = set(raw) - _STUDY_KEYS
    if unknown:
        raise UserError(f"{path}: unknown key(s) {sorted(unknown)}; expected {sorted(_STUDY_KEYS)}")
    for key in ("size", "steps", "rows"):
        if key not in raw:
            raise UserError(f"{path}: '{key}' is missing")
    name = str(raw.get("name") or path.stem)
    metrics = tuple(raw.get("metrics") or METRICS)
    bad = [m for m in metrics if m not in METRICS]
    if bad:
        raise UserError(f"{path}: unknown metric(s) {bad}; expected some of {list(METRICS)}")
    rows, names, runs = [], set(), set()
    for i, r in enumerate(raw["rows"]):
        where = f"{path}: rows[{i}]"
        if not isinstance(r, dict) or "name" not in r:
            raise UserError(f"{where}: each row is a mapping with at least 'name'")
        unknown = set(r) - _ROW_KEYS
        if unknown:
            raise UserError(f"{where}: unknown key(s) {sorted(unknown)}; expected {sorted(_ROW_KEYS)}")
        row = Row(name=str(r["name"]), label=str(r.get("label") or r["name"]), run=str(r.get("run") or r["name"]),
                  experiment=r.get("experiment"), overrides=_check_overrides(where, r.get("overrides") or []),
                  reference=r.get("reference"), data=r.get("data"), paper=dict(r.get("paper") or {}),
                  oracle=r.get("oracle", False))
        if not isinstance(row.oracle, bool):
            raise UserError(f"{where}: oracle must be true or false, got {row.oracle!r}")
        for key in (row.name, row.run):
            if not _NAME.match(key):
                raise UserError(f"{where}: '{key}' must be letters, digits, '_', '.', '-' (it names a directory)")
        if row.name in names or row.run in runs:
            raise UserError(f"{where}: row name '{row.name}' / run '{row.run}' used twice in the study")
        names.add(row.name)
        runs.add(row.run)
        if row.reference is not None:
            if row.reference not in REFERENCE_MODELS:
                raise UserError(f"{where}: reference must be one of {REFERENCE_MODELS}, got {row.reference!r}")
            if row.experiment or not row.data:
                raise UserError(f"{where}: a reference row names 'data' and no 'experiment'")
        bad = [m for m in row.paper if m not in METRICS]
        if bad:
            raise UserError(f"{where}: paper numbers for unknown metric(s) {bad}")
        rows.append(row)
    if not rows:
        raise UserError(f"{path}: 'rows' is empty")
    file_seeds = raw.get("seeds", [0])
    file_seeds = list(range(file_seeds)) if isinstance(file_seeds, int) else list(file_seeds)
    chosen = [int(s) for s in (seeds if seeds is not None else file_seeds)]
    if not chosen or len(set(chosen)) != len(chosen):
        raise UserError(f"{path}: seeds must be distinct and at least one, got {chosen}")
    group_by = raw.get("group_by")
    if group_by not in (None, "data"):
        raise UserError(f"{path}: group_by must be 'data' or null, got {group_by!r}")
    table = raw.get("table", "metrics")
    if table not in TABLES:
        raise UserError(f"{path}: table must be one of {list(TABLES)}, got {table!r}")
    return Study(
        name=name, path=path, title=str(raw.get("title") or name), description=str(raw.get("description") or ""),
        paper_source=str(raw.get("paper_source") or ""), seeds=tuple(chosen),
        size=int(size if size is not None else raw["size"]), steps=int(steps if steps is not None else raw["steps"]),
        default_size=int(raw["size"]), default_steps=int(raw["steps"]),
        overrides=_check_overrides(f"{path}: overrides", raw.get("overrides") or []),
        metrics=metrics, group_by=group_by, rows=tuple(rows), table=table)


# -- jobs ----------------------------------------------------------------------------------------------------------
def _is_hydra(override: str) -> bool:
    key = override.lstrip("+~")
    return key.startswith("hydra.") or key.startswith("hydra/")


def _is_data(override: str) -> bool:
    return override.lstrip("+~").startswith("data.")


def row_overrides(study: Study, row: Row, extra: tuple[str, ...] = ()) -> list[str]:
    """The Hydra overrides that define a row's jobs (seed excluded), in the order they are applied."""
    config_extra = [o for o in extra if not _is_hydra(o)]
    if row.reference:
        # Reference rows take the study's data settings (so they see the same test pairs), nothing else.
        shared = [o for o in list(study.overrides) + config_extra if _is_data(o)]
        return [f"model={row.reference}", f"data={row.data}", *shared, f"data.size={study.size}",
                *row.overrides]
    head = [f"experiment={row.experiment}"] if row.experiment else []
    return [*head, *study.overrides, f"data.size={study.size}", f"trainer.max_steps={study.steps}",
            *row.overrides, *config_extra]


def row_seeds(study: Study, row: Row) -> tuple[int, ...]:
    # A reference model has nothing to train: one evaluation stands for every seed.
    return study.seeds[:1] if row.reference else study.seeds


def compose_job(kind: str, overrides: list[str]) -> DictConfig:
    """The job's config as Hydra composes it (hydra node excluded), for hashing and for tests."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    name = "evaluate" if kind == "reference" else "train"
    outer = GlobalHydra.instance().is_initialized()
    if outer:  # compose inside someone else's Hydra app (e.g. a test) without disturbing it
        saved = GlobalHydra.instance().hydra
        GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(config_name=name, overrides=overrides)
    except Exception as err:  # noqa: BLE001 - a composition error is a problem in the study file
        raise UserError(f"overrides {overrides} do not compose: {str(err).splitlines()[0]}") from None
    finally:
        if outer:
            GlobalHydra.instance().initialize(saved)


def _drop(container: dict, dotted: str) -> None:
    *parents, last = dotted.split(".")
    node = container
    for p in parents:
        node = node.get(p) if isinstance(node, dict) else None
        if node is None:
            return
    if isinstance(node, dict):
        node.pop(last, None)


def config_fingerprint(cfg: DictConfig) -> dict:
    """The composed config resolved, with placement-only keys removed (what the job hash covers)."""
    cfg = cfg.copy()
    if "paths" in cfg and "output_dir" in cfg.paths:
        cfg.paths.output_dir = "<job dir>"  # a hydra: interpolation; its value is the job dir either way
    if "out_dir" in cfg:
        cfg.out_dir = "<job dir>"
    container = OmegaConf.to_container(cfg, resolve=True)
    for key in NEUTRAL_KEYS:
        _drop(container, key)
    return container


def config_key(fingerprint: dict) -> str:
    blob = json.dumps(fingerprint, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


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
    status: str = "missing"        # done | failed | incomplete | stale | missing
    error: str = ""

    @property
    def kind(self) -> str:
        return self.row.kind


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def job_status(job_dir: Path, key: str) -> tuple[str, str]:
    """(status, error line) of a job directory against the key the study expects now."""
    if not job_dir.exists() or not any(job_dir.iterdir()):
        return "missing", ""
    record = _read_json(job_dir / JOB_RECORD)
    if record is None or record.get("key") != key:
        return "stale", ""
    if _read_json(job_dir / "metrics.json") is not None:
        return "done", ""
    failed = job_dir / FAILED
    if failed.is_file():
        text = failed.read_text().strip()
        return "failed", text.splitlines()[0] if text else "failed"
    started = (job_dir / STDERR).exists() or (job_dir / "checkpoints").exists()
    return ("incomplete" if started else "missing"), ""


def plan(study: Study, root: str | Path, extra: tuple[str, ...] = ()) -> list[Job]:
    """Every job of the study with its status in ``root``; reads the disk, writes nothing."""
    root = Path(root)
    jobs = []
    for row in study.rows:
        overrides = row_overrides(study, row, extra)
        for seed in row_seeds(study, row):
            cfg = compose_job(row.kind, [*overrides, f"seed={seed}"])
            fp = config_fingerprint(cfg)
            job = Job(study=study.name, row=row, seed=seed, dir=root / f"{row.run}_s{seed}", overrides=overrides,
                      key=config_key(fp), fingerprint=fp, data=str(cfg.data.get("name") or row.data))
            job.status, job.error = job_status(job.dir, job.key)
            jobs.append(job)
    return jobs


def to_launch(jobs: list[Job], retry_failed: bool = True, force: bool = False) -> list[Job]:
    """The jobs a run must (re)launch: everything without a matching result (failed ones unless told not to)."""
    if force:
        return list(jobs)
    skip = {"done"} | (set() if retry_failed else {"failed"})
    return [j for j in jobs if j.status not in skip]


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def _changed_keys(old: dict, new: dict) -> list[str]:
    a, b = _flat(old), _flat(new)
    return sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))


def prepare_job_dir(job: Job, root: Path, force: bool = False) -> None:
    """Make ``job.dir`` ready to (re)launch: move a stale or forced result aside, record the key, clear old marks."""
    if job.dir.exists() and (job.status == "stale" or (force and job.status != "missing")):
        old = _read_json(job.dir / JOB_RECORD) or {}
        changed = _changed_keys(old.get("config", {}), job.fingerprint) if old else ["(no sweep_job.json)"]
        stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        dest = root / ".stale" / f"{job.dir.name}.{old.get('key', 'unknown')}.{stamp}"
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(job.dir), dest)
        reason = "forced" if force and job.status != "stale" else f"config changed: {', '.join(changed[:6])}"
        print(f"[sweep] {job.dir.name}: {reason}; moved the old directory to {dest}", file=sys.stderr)
    job.dir.mkdir(parents=True, exist_ok=True)
    for name in (FAILED, STDERR):
        (job.dir / name).unlink(missing_ok=True)
    write_json(job.dir / JOB_RECORD, {
        "key": job.key, "study": job.study, "row": job.row.name, "seed": job.seed, "kind": job.kind,
        "overrides": [*job.overrides, f"seed={job.seed}"], "config": job.fingerprint})


# -- the per-job Hydra callback ------------------------------------------------------------------------------------
class _Tee:
    """A text stream that writes to the original stream and to a file (the job's own stderr.log)."""

    def __init__(self, stream, path: Path):
        self.stream, self.file = stream, open(path, "a", buffering=1)

    def write(self, s: str) -> int:
        self.stream.write(s)
        self.file.write(s)
        return len(s)

    def flush(self) -> None:
        self.stream.flush()
        self.file.flush()

    def __getattr__(self, name):
        return getattr(self.stream, name)


class JobRecorder(Callback):
    """Hydra callback added to every sweep job: sets torch threads, keeps the job's stderr, records a failure.

    Runs inside the job's process whatever the launcher (basic, joblib worker, SLURM node).
    """

    def __init__(self, threads: int | None = None):
        self.threads = threads
        self._saved = None

    def on_job_start(self, config: DictConfig, **kwargs) -> None:
        from hydra.core.hydra_config import HydraConfig

        out = Path(HydraConfig.get().runtime.output_dir)
        if self.threads:
            import torch

            torch.set_num_threads(int(self.threads))
        self._saved = sys.stderr
        sys.stderr = _Tee(sys.stderr, out / STDERR)

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        from hydra.core.hydra_config import HydraConfig
        from hydra.core.utils import JobStatus

        tee, sys.stderr = sys.stderr, self._saved or sys.__stderr__
        out = Path(HydraConfig.get().runtime.output_dir)
        if job_return.status == JobStatus.FAILED:
            err = job_return._return_value
            text = "".join(traceback.format_exception(type(err), err, err.__traceback__))
            if isinstance(tee, _Tee):
                tee.file.write(text)
            write_text(out / FAILED, _exception_line(err) + "\n")
        if isinstance(tee, _Tee):
            tee.file.close()


def _exception_line(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__


_ERROR_LINE = re.compile(r"^(error:|[\w.]*(Error|Exception|Interrupt|Exit)\b)|Killed|out of memory", re.IGNORECASE)


def last_error_line(text: str, fallback: bool = True) -> str:
    """The last line that reads like an error (``error: ...``, ``pkg.ValueError: ...``), else the last line."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if _ERROR_LINE.search(ln):
            return ln
    return lines[-1] if lines and fallback else ""


# -- launching -----------------------------------------------------------------------------------------------------
def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Launch:
    """How jobs run: the Hydra launcher overrides and the torch threads each job may use."""

    jobs: int = 1
    threads: int = 1
    hydra_overrides: tuple[str, ...] = ()

    @classmethod
    def local(cls, jobs: int = 1, threads: int | None = None, extra: tuple[str, ...] = ()) -> Launch:
        cores = _cores()
        if jobs < 1:
            raise UserError(f"--jobs must be >= 1, got {jobs}")
        threads = threads or max(1, cores // jobs)
        if jobs * threads > cores:
            raise UserError(f"{jobs} jobs x {threads} threads > {cores} cores: lower --jobs or --threads")
        launcher = ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"] if jobs > 1 else []
        return cls(jobs=jobs, threads=threads, hydra_overrides=tuple(launcher + [o for o in extra if _is_hydra(o)]))


def multirun_command(study: Study, row: Row, seeds: list[int], root: Path, launch: Launch,
                     extra: tuple[str, ...] = ()) -> list[str]:
    """``python -m nvs.train -m ...`` (or nvs.evaluate) for one row over the given seeds."""
    module = "nvs.evaluate" if row.reference else "nvs.train"
    return [sys.executable, "-m", module, "-m", *row_overrides(study, row, extra),
            "seed=" + ",".join(str(s) for s in seeds),
            f"hydra.sweep.dir={root.resolve()}", f"hydra.sweep.subdir={row.run}_s${{seed}}",
            "+hydra.callbacks.nvs_sweep._target_=nvs.sweep.JobRecorder",
            f"+hydra.callbacks.nvs_sweep.threads={launch.threads}", *launch.hydra_overrides]


def _run_streaming(cmd: list[str], env: dict) -> tuple[int, str]:
    """Run ``cmd``; its stdout/stderr pass through, the last stderr lines are kept for the error line."""
    tail: collections.deque[str] = collections.deque(maxlen=200)
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env, bufsize=1)

    def pump():
        for line in proc.stderr:
            sys.stderr.write(line)
            tail.append(line)

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    try:
        rc = proc.wait()
    except KeyboardInterrupt:
        proc.terminate()
        proc.wait()
        raise
    t.join()
    return rc, "".join(tail)


def launch_row(study: Study, jobs: list[Job], root: Path, launch: Launch, extra: tuple[str, ...] = ()) -> list[Job]:
    """Launch one row's pending jobs until each has run once; returns them with their new status."""
    row = jobs[0].row
    env = dict(os.environ, OMP_NUM_THREADS=str(launch.threads), MKL_NUM_THREADS=str(launch.threads),
               PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    pending = list(jobs)
    while pending:
        cmd = multirun_command(study, row, [j.seed for j in pending], root, launch, extra)
        print(f"[sweep] {row.name}: seeds {[j.seed for j in pending]}\n[sweep] $ {shlex.join(cmd)}", file=sys.stderr)
        rc, tail = _run_streaming(cmd, env)
        started = [j for j in pending if (j.dir / STDERR).exists() or (j.dir / "metrics.json").exists()]
        for j in pending:
            j.status, j.error = job_status(j.dir, j.key)
            if j in started and j.status in ("incomplete", "missing"):
                # Died without an exception Hydra could catch (sys.exit, a killed worker): its own stderr says why.
                log = (j.dir / STDERR).read_text(errors="replace") if (j.dir / STDERR).exists() else ""
                j.error = (last_error_line(log, fallback=False) or last_error_line(tail, fallback=False)
                           or f"no result (multirun exit code {rc}{'; killed by a signal' if rc < 0 else ''})")
                write_text(j.dir / FAILED, j.error + "\n")
                j.status = "failed"
        if not started:
            # Nothing ran (the multirun failed before its first job, e.g. a config error): all of them failed.
            for j in pending:
                j.error = last_error_line(tail) or f"multirun exit code {rc}"
                write_text(j.dir / FAILED, j.error + "\n")
                j.status = "failed"
        # Jobs the multirun never reached (an earlier job ended the process) get their own turn.
        pending = [j for j in pending if j not in started and j.status != "failed"]
    return jobs


# -- collection ----------------------------------------------------------------------------------------------------
CSV_COLUMNS = ["study", "row", "label", "kind", "data", "seed", "status", "error", *METRICS, "n_pairs", "params",
               "train_wall_s", "train_samples_per_s", "eval_ms_per_image", "steps", "image_size", "precision",
               "device", "git_sha", "run_dir", "overrides", *[f"paper_{m}" for m in METRICS],
               "eval_forward_ms_per_image", "train_step_ms", *SKIP_FRACTIONS]


def _read_overrides(job_dir: Path) -> list[str]:
    path = job_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return []
    try:
        return [str(o) for o in OmegaConf.load(path)]
    except Exception:  # noqa: BLE001 - an unreadable file only loses the overrides column
        return []


def collect(jobs: list[Job]) -> list[dict]:
    """One record per job: its status, error line, test metrics and costs (None where absent)."""
    records = []
    for j in jobs:
        m = _read_json(j.dir / "metrics.json") if j.status == "done" else None
        m = m or {}
        test = m.get("test") or {}
        error = j.error
        if j.status == "incomplete":
            error = "interrupted; re-run the study to resume from last.ckpt"
        elif j.status == "stale":
            old = (_read_json(j.dir / JOB_RECORD) or {}).get("config")
            changed = ", ".join(_changed_keys(old, j.fingerprint)[:6]) if old else "no sweep_job.json"
            error = f"result is from a different config ({changed}); re-run the study"
        rec = {
            "study": j.study, "row": j.row.name, "label": j.row.label, "kind": j.kind,
            "data": m.get("data") or j.data, "seed": j.seed, "status": j.status, "error": error,
            **{k: _num(test.get(k)) for k in METRICS},
            "n_pairs": test.get("n_pairs"), "params": m.get("params"),
            "train_wall_s": _num(m.get("train_wall_s")), "train_samples_per_s": _num(m.get("train_samples_per_s")),
            **{k: _num(m.get(k)) for k in COSTS}, **{k: _num(test.get(k)) for k in SKIP_FRACTIONS},
            "steps": m.get("steps"),
            "image_size": m.get("image_size"), "precision": m.get("precision"), "device": m.get("device"),
            "git_sha": m.get("git_sha"), "run_dir": _shown_path(j.dir),
            "overrides": " ".join(_read_overrides(j.dir)) if j.status == "done" else "",
            **{f"paper_{k}": j.row.paper.get(k) for k in METRICS},
        }
        records.append(rec)
    return records


def _shown_path(p: Path) -> str:
    """Relative to the working directory when inside it (committed tables should not carry a machine's paths)."""
    try:
        return Path(p).resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return str(p)


def _num(v) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(f) else f


def render_csv(records: list[dict]) -> str:
    import csv

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in records:
        w.writerow({k: ("" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]))
                    for k in CSV_COLUMNS})
    return buf.getvalue()


def mean_std(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (ddof=1; None for fewer than two values)."""
    vals = [v for v in values if v is not None]
    if not vals:
        return None, None
    mean = sum(vals) / len(vals)
    if len(vals) < 2:
        return mean, None
    return mean, math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1))


def _fmt(mean: float | None, std: float | None, decimals: int) -> str:
    if mean is None:
        return "—"
    return f"{mean:.{decimals}f}" + (f" ± {std:.{decimals}f}" if std is not None else "")


def _fmt_params(n) -> str:
    if n is None:
        return "—"
    n = int(n)
    return f"{n / 1e6:.2f}M" if n >= 1e5 else str(n)


def summarize(study: Study, records: list[dict]) -> list[dict]:
    """Per row: mean/std of each metric and cost over its done seeds, counts, and the error lines of failures."""
    out = []
    for row in study.rows:
        recs = [r for r in records if r["row"] == row.name]
        done = [r for r in recs if r["status"] == "done"]
        s = {"row": row.name, "label": row.label, "kind": row.kind, "n_done": len(done), "n_jobs": len(recs),
             "data": next((r["data"] for r in recs if r["data"]), row.data), "paper": row.paper,
             "oracle": row.oracle, "notes": _notes(recs)}
        for k in (*METRICS, "params", "train_wall_s", *COSTS, *SKIP_FRACTIONS):
            s[k] = mean_std([_num(r[k]) for r in done])
        out.append(s)
    return out


def _notes(recs: list[dict]) -> list[str]:
    """'s0, s2 failed: <error line>' for each distinct (status, error) among the unfinished jobs of a row."""
    by: dict[tuple[str, str], list[int]] = {}
    for r in recs:
        if r["status"] != "done":
            by.setdefault((r["status"], r["error"] or ""), []).append(r["seed"])
    return [f"{', '.join(f's{s}' for s in seeds)} {status}" + (f": {err}" if err else "")
            for (status, err), seeds in by.items()]


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_markdown(study: Study, records: list[dict], provenance: dict) -> str:
    rows = summarize(study, records)
    # Image metrics always have a column; depth metrics only where some row has them (or the paper does).
    present = [m for m in study.metrics if m in IMAGE_METRICS
               or any(r[m][0] is not None for r in rows) or any(m in r["paper"] for r in rows)]
    paper_metrics = [m for m in study.metrics if any(m in r["paper"] for r in rows)]
    counts = collections.Counter(r["status"] for r in records)
    lines = [f"# {study.name}: {study.title}", ""]
    if study.description:
        lines += [study.description.strip(), ""]
    lines += [
        f"Generated by `nvs.sweep` from `{study.path.as_posix()}`; do not edit by hand, re-run the command.", "",
        "| | |", "|---|---|",
        f"| command | `{provenance['command']}` |",
        f"| git SHA | `{provenance['git_sha']}`" + (f" (jobs: {', '.join(f'`{s}`' for s in provenance['job_shas'])})"
                                                    if provenance["job_shas"] else "") + " |",
        f"| date | {provenance['date']} |",
        f"| device | {'; '.join(provenance['devices']) or '—'} |",
        f"| image size | {study.size}² |",
        f"| steps | {study.steps} |",
        f"| seeds | {', '.join(str(s) for s in study.seeds)} (reference rows: {study.seeds[0]}) |",
        f"| jobs | {', '.join(f'{n} {s}' for s, n in sorted(counts.items()))} |",
        "",
    ]
    if paper_metrics:
        source = f" ({study.paper_source})" if study.paper_source else ""
        lines += [f"**Paper** columns are the published numbers{source}, measured on the real "
                  "datasets at 256². **Ours** are measured here on the embedded renders at the size above; compare "
                  "orderings, not values. SSIM (paper) is the paper's own SSIM variant; SSIM is the standard one.",
                  ""]
    lines += ["Values are mean ± sample std over the seeds that finished (n = finished/planned); reference rows need "
              "no training (copy source = floor, warp with ground-truth depth = ceiling of depth-based warping).", ""]
    groups: dict[str | None, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["data"] if study.group_by == "data" else None, []).append(r)
    if study.table == "cost":
        lines += _cost_tables(groups, present)
    else:
        lines += _metrics_tables(groups, present, paper_metrics)
    return "\n".join(lines)


def _label(r: dict) -> str:
    return _md_cell(r["label"] + (" (reference)" if r["kind"] == "reference" else "")
                    + (" (oracle)" if r["oracle"] else ""))


def _status(r: dict) -> str:
    status = "ok" if not r["notes"] else "; ".join(r["notes"])
    if any(" failed" in n for n in r["notes"]):
        status = "**FAILED** " + status
    return _md_cell(status)


def _metrics_tables(groups: dict[str | None, list[dict]], present: list[str], paper_metrics: list[str]) -> list[str]:
    """The paper's layout: metrics, parameters, train wall time, eval time per image, the paper's numbers."""
    paper_titles = [f"Paper {'SSIM' if m == 'ssim_paper' else METRIC_FORMAT[m][0]}" for m in paper_metrics]
    header = ["Method", "n", *[f"{METRIC_FORMAT[m][0]} {METRIC_FORMAT[m][1]}" for m in present],
              "Params", "Train (s)", "Eval (ms/img)", *paper_titles, "Status"]
    lines = []
    for group, grows in groups.items():
        if group is not None:
            lines += [f"## {group}", ""]
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for r in grows:
            cells = [_label(r), f"{r['n_done']}/{r['n_jobs']}"]
            cells += [_fmt(*r[m], METRIC_FORMAT[m][2]) for m in present]
            cells += [_fmt_params(r["params"][0]), _fmt(*r["train_wall_s"], 0) if r["kind"] == "train" else "—",
                      _fmt(*r["eval_ms_per_image"], 1)]
            cells += [f"{r['paper'][m]:.4f}" if m in r["paper"] else "—" for m in paper_metrics]
            cells.append(_status(r))
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
        lines += orderings(grows, paper_metrics)
    return lines


def orderings(rows: list[dict], metrics: list[str]) -> list[str]:
    """Markdown lines comparing the paper's ranking of a table's rows with ours, per metric.

    Only rows with both a paper number and a measured mean take part. A pair of rows agrees when ours orders it the
    way the paper does (pairs the paper ties are left out). Ours is a tie when the two means differ by less than
    ORDER_TIE of the larger one or, with seeds, less than the sum of their standard deviations: such a pair is
    counted neither way. The lines list both rankings (best first), the agreeing pairs, the ties and the swaps.
    """
    lines = []
    for m in metrics:
        ranked = [r for r in rows if m in r["paper"] and r[m][0] is not None]
        if len(ranked) < 2:
            continue
        sign = 1.0 if METRIC_FORMAT[m][1] == "↓" else -1.0
        paper = sorted(ranked, key=lambda r: sign * r["paper"][m])
        ours = sorted(ranked, key=lambda r: sign * r[m][0])
        agree, total, swapped, tied = 0, 0, [], []
        for i, a in enumerate(paper):
            for b in paper[i + 1:]:
                if a["paper"][m] == b["paper"][m]:
                    continue
                total += 1
                (ma, sa), (mb, sb) = a[m], b[m]
                if abs(ma - mb) < max(ORDER_TIE * max(abs(ma), abs(mb)), (sa or 0.0) + (sb or 0.0)):
                    tied.append(f"{a['row']} / {b['row']}")
                elif sign * (ma - mb) < 0:
                    agree += 1
                else:
                    swapped.append(f"{a['row']} / {b['row']}")
        line = (f"- **{METRIC_FORMAT[m][0]}** (best first) paper: {' > '.join(r['row'] for r in paper)}; "
                f"ours: {' > '.join(r['row'] for r in ours)}; {agree}/{total} pairs in the paper's order")
        line += f", {len(tied)} tied (ours: {', '.join(tied)})" if tied else ""
        lines.append(line + (f"; swapped: {', '.join(swapped)}" if swapped else ""))
    return ["Orderings against the paper:", "", *lines, ""] if lines else []


PICK_COST = "eval_forward_ms_per_image"


def pick_cheapest(rows: list[dict], cost: str = PICK_COST,
                  tolerance: float = PICK_L1_TOLERANCE) -> tuple[dict | None, dict | None]:
    """(best, pick) among one table's trained, non-oracle rows that have a mean L1.

    best has the lowest mean L1; pick has the lowest mean ``cost`` among the rows whose L1 is at most
    (1 + tolerance) x best's (ties go to the lower L1). Rows are ``summarize`` entries; (None, None) without any.
    """
    eligible = [r for r in rows if r["kind"] == "train" and not r["oracle"] and r["l1"][0] is not None]
    if not eligible:
        return None, None
    best = min(eligible, key=lambda r: r["l1"][0])
    within = [r for r in eligible if r["l1"][0] <= best["l1"][0] * (1 + tolerance) and r[cost][0] is not None]
    return best, min(within, key=lambda r: (r[cost][0], r["l1"][0]), default=None)


def _skipped_cell(r: dict) -> str:
    if r["warp_skipped"][0] is None:
        return "—"
    levels = [r[f"warp_skipped_{lv}"][0] for lv in SKIP_LEVELS]
    return f"{100 * r['warp_skipped'][0]:.0f}% (" + "/".join("—" if v is None else f"{100 * v:.0f}"
                                                              for v in levels) + ")"


def _cost_tables(groups: dict[str | None, list[dict]], present: list[str]) -> list[str]:
    """Cost against error per dataset: eval forward time, speed-up over the first trained row, median train step
    time, the metrics, L1 relative to the best non-oracle row, warps skipped, and the pick (see ``pick_cheapest``)."""
    pct = f"{100 * PICK_L1_TOLERANCE:g}%"
    lines = [f"Eval is the forward pass alone per test image (batch of the test loader, metrics excluded); ×: how many "
             "times faster than the table's first trained row; train is the median time of one training step "
             "(forward, backward, optimizer). ΔL1 is relative to the best L1 among the trained rows that use no "
             "ground truth (oracle rows are upper bounds and reference rows are not configurations: neither is "
             f"ever the best or the pick). ★ marks the cheapest row at evaluation whose L1 is within {pct} of that "
             "best. Warps skipped: the fraction of (test sample, skip level) warps an adaptive model skipped, then "
             "per level conv0/conv2/conv3/conv4 in %.", ""]
    header = ["Configuration", "n", "Eval (ms/img)", "×", "Train (ms/step)",
              *[f"{METRIC_FORMAT[m][0]} {METRIC_FORMAT[m][1]}" for m in present], "ΔL1", "Warps skipped", "Pick",
              "Status"]
    for group, grows in groups.items():
        if group is not None:
            lines += [f"## {group}", ""]
        best, pick = pick_cheapest(grows)
        base = next((r for r in grows if r["kind"] == "train" and not r["oracle"] and r[PICK_COST][0]), None)
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for r in grows:
            cost = r[PICK_COST][0]
            cells = [_label(r), f"{r['n_done']}/{r['n_jobs']}", _fmt(*r[PICK_COST], 1),
                     f"{base[PICK_COST][0] / cost:.2f}×" if base and cost else "—",
                     _fmt(*r["train_step_ms"], 0) if r["kind"] == "train" else "—"]
            cells += [_fmt(*r[m], METRIC_FORMAT[m][2]) for m in present]
            cells += [f"{100 * (r['l1'][0] / best['l1'][0] - 1):+.1f}%" if best and r["l1"][0] is not None else "—",
                      _skipped_cell(r), "★" if r is pick else "", _status(r)]
            lines.append("| " + " | ".join(cells) + " |")
        lines += ["", _pick_sentence(best, pick, base, pct), ""]
    return lines


def _pick_sentence(best: dict | None, pick: dict | None, base: dict | None, pct: str) -> str:
    if best is None or pick is None:
        return "No pick: no trained row without ground truth has both an L1 and an eval time yet."
    head = f"**Pick**: {_md_cell(pick['label'])}, the cheapest at evaluation within {pct} of the best L1 " \
           f"({best['l1'][0]:.4f}, {_md_cell(best['label'])})"
    if base is None or pick is base:
        return head + ": no configuration cheaper than the first row stays within that margin, so nothing can be " \
                      "skipped here at this budget."
    return head + f": {base[PICK_COST][0] / pick[PICK_COST][0]:.2f}× faster than {_md_cell(base['label'])} at " \
                  f"{100 * (pick['l1'][0] / base['l1'][0] - 1):+.1f}% L1 against it."


def provenance(records: list[dict], command: str) -> dict:
    from nvs.build import git_sha

    done = [r for r in records if r["status"] == "done"]
    return {
        "command": command,
        "git_sha": git_sha(),
        "job_shas": sorted({r["git_sha"] for r in done if r["git_sha"]}),
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "devices": sorted({r["device"] for r in done if r["device"]}),
    }


def write_results(study: Study, jobs: list[Job], results_dir: str | Path, command: str) -> tuple[Path, Path]:
    """Collect the jobs into ``<results>/<stem>.csv`` and ``.md`` (atomic writes); returns both paths."""
    records = collect(jobs)
    results_dir = Path(results_dir)
    csv_path, md_path = results_dir / f"{study.results_stem}.csv", results_dir / f"{study.results_stem}.md"
    write_text(csv_path, render_csv(records))
    write_text(md_path, render_markdown(study, records, provenance(records, command)))
    return csv_path, md_path


# -- command line --------------------------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m nvs.sweep", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="Study schema, launchers (joblib, SLURM) and examples: sweeps/README.md")
    p.add_argument("study", help="a study file, e.g. sweeps/ablation.yaml")
    p.add_argument("overrides", nargs="*", help="extra Hydra overrides for every job, e.g. "
                   "hydra/launcher=submitit_slurm hydra.launcher.partition=gpu trainer.devices=2")
    p.add_argument("--seeds", type=int, help="use seeds 0..N-1 instead of the study's")
    p.add_argument("--size", type=int, help="image size (data.size) instead of the study's; e.g. 256")
    p.add_argument("--steps", type=int, help="training steps (trainer.max_steps) instead of the study's")
    p.add_argument("--jobs", type=int, default=1, help="parallel local jobs (hydra/launcher=joblib); default 1")
    p.add_argument("--threads", type=int, help="torch threads per job (default: cores // jobs)")
    p.add_argument("--runs", default="runs/sweeps", help="sweep root; jobs go to <runs>/<size>px_<steps>steps/")
    p.add_argument("--results", default="results", help="where <study>.csv and <study>.md are written")
    p.add_argument("--collect-only", metavar="DIR", help="tabulate the jobs under DIR (a <runs>/<scale> directory) "
                   "without launching anything")
    p.add_argument("--dry-run", action="store_true", help="print the plan and the commands; launch and write nothing")
    p.add_argument("--skip-failed", action="store_true", help="do not retry jobs that failed before")
    p.add_argument("--force", action="store_true", help="re-run every job (old directories go to <root>/.stale)")
    p.add_argument("--figures", action="store_true", help="also draw the study's figures (nvs.figures) into "
                   "--results from the finished jobs")
    return p


def _print_plan(jobs: list[Job], launching: list[Job]) -> None:
    counts = collections.Counter(j.status for j in jobs)
    print(f"[sweep] {len(jobs)} jobs: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
          + f"; launching {len(launching)}", file=sys.stderr)
    for j in jobs:
        mark = "->" if j in launching else "  "
        print(f"[sweep] {mark} {j.row.name:<24} s{j.seed:<3} {j.status:<10} {j.dir}"
              + (f"  ({j.error})" if j.error else ""), file=sys.stderr)


def run(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    command = "python -m nvs.sweep " + shlex.join(argv)
    seeds = list(range(args.seeds)) if args.seeds is not None else None
    study = load_study(args.study, seeds=seeds, size=args.size, steps=args.steps)
    extra = tuple(args.overrides)
    root = Path(args.collect_only) if args.collect_only else Path(args.runs) / study.scale
    if args.collect_only and not root.is_dir():
        raise UserError(f"--collect-only {root}: no such directory")
    if not args.dry_run:  # before any job runs: the tables must have somewhere to go
        from nvs.run_files import check_writable

        check_writable(args.results)
    jobs = plan(study, root, extra)
    launching = [] if args.collect_only else to_launch(jobs, retry_failed=not args.skip_failed, force=args.force)
    _print_plan(jobs, launching)
    if args.dry_run:
        launch = Launch.local(args.jobs, args.threads, extra)
        for row in study.rows:
            seeds_left = [j.seed for j in launching if j.row is row]
            if seeds_left:
                print(shlex.join(multirun_command(study, row, seeds_left, root, launch, extra)))
        return 0
    if launching:
        launch = Launch.local(args.jobs, args.threads, extra)
        print(f"[sweep] {launch.jobs} job(s) at a time x {launch.threads} thread(s), {_cores()} cores",
              file=sys.stderr)
        for row in study.rows:
            row_jobs = [j for j in launching if j.row is row]
            if not row_jobs:
                continue
            for j in row_jobs:
                prepare_job_dir(j, root, force=args.force)
            launch_row(study, row_jobs, root, launch, extra)
        jobs = plan(study, root, extra)
    csv_path, md_path = write_results(study, jobs, args.results, command)
    counts = collections.Counter(j.status for j in jobs)
    print(f"[sweep] wrote {csv_path} and {md_path} ("
          + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + ")", file=sys.stderr)
    if args.figures:
        from nvs.figures import Run, make_figures

        runs = [Run(j.dir, j.row.label, j.data or "", bool(j.row.reference)) for j in jobs if j.status == "done"]
        for path in make_figures(runs, Path(args.results), study.results_stem) if runs else []:
            print(f"[sweep] wrote {path}", file=sys.stderr)
    return 0 if counts.get("done", 0) == len(jobs) else 1


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: list[str] | None = None) -> None:
    # `kill <sweep pid>` (SIGTERM) stops the running job too, as Ctrl-C does: no orphan keeps writing its run dir.
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        sys.exit(run(argv))
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("[sweep] interrupted; run the same command again to resume", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
