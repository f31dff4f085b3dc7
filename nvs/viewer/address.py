"""Where the viewer may listen: a loopback address and a port that is free now. Light on purpose (no torch, no
aiohttp): ``python -m nvs.viewer`` checks the address before it loads the model and the libraries."""

from __future__ import annotations

import errno
import ipaddress
import socket

from nvs.core.errors import UserError


def check_address(host: str, port: int) -> None:
    """Loopback only, and a port that is free now (0: any free port); one clear UserError otherwise."""
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise UserError(f"host={host!r}: the viewer serves on a loopback address only (127.0.0.1)")
    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise UserError(f"port={port!r}: expected a port number 0..65535 (0: any free port)")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no conflict
        try:
            s.bind((host, port))
        except OSError as err:
            raise bind_error(host, port, err) from None


def bind_error(host: str, port: int, err: OSError) -> UserError:
    """The one line for a failed bind: a taken port names the way out."""
    if err.errno == errno.EADDRINUSE:
        return UserError(f"port {port} on {host} is already in use: pass port=<another> (or port=0 for any free port)")
    return UserError(f"cannot listen on {host}:{port}: {err.strerror or err}")
