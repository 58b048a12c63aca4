"""The package's messages (Python's ``logging``, logger ``"mi_partpm"``) in Mitsuba's log.

Used from Python, as Mitsuba is, the warnings and progress lines of a render follow
``mi.set_log_level``: they go through ``mi.Log`` with the level they were given (a warning
as Warn, progress as Info), so a level of Error silences the warnings and a level of Info
shows the progress, as for Mitsuba's own messages. Where the application has set up
Python's logging (a handler on the package's logger or on the root logger: the command line,
pytest, a user's ``logging.basicConfig``), that logging prints them instead and Mitsuba's log
stays out of it.
"""
from __future__ import annotations

import logging
import sys
import threading
import types
from contextlib import contextmanager

import mitsuba as mi

__all__ = ["LOGGER", "install", "follow_mitsuba_level"]

#: The logger every module of the package writes to.
LOGGER = "mi_partpm"

#: Python's levels for Mitsuba's (Trace and Debug are both DEBUG).
_PYTHON_LEVEL = {"Trace": logging.DEBUG, "Debug": logging.DEBUG, "Info": logging.INFO,
                 "Warn": logging.WARNING, "Error": logging.ERROR}


def _mitsuba_level(levelno: int):
    """Mitsuba's level for a record's. An error is logged as Warn: Mitsuba raises an
    exception for a message at its error level (Error), and the package raises its errors
    itself."""
    if levelno >= logging.WARNING:
        return mi.LogLevel.Warn
    return mi.LogLevel.Info if levelno >= logging.INFO else mi.LogLevel.Debug


def _relay(level, message): mi.Log(level, message)  # noqa: E704 (one line: see _log_as)


def _log_as(record, level, message):
    """``mi.Log(level, message)``, which names the Python file, line and function that
    called it: called here through a copy of :func:`_relay` that carries the record's own,
    so the line names the place that wrote the message, not this module."""
    code = _relay.__code__.replace(co_filename=record.pathname, co_name=record.funcName,
                                   co_qualname=record.funcName,
                                   co_firstlineno=max(int(record.lineno), 1))
    types.FunctionType(code, _relay.__globals__)(level, message)


def _application_logs() -> bool:
    """Whether the application's logging prints the package's records: a handler other than
    this module's on the package's logger or on a logger it propagates to (the root's)."""
    logger = logging.getLogger(LOGGER)
    while logger is not None:
        if any(not isinstance(h, _MitsubaHandler) for h in logger.handlers):
            return True
        logger = logger.parent if logger.propagate else None
    return False


class _MitsubaHandler(logging.Handler):
    """Hands a record to Mitsuba's log unless the application's own logging prints it."""

    def emit(self, record):
        if _application_logs():
            return
        try:
            message = record.getMessage()
            level = _mitsuba_level(record.levelno)
            if mi.variant() is None or threading.current_thread() is not threading.main_thread():
                # No variant (no Mitsuba log to write to), or a thread Mitsuba does not know:
                # the message as it is, at Mitsuba's level (its default, Warn, without one).
                least = mi.LogLevel.Warn if mi.variant() is None else mi.log_level()
                if level >= least:
                    print(message, file=sys.stderr, flush=True)
                return
            _log_as(record, level, message)
        except Exception:                 # noqa: BLE001 (logging must not break a render)
            self.handleError(record)


def install():
    """Attach the handler to the package's logger (once)."""
    logger = logging.getLogger(LOGGER)
    if not any(isinstance(h, _MitsubaHandler) for h in logger.handlers):
        logger.addHandler(_MitsubaHandler())


@contextmanager
def follow_mitsuba_level():
    """For the time of a render: let the package's records through down to Mitsuba's current
    log level (``mi.set_log_level`` may have changed it since the last), where Mitsuba's log
    prints them; afterwards the logger's level is as it was, so logging the application sets
    up later is not overruled. A level the application set on the logger, or its own
    logging, is left to decide."""
    logger = logging.getLogger(LOGGER)
    if logger.level != logging.NOTSET or _application_logs() or mi.variant() is None:
        yield                             # the application's choice
        return
    logger.setLevel(_PYTHON_LEVEL.get(mi.log_level().name, logging.WARNING))
    try:
        yield
    finally:
        logger.setLevel(logging.NOTSET)
