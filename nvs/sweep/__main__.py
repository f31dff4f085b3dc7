"""python -m nvs.sweep sweeps/<study>.yaml: run a study's jobs through Hydra multirun, then tabulate them.

A study file (schema in ``sweeps/README.md``) names rows, seeds, a scale (image size, steps) and the paper's numbers.
Each (row, seed) is one job with a fixed run directory ``<runs>/<size>px_<steps>steps/<run>_s<seed>``, launched by
``python -m nvs.train -m`` (or ``python -m nvs.evaluate -m`` for reference rows) with
``hydra.sweep.dir=<runs>/<scale>`` and ``hydra.sweep.subdir=<run>_s${seed}`` -- one multirun per row over the seeds
it still needs, through whatever Hydra launcher is selected (basic, joblib, submitit). An evaluation row
(``evaluates: <trained row>``, ``nvs.sweep.eval_rows``) runs ``nvs.evaluate`` on each of that row's tested checkpoints
after the trained rows, one job at a time; one whose checkpoint is not on this machine waits (not launched, shown
missing).

Resumability: before launching, the runner writes ``sweep_job.json`` (the job's key, made of the overrides that
define it, and its composed config) into the job directory. A job whose directory holds ``metrics.json`` and a
record that still stands for it (``nvs.sweep.jobs`` says when) is done and never relaunched; an interrupted job
resumes from ``checkpoints/last.ckpt`` via train.yaml's ``ckpt_path=auto``; a stale directory (the study or a value
in ``conf/`` changed) is moved to ``<runs>/<scale>/.stale/`` first, so a stale checkpoint is never resumed. A failed
job leaves ``failed.txt`` (its last error line) and is shown as failed in the tables.

Collection writes ``results/<study>.csv`` (one line per job) and ``results/<study>.md`` (mean ± std over seeds
per row, the paper's numbers beside ours, orderings decided by a two-level bootstrap over seeds and test models,
each with a per-model figure ``<study>_per_model_<data>.png``; or, with ``table: cost``, cost against error with the
cheapest row within 1% of the best L1 marked), both atomically.

Committed jobs: ``--export-jobs`` copies each finished job's small files to ``<results>/jobs/<scale>/``
(``nvs.sweep.export``); every run treats the jobs found there as done under the same identity and staleness rule,
so ``--collect-only`` on a fresh clone rebuilds the tables from them.
"""

from __future__ import annotations

import argparse
import collections
import shlex
import signal
import sys
from pathlib import Path

from nvs.core.errors import UserError
from nvs.run.finished import Run
from nvs.sweep.cost_check import check_precision
from nvs.sweep.export import export_jobs, export_root
from nvs.sweep.jobs import Job, Status, plan, prepare_job_dir, refresh, to_launch
from nvs.sweep.launch import Launch, available_cores, interrupt_on_signal, launch_row, multirun_command
from nvs.sweep.lock import LOCKS, JobLocks
from nvs.sweep.progress import Progress
from nvs.sweep.study import load_study
from nvs.sweep.tables import write_results
from nvs.sweep.testset import check_launch


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
    p.add_argument("--collect-only", metavar="DIR", nargs="?", const="", help="tabulate without launching anything: "
                   "the jobs under DIR (a <runs>/<scale> directory; default: the --runs one) and the committed ones "
                   "in <results>/jobs/<scale>")
    p.add_argument("--export-jobs", action="store_true", help="copy every finished job's small files (never "
                   "checkpoints) to <results>/jobs/<scale>/, where later runs and fresh clones find them")
    p.add_argument("--dry-run", action="store_true", help="print the plan and the commands; launch and write nothing")
    p.add_argument("--rows", metavar="GLOBS", help="launch only the rows whose name matches one of these comma-separated "
                   "globs, e.g. 'chen_*,*_chairs' (a study split across sessions or machines); the tables still "
                   "list every row")
    p.add_argument("--accept-precision", action="store_true", help="launch even where this machine measures the "
                   "jobs' pinned precision (e.g. bf16 without native bf16) >= 1.5x slower than its fastest mode")
    p.add_argument("--skip-failed", action="store_true", help="do not retry jobs that failed before")
    p.add_argument("--force", action="store_true", help="re-run every job (old directories go to <root>/.stale)")
    p.add_argument("--time", action="store_true", help="time every trained and evaluation row's forward on this "
                   "machine in one process, interleaved, at the study's size and 256² (the --rows ones only, where "
                   "given), into <results>/timing/<study>.json, read by the cost table (nvs.sweep.timing)")
    p.add_argument("--figures", action="store_true", help="also draw the study's figures (nvs.figures) into "
                   "--results from the finished jobs")
    return p


