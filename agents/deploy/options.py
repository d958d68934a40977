"""Command-line values of the deployment tools that name a thing: ``NAME=VALUE`` items
(``otr sim-robot --object-mesh box=box.obj --object-mass box=2.5``, ``otr deploy --mocap-name
largebox=box_1``), parsed one way, with errors that name the flag and the item."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")


def name_values(items: Iterable[str] | None, flag: str, form: str, example: str,
                convert: Callable[[str], T] = str) -> dict[str, T]:
    """``flag``'s repeated ``NAME=VALUE`` items as {name: convert(value)}, in order. A malformed
    item (no ``=``, an empty side), a name given twice or a value ``convert`` refuses (it raises
    ``ValueError``) raises ``ValueError`` naming the flag, the item and the expected ``form``
    (e.g. ``"NAME=FILE"``) with an ``example``."""
    out: dict[str, T] = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name or not value:
            raise ValueError(f"{flag} {item!r}: expected {form} (e.g. {example})")
        if name in out:
            raise ValueError(f"{flag} {item!r}: '{name}' is given twice")
        try:
            out[name] = convert(value)
        except ValueError as exc:
            raise ValueError(f"{flag} {item!r}: {exc}") from None
    return out


def positive_float(value: str) -> float:
    """A finite number > 0 (a mass in kg, a friction coefficient)."""
    try:
        x = float(value)
    except ValueError:
        raise ValueError(f"'{value}' is not a number") from None
    if not math.isfinite(x) or x <= 0.0:
        raise ValueError(f"{value} must be a finite number > 0")
    return x
