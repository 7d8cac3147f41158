"""Shared wrapper for the Hydra entry points: user errors become one line and exit status 1."""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from typing import Any

from roboseg.errors import RobosegError

log = logging.getLogger("roboseg")


def user_errors_exit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorate a command body so that :class:`RobosegError` prints ``error: <msg>`` and exits 1."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except RobosegError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(1)

    return wrapper