def _print_plan(jobs: list[Job], launching: list[Job]) -> None:
    counts = collections.Counter(j.status for j in jobs)
    print(f"[sweep] {len(jobs)} jobs: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
          + f"; launching {len(launching)}", file=sys.stderr)
    for j in jobs:
        mark = "->" if j in launching else "  "
        note = j.error
        if j.waiting and j.status != Status.DONE:  # an evaluation job without its evaluated job's checkpoint
            note = f"after {j.source.dir.name}, trained first in this run" if j in launching else j.waiting
        print(f"[sweep] {mark} {j.row.name:<24} s{j.seed:<3} {j.status:<10} {j.dir}"
              + (f"  ({note})" if note else ""), file=sys.stderr)


def _after_sources(jobs: list[Job], launching: list[Job], retry_failed: bool, force: bool) -> list[Job]:
    """The evaluation jobs that wait for a job this run launches: they run after it, when its checkpoint exists."""
    skip = {Status.DONE} | (set() if retry_failed else {Status.FAILED})
    ids = {id(j) for j in launching}
    return [j for j in jobs if j.waiting and id(j.source) in ids and (force or j.status not in skip)]


def _ready(planned: list[Job], fresh: dict[str, Job]) -> list[Job]:
    """The evaluation jobs of ``planned`` as planned again now (``fresh``, by directory name) whose checkpoint is
    there; one line for each that still waits (its evaluated job failed or was not run)."""
    ready = []
    for j in planned:
        now = fresh.get(j.dir.name, j)
        if now.waiting:
            print(f"[sweep] {j.row.name} s{j.seed}: not launched, {now.waiting}", file=sys.stderr)
        else:
            ready.append(now)
    return ready


def _selected_rows(study, globs: str) -> set[str]:
    """Names of the study's rows that match the comma-separated globs; a glob that matches none is an error."""
    import fnmatch

    names, chosen = [r.name for r in study.rows], set()
    for pattern in (g.strip() for g in globs.split(",")):
        hits = fnmatch.filter(names, pattern) if pattern else []
        if not hits:
            raise UserError(f"--rows {globs!r}: {pattern!r} matches no row of {study.path}; rows: {', '.join(names)}")
        chosen.update(hits)
    return chosen


def _lock(locks: JobLocks, jobs: list[Job], force: bool, held: dict[str, str]) -> list[Job]:
    """The jobs whose lock this sweep takes; one taken by another sweep is left to it (one line each, and its holder
    in ``held``), and one that another sweep finished since the plan is not run again."""
    kept = []
    for j in jobs:
        holder = locks.acquire(j.dir.name)
        if holder is not None:
            held[f"{j.row.name} s{j.seed}"] = holder
            print(f"[sweep] {j.row.name} s{j.seed}: skipped, another sweep is running it ({holder}; lock "
                  f"{locks.path(j.dir.name)})", file=sys.stderr)
        elif not force and refresh(j).status == Status.DONE:
            locks.release(j.dir.name)
        else:
            kept.append(j)
    return kept


