"""Shared wrapper for the Hydra entry points: user errors become one line and exit status 1."""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from typing import Any

from omegaconf import ListConfig

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


def parse_scales(value: Any, key: str) -> list[float]:
    """A config's list of scale factors (one number or a list; null: ``[1.0]``) as floats;
    :class:`RobosegError` naming ``key`` when an item is not a number (the model loader checks
    that they are positive)."""
    if value is None:
        return [1.0]
    items = list(value) if isinstance(value, list | tuple | ListConfig) else [value]
    try:
        return [float(x) for x in items]
    except (TypeError, ValueError):
        raise RobosegError(f"{key}: expected numbers, got {value!r}") from None
