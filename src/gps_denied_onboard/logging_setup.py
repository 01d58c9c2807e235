"""structlog configuration: one JSON object per line on stderr (journald/FDR friendly), and the debug
log file where a command's unexpected exception keeps its traceback (``log_unexpected``).

Each line goes to stderr in one write, newline included: the navigator core and its vision worker share
one stderr (the unit's journal stream, the SITL harness's log file), and a line written as the record and
then its newline (``print``, two writes on an unbuffered stderr) let the other process's line in between:
two records on one line, a lost newline, in a flight with the faults scenario."""

from __future__ import annotations

import datetime
import logging
import os
import sys
import traceback
from pathlib import Path

import structlog

from gps_denied_onboard.constants import DEBUG_LOG_ENV, DEBUG_LOG_FILENAME, DEBUG_LOG_MAX_BYTES, LogEvent

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}


#: Whether ``configure_logging`` ran in this process (the log then goes to stderr at a chosen level).
_configured = False


def configure_logging(level: str = "info", *, json: bool = True) -> None:
    global _configured
    _configured = True
    processors: list[structlog.types.Processor] = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
        structlog.processors.StackInfoRenderer(),
        structlog.processors.format_exc_info,
    ]
    renderer: structlog.types.Processor = (
        structlog.processors.JSONRenderer() if json else structlog.dev.ConsoleRenderer(colors=False)
    )
    structlog.configure(
        processors=[*processors, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(_LEVELS[level]),
        logger_factory=structlog.WriteLoggerFactory(file=sys.stderr),
        cache_logger_on_first_use=False,
    )


def debug_log_path() -> Path:
    """Where ``log_unexpected`` keeps tracebacks (see ``constants.DEBUG_LOG_ENV``)."""
    named = os.environ.get(DEBUG_LOG_ENV)
    if named:
        return Path(named)
    logs = os.environ.get("LOGS_DIRECTORY")  # systemd: the first of LogsDirectory='s paths
    base = Path(logs.split(":")[0]) if logs else Path.home() / ".local" / "state" / "gdnav"
    return base / DEBUG_LOG_FILENAME


def log_unexpected(command: str, exc: BaseException) -> str:
    """Keep the traceback of ``exc``, which ended ``command`` unmapped (a bug): logged at debug level and
    appended to the debug log file. Returns where it went, for the one line on stderr."""
    text = "".join(traceback.format_exception(exc))
    if _configured:  # structlog left as it comes would print every level on stdout
        structlog.get_logger("gdnav").debug(LogEvent.CLI_UNEXPECTED_ERROR, command=command, traceback=text)
    path = debug_log_path()
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")
    entry = f"--- {stamp} gdnav {command} (pid {os.getpid()})\n{text}"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fresh = not path.exists() or path.stat().st_size + len(entry) > DEBUG_LOG_MAX_BYTES
        with path.open("w" if fresh else "a", encoding="utf-8") as fh:
            fh.write(entry)
    except OSError as exc_io:
        return f"traceback not kept: {path}: {exc_io.strerror or exc_io}; set {DEBUG_LOG_ENV}"
    return f"traceback in {path}"