def run(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    command = "python -m nvs.sweep " + shlex.join(argv)
    seeds = list(range(args.seeds)) if args.seeds is not None else None
    study = load_study(args.study, seeds=seeds, size=args.size, steps=args.steps)
    extra = tuple(args.overrides)
    if args.time and study.table != "cost":
        raise UserError(f"--time: {study.path} has no cost table (table: cost) to show the times in")
    root = Path(args.collect_only) if args.collect_only else Path(args.runs) / study.scale
    # Committed jobs count as finished, except under --force (which re-runs everything into --runs).
    exported = None if args.force else export_root(args.results, study.scale)
    if args.collect_only and not root.is_dir():
        raise UserError(f"--collect-only {root}: no such directory")
    if not args.dry_run:  # before any job runs: the tables must have somewhere to go
        from nvs.run.artifacts import check_writable  # pandas: only when something is written

        check_writable(args.results)
    jobs = plan(study, root, extra, exported)
    launching = [] if args.collect_only is not None else to_launch(jobs, retry_failed=not args.skip_failed,
                                                                   force=args.force)
    if launching:
        launching += _after_sources(jobs, launching, not args.skip_failed, args.force)
    if args.rows is not None:
        chosen = _selected_rows(study, args.rows)
        launching = [j for j in launching if j.row.name in chosen]
        ids = {id(j) for j in launching}  # an evaluation whose trained job --rows leaves out keeps waiting
        launching = [j for j in launching if not j.waiting or id(j.source) in ids]
    _print_plan(jobs, launching)
    if launching and not args.force:  # never continue a study on another render of its data
        check_launch([j for j in jobs if j.status == Status.DONE], [j for j in launching if j.kind != "evaluate"])
    if launching and args.collect_only is None:
        launch = Launch.local(args.jobs, args.threads, extra)
        remote = any(o.startswith("hydra/launcher=submitit_slurm") for o in extra)  # a cluster's machines
        check_precision(launching, launch.threads, remote, args.accept_precision or args.dry_run,
                        lambda text: print(text, file=sys.stderr))
    if args.dry_run:
        launch = Launch.local(args.jobs, args.threads, extra)
        for row in study.rows:
            left = [j for j in launching if j.row is row]
            for batch in ([[j] for j in left] if row.evaluates else [left] if left else []):
                if batch[0].waiting:  # its checkpoint comes from a job this run trains first
                    print(f"# {row.name} s{batch[0].seed}: nvs.evaluate on {batch[0].source.dir.name}'s checkpoint, "
                          "once it is trained")
                    continue
                print(shlex.join(multirun_command(study, row, [j.seed for j in batch], root, launch, extra,
                                                  batch[0].source)))
        return 0
    if launching:
        launch = Launch.local(args.jobs, args.threads, extra)
        print(f"[sweep] {launch.jobs} job(s) at a time x {launch.threads} thread(s), {available_cores()} cores",
              file=sys.stderr)
        # the order they run in: the evaluation rows after every other (their checkpoints may be trained here)
        rows = sorted(study.rows, key=lambda r: r.evaluates is not None)
        order = [j for row in rows for j in launching if j.row is row]
        progress = Progress(order, skipped=len(jobs) - len(order))
        progress.begin()
        held: dict[str, str] = {}  # job -> the other sweep holding it
        fresh: dict[str, Job] | None = None  # the evaluation jobs planned again once the trained rows have run
        with JobLocks(root) as locks:
            for row in rows:
                planned = [j for j in order if j.row is row]
                if row.evaluates and planned:
                    if fresh is None:
                        fresh = {j.dir.name: j for j in plan(study, root, extra, exported) if j.row.evaluates}
                    planned = _ready(planned, fresh)
                row_jobs = _lock(locks, planned, args.force, held)
                if not row_jobs:
                    continue
                for j in row_jobs:
                    prepare_job_dir(j, root, force=args.force)
                # the child holds the row's locks too: a job stays locked until its training process has ended
                launch_row(study, row_jobs, root, launch, extra, keep_fds=locks.fds(j.dir.name for j in row_jobs),
                           progress=progress)
                locks.release()
        progress.end()
        if len(held) == len(order):  # a second sweep of the same study and directories while the first runs
            first, holder = next(iter(held.items()))
            raise UserError(f"{root}: another sweep is running every job this one would launch ({first}: {holder}; "
                            f"locks in {root / LOCKS}); refused: nothing launched, the tables and exports left as "
                            "they are (run it again once that sweep has ended)")
        jobs = plan(study, root, extra, exported)
    if args.export_jobs:
        dest = export_root(args.results, study.scale)
        written = {p.name for p in export_jobs(jobs, dest)}
        print(f"[sweep] exported {len(written)} finished job(s) to {dest}", file=sys.stderr)
        for j in jobs:  # the tables read the committed copies, as a fresh clone will
            if j.dir.name in written:
                j.dir = dest / j.dir.name
    if args.time:  # after the jobs: nothing else runs beside the timed forwards
        from nvs.sweep.time_rows import run_timing

        path = run_timing(study, args.results, _selected_rows(study, args.rows) if args.rows else None)
        print(f"[sweep] wrote {path}", file=sys.stderr)
    csv_path, md_path = write_results(study, jobs, args.results, command)
    counts = collections.Counter(j.status for j in jobs)
    print(f"[sweep] wrote {csv_path} and {md_path} ("
          + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + ")", file=sys.stderr)
    if args.figures:
        from nvs.report.figures import make_figures

        # Drawing needs a trained job's checkpoint: committed jobs without their run directory are left out.
        dirs = [(j, root / j.dir.name if (root / j.dir.name / "checkpoints").is_dir() else j.dir)
                for j in jobs if j.status == Status.DONE and j.kind != "evaluate"]
        runs = [Run(d, j.row.label, j.data or "", bool(j.row.reference)) for j, d in dirs
                if j.row.reference or (d / "checkpoints").is_dir()]
        if len(runs) < len(dirs):
            print(f"[sweep] figures: {len(dirs) - len(runs)} finished job(s) have no checkpoint here "
                  "(committed files only); drawn without them", file=sys.stderr)
        for path in make_figures(runs, Path(args.results), study.results_stem) if runs else []:
            print(f"[sweep] wrote {path}", file=sys.stderr)
    return 0 if counts.get(Status.DONE, 0) == len(jobs) else 1


def main(argv: list[str] | None = None) -> None:
    # `kill <sweep pid>` (SIGTERM) stops the running job too, as Ctrl-C does: no orphan keeps writing its run dir.
    signal.signal(signal.SIGTERM, interrupt_on_signal)
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
