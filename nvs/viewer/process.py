"""The viewer in a child process (``python -m nvs.viewer ... port=0``), for the tools that drive it over HTTP
(``nvs.viewer.load``, ``nvs.viewer.screenshot``) and the tests."""

from __future__ import annotations

import collections
import re
import subprocess
import sys
import threading
from pathlib import Path

from nvs.core.errors import UserError

_URL = re.compile(r"viewer: (http://\S+)")


class ViewerProcess:
    """``python -m nvs.viewer *args port=0`` in a child process; the context value is its URL (``http://host:port/``).

    Output after the URL line is drained into ``tail`` (the last lines) so the child never blocks on a full pipe.
    """

    def __init__(self, args: list[str], timeout_s: float = 180.0, cwd: str | Path | None = None):
        self.args, self.timeout_s, self.cwd = list(args), timeout_s, cwd
        self.tail: collections.deque[str] = collections.deque(maxlen=50)
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> str:
        cmd = [sys.executable, "-m", "nvs.viewer", *self.args, "port=0"]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=self.cwd)
        found: list[str] = []
        ready = threading.Event()

        def drain():
            for line in self.proc.stdout:
                self.tail.append(line.rstrip())
                m = _URL.search(line)
                if m and not found:
                    found.append(m.group(1))
                    ready.set()
            ready.set()  # the child exited

        threading.Thread(target=drain, daemon=True).start()
        ready.wait(self.timeout_s)
        if not found:
            self.__exit__(None, None, None)
            raise UserError("the viewer did not start:\n" + "\n".join(self.tail))
        return found[0]

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
