"""Before launching: what this machine measures for the precision a study pins, so no study runs at 10x its plan.

A study pins ``trainer.precision`` and ``channels_last`` in its overrides (they are part of every job's key), so a
committed job never goes stale because another machine would pick another mode under ``precision=auto``. The price
is that a pinned bf16 runs emulated on a CPU without native bf16 (AVX2-only: ~10x the planned cost). This check times
the pinned mode against the fastest (nvs.run.precision's probe, cached) and refuses such a launch unless the user accepts
the cost; ``trainer.precision=...`` on the sweep's command line instead makes other jobs (another key), which the
tables mark with their precision.
"""

from __future__ import annotations

from nvs.core.errors import UserError
from nvs.sweep.jobs import Job

ACCEPT_FLAG = "--accept-precision"


def _mode_of(job: Job) -> tuple[str, object, str]:
    trainer = job.fingerprint.get("trainer") or {}
    return (str(trainer.get("precision", "auto")), job.fingerprint.get("channels_last", "auto"),
            str(trainer.get("accelerator", "auto")))


def check_precision(launching: list[Job], threads: int, remote: bool, accept: bool, log) -> None:
    """One line per pinned mode; a UserError when a pinned mode is measured ``WARN_SLOWDOWN`` x slower than the
    fastest here (unless ``accept``). ``remote``: the jobs run on other machines (a cluster launcher): not probed."""
    modes = sorted({_mode_of(j) for j in launching if j.kind == "train"}, key=str)
    if not modes:
        return
    if remote:
        log(f"[sweep] precision: {', '.join(m[0] for m in modes)}; the jobs run on the launcher's machines, "
            "which this machine cannot measure")
        return
    import torch

    from nvs.run.precision import WARN_SLOWDOWN, choose

    before = torch.get_num_threads()
    torch.set_num_threads(threads)  # the probe at the jobs' thread count (it is part of the cache key)
    try:
        for precision, layout, accelerator in modes:
            try:
                choice = choose(precision, layout, accelerator, warn=lambda _: None)
            except ValueError as err:
                raise UserError(f"trainer.precision={precision}: {err}") from None
            ms = choice.probe_ms
            if not ms or choice.mode not in ms:
                log(f"[sweep] {choice.line()}")
                continue
            fastest = min(ms, key=ms.get)
            slowdown = ms[choice.mode] / ms[fastest]
            log(f"[sweep] precision: the jobs run {choice.mode} ({precision}); this machine's probe at "
                f"{threads} thread(s): {', '.join(f'{m} {v:.1f} ms' for m, v in ms.items())} -> "
                f"{slowdown:.2f}x the fastest ({fastest})")
            if slowdown >= WARN_SLOWDOWN and not accept:
                raise UserError(
                    f"this machine runs the jobs' {choice.mode} at {slowdown:.1f}x the cost of {fastest} "
                    "(bf16 is emulated without avx512_bf16/amx_bf16): they would take ~"
                    f"{slowdown:.0f}x their planned time. Run the study on a CPU with native bf16 or a GPU, or "
                    f"pass {ACCEPT_FLAG} to run it here anyway; trainer.precision=32-true on the command line "
                    "trains other jobs (another key; the tables mark their precision)")
    finally:
        torch.set_num_threads(before)
