"""``python -m service``: check, then serve the app with uvicorn on the settings' host and port.

``--host`` and ``--port`` override ``DPC_SERVER__HOST`` and ``DPC_SERVER__PORT`` (see ``--help``).
Bad settings, a port that cannot be had (``service.api.listener``) or a failed startup check
(``service.api.startup``) end the process with one line on stderr and exit status 2, before
anything listens; no traceback. A ``DPC_`` variable that names no setting is logged as a
warning first.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

import uvicorn
from pydantic import ValidationError
from pydantic_settings import SettingsError

from service import memory
from service.api import logs, startup
from service.api.app import create_app
from service.api.listener import listen
from service.settings import Settings

UVICORN_STARTUP_FAILURE = 3


def main(argv: Sequence[str] | None = None) -> None:
    arguments = parser().parse_args(argv)
    try:
        flags = {key: value for key, value in vars(arguments).items() if value is not None}
        settings = Settings(server=flags)  # merged over DPC_SERVER__*: the flags win
    except ValidationError as error:
        fail(f"invalid settings: {settings_message(error)}")
    except SettingsError as error:  # a DPC_* value that is not JSON where JSON is expected
        fail(f"invalid settings: {error}; a group's value is JSON, e.g. DPC_AUTH__KEYS='{{...}}'")
    logs.configure(settings.server.log_level, settings.server.log_format)
    for warning in startup.unknown_variables(os.environ):  # DPC_SERVR__PORT: a typo, ignored
        logging.getLogger("service").warning(warning)
    memory.fix_mmap_threshold()  # before the model, the gallery and the worker threads
    startup.quiet_onnxruntime()
    try:
        sock = listen(settings.server.host, settings.server.port)  # a port in use: said at once
        prepared = startup.prepare(settings)  # here, so that a failure ends with one line
    except startup.StartupError as error:
        fail(str(error))
    # the lifespan logs the model's path, hash and execution providers once they are loaded
    config = uvicorn.Config(
        create_app(settings, prepared),
        host=settings.server.host,
        port=settings.server.port,
        log_level=settings.server.log_level,
        log_config=None,  # uvicorn's own lines go through our (JSON) handler
        access_log=False,  # logs.RequestLog writes one line a request, without the query
    )
    server = uvicorn.Server(config)
    try:
        server.run(sockets=[sock])
    except KeyboardInterrupt:  # Ctrl-C once serving: a normal stop, as uvicorn.run's
        pass
    if not server.started:  # the app's start-up failed: uvicorn.run's own status
        sys.exit(UVICORN_STARTUP_FAILURE)


def parser() -> argparse.ArgumentParser:
    """The command line: the server's address; every other setting is an environment variable."""
    defaults = Settings.model_fields["server"].default
    parser = argparse.ArgumentParser(
        prog="python -m service",
        description="Serve the DPC-MN pose service over HTTP (the API, /docs and the console at "
        "/ui). Every setting is an environment variable DPC_<GROUP>__<FIELD> "
        "(service/settings.py); the flags below override theirs.",
        epilog="Exit status 2: bad settings, a port that cannot be had, or a failed start-up "
        "check, said in one line.",
    )
    parser.add_argument(
        "--host", help=f"address to listen on (DPC_SERVER__HOST; default {defaults.host})"
    )
    parser.add_argument(
        "--port", type=int, help=f"port to listen on (DPC_SERVER__PORT; default {defaults.port})"
    )
    return parser


def settings_message(error: ValidationError) -> str:
    """One line; an API key is never echoed (it may sit in a location or an input)."""
    parts = []
    for item in error.errors():
        where = "__".join(str(part) for part in item["loc"][:2]).upper()  # not auth.keys.<key>
        parts.append(f"DPC_{where}: {item['msg']}")  # the message, not the input
    return "; ".join(parts)


def fail(message: str) -> NoReturn:
    print(f"dpc-mn-service: cannot start: {message}", file=sys.stderr)
    sys.exit(startup.EXIT_STATUS)


if __name__ == "__main__":
    main()
