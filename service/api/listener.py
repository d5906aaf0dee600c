"""The server's listening socket, bound before the model loads.

uvicorn binds only after the app has started, and a port in use then ends the process with
status 3 and the OS's words. Bound here first, a port that cannot be had is a start-up check
like the others (``service.api.startup``): one line naming the port and the settings that
change it, status 2, at once; and the port stays held while the model and gallery load.
"""

from __future__ import annotations

import errno
import socket

from service.api.startup import StartupError


def listen(host: str, port: int) -> socket.socket:
    """A socket bound to ``host``:``port`` as uvicorn binds one (``SO_REUSEADDR``), for
    ``uvicorn.Server.run(sockets=...)``; ``StartupError`` saying what to change."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except (OSError, OverflowError) as error:
        sock.close()
        raise StartupError(cannot_listen(host, port, error)) from None
    sock.set_inheritable(True)
    return sock


def cannot_listen(host: str, port: int, error: Exception) -> str:
    where = f"port {port} on {host}"
    change_port = "pick another with --port or DPC_SERVER__PORT"
    code = getattr(error, "errno", None)
    if code == errno.EADDRINUSE:
        return (
            f"{where} is in use (another service, or another copy of this one, listens there): "
            f"stop it, or {change_port}"
        )
    if code == errno.EACCES:
        return f"{where} needs privileges this user lacks: {change_port} (above 1023)"
    if code == errno.EADDRNOTAVAIL or isinstance(error, socket.gaierror):
        return (
            f"cannot listen on {host}: it is not an address of this machine; pick another "
            "with --host or DPC_SERVER__HOST (0.0.0.0: every address)"
        )
    return f"cannot listen on {where}: {error}; {change_port}, or another --host"
