"""The Hydra callback inside every job of a sweep: torch threads, the job's own stderr.log, failed.txt on a failure.

Training jobs load it through ``+hydra.callbacks.nvs_sweep._target_=nvs.sweep.recorder.JobRecorder``, so it imports
only the standard library, Hydra and nvs.core.atomic (torch only when it sets the thread count): never Lightning, the data
layer or pandas.
"""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from nvs.core.atomic import write_text

# The files a job leaves for the runner besides its results: the error line of a failure, the job's stderr.
FAILED = "failed.txt"
STDERR = "stderr.log"
TARGET = f"{__name__}.JobRecorder"


class _Tee:
    """A text stream that writes to a file (the job's own stderr.log) and to the original stream, as long as that
    can be written: when the sweep runner is killed its end of the pipe is gone, and the job (stopped by the SIGTERM
    it then gets) must still print its resume line and exit as interrupted, not fail on a broken pipe."""

    def __init__(self, stream, path: Path):
        self.stream, self.file = stream, open(path, "a", buffering=1)

    def write(self, s: str) -> int:
        self.file.write(s)
        if self.stream is not None:
            try:
                self.stream.write(s)
            except OSError:  # BrokenPipeError: nobody reads the job's stderr any more; its file has it all
                self.stream = None
        return len(s)

    def flush(self) -> None:
        self.file.flush()
        if self.stream is not None:
            try:
                self.stream.flush()
            except OSError:
                self.stream = None

    def __getattr__(self, name):
        return getattr(self.stream if self.stream is not None else self.file, name)


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
            write_text(out / FAILED, exception_line(err) + "\n")
        if isinstance(tee, _Tee):
            tee.file.close()


def exception_line(err: BaseException) -> str:
    """``TypeName: first line of the message`` (the line failed.txt holds)."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__
