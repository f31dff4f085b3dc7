"""Where a result came from: git SHA, device, command and date, in one place for every tool that writes a report.

Only the standard library and torch are imported, so a tool can stamp a report without importing Lightning, the
data layer or the network.
"""

from __future__ import annotations

import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent


def git_sha() -> str:
    """HEAD of the checkout nvs runs from, ``-dirty`` when tracked files differ; ``unknown`` outside git."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=_HERE).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, timeout=5, cwd=_HERE).stdout.strip()
        return (sha + ("-dirty" if dirty else "")) if sha else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def device_name(accelerator_device: torch.device | None = None) -> str:
    """``NVIDIA H200`` for a GPU, ``cpu: <model> (<n> threads)`` for the CPU."""
    dev = accelerator_device or torch.device("cpu")
    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    return f"cpu: {cpu_model()} ({torch.get_num_threads()} threads)"


def utc_now(iso: bool = False) -> str:
    now = datetime.now(timezone.utc)
    return now.isoformat(timespec="seconds") if iso else now.strftime("%Y-%m-%d %H:%M UTC")


def command_line(module: str, argv: list[str] | None = None) -> str:
    """The command as a user would type it: ``python -m <module> <args>`` (shell-quoted)."""
    argv = sys.argv[1:] if argv is None else argv
    return " ".join(shlex.quote(a) for a in ["python", "-m", module, *argv])


def header(command: str, device: torch.device | None = None, iso: bool = False, **extra) -> dict:
    """The provenance record every report starts with; ``extra`` adds tool-specific fields after the common ones."""
    return {"command": command, "git_sha": git_sha(), "date": utc_now(iso=iso), "device": device_name(device),
            "torch": torch.__version__, **extra}


def markdown(head: dict) -> str:
    """The record as the lines under a report's title (Markdown hard line breaks)."""
    names = {"command": "Command", "git_sha": "Git SHA", "date": "Date", "device": "Device", "torch": "torch"}
    lines = []
    for key, value in head.items():
        label = names.get(key, key.replace("_", " "))
        shown = f"`{value}`" if key in ("command", "git_sha") else str(value)
        lines.append(f"{label}: {shown}")
    return "  \n".join(lines)
