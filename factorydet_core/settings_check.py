"""Checks of settings read from untrusted places: a checkpoint's note, a training run's record in
the session database, ``--set KEY=VALUE`` on the command line, a hand-edited JSON file.

A ``Setting`` says what kind of value one setting holds and its range; ``check`` returns the value
as a plain Python value or raises one line of ``InputError`` naming the setting. It lives in the
base layer so that every stage's settings (the front half's ``FrontEndParams``, the learned stages'
constructors) are checked by the same rules, wherever they were built from. ``short_repr`` and
``exception_line`` put a value or an exception on one line of such a message.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping

import numpy as np

from factorydet_core.types import InputError


@dataclasses.dataclass(frozen=True)
class Setting:
    """What one setting may hold.

    Args:
        kind: ``int``, ``float`` (an int is taken too), ``bool`` or ``str``.
        low: least value of a number; ``low_open`` excludes it.
        high: greatest value of a number.
        optional: ``None`` is allowed.
        choices: the allowed values of a ``str``.
        low_open: ``low`` itself is not allowed.
    """

    kind: type
    low: float = -math.inf
    high: float = math.inf
    optional: bool = False
    choices: tuple[str, ...] | None = None
    low_open: bool = False

    def check(self, name: str, value: object) -> object:
        """``value`` as a plain Python value of ``kind`` (or ``None``); ``InputError`` naming
        ``name`` if it is not one this setting allows."""
        if value is None:
            if self.optional:
                return None
            raise InputError(f"{name} must not be null")
        if self.kind is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise InputError(f"{name} must be true or false, got {short_repr(value)}")
            return bool(value)
        if self.kind is str:
            if not isinstance(value, str) or (self.choices is not None and value not in self.choices):
                allowed = f"one of {', '.join(self.choices)}" if self.choices is not None else "a text"
                raise InputError(f"{name} must be {allowed}, got {short_repr(value)}")
            return value
        # bool is an Integral too, but a flag is never a count.
        integral = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
        real = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
        if self.kind is int and not integral:
            raise InputError(f"{name} must be an integer, got {short_repr(value)}")
        if not real:
            raise InputError(f"{name} must be a number, got {short_repr(value)}")
        try:
            # A JSON integer may have hundreds of digits: too large for a float.
            number = int(value) if self.kind is int else float(value)
        except OverflowError:
            number = math.inf
        if isinstance(number, float) and not math.isfinite(number):
            raise InputError(f"{name} must be a finite number, got {short_repr(value)}")
        above_low = number > self.low if self.low_open else number >= self.low
        if not (above_low and number <= self.high):
            bracket = "(" if self.low_open else "["
            got = short_repr(number)
            raise InputError(f"{name} must lie in {bracket}{self.low}, {self.high}], got {got}")
        return number

    def check_tuple(
        self, name: str, value: object, *, length: int | None = None, max_length: int = 64
    ) -> tuple:
        """``value``, a list or tuple of ``length`` items (any number up to ``max_length`` when
        ``None``), as a tuple of items each checked by this setting; ``InputError`` naming ``name``
        otherwise (a text or a mapping is not a list of numbers, though Python would iterate it)."""
        want = f"{length} values" if length is not None else f"a list of at most {max_length} values"
        if not isinstance(value, (list, tuple)):
            raise InputError(f"{name} must be {want}, got {short_repr(value)}")
        if (length is not None and len(value) != length) or len(value) > max_length:
            raise InputError(f"{name} must be {want}, got {len(value)}: {short_repr(value)}")
        return tuple(self.check(name, item) for item in value)


def check_settings(values: Mapping[str, object], settings: Mapping[str, Setting]) -> dict[str, object]:
    """``values`` checked by their ``settings`` (names without a setting pass unchanged)."""
    return {
        name: settings[name].check(name, value) if name in settings else value
        for name, value in values.items()
    }


def short_repr(value: object, limit: int = 40) -> str:
    """``repr(value)`` on one line, cut to ``limit`` characters (a note or a database row may hold
    a text or a number of any length)."""
    try:
        text = " ".join(repr(value).split())
    except Exception:  # a hostile object's own __repr__ may fail; its type is enough to name it
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def exception_line(exc: BaseException, limit: int | None = None) -> str:
    """``"Type: message"`` of an exception on one line, cut to ``limit`` characters if given."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:limit]
