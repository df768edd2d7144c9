"""Command-line option types shared by the commands (argparse ``type=`` callables)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def finite_number(unit: str, minimum: float = 0.0, allow_minimum: bool = True) -> Callable[[str], float]:
    """An argparse type: a finite number of ``unit`` at least ``minimum`` (above it when not
    ``allow_minimum``).  ``nan`` and ``inf`` parse as floats, so they must be refused here: every
    comparison with nan is false, and a check such as ``value < 0`` lets it through."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number of {unit}, got {text!r}") from None
        ok = math.isfinite(value) and (value >= minimum if allow_minimum else value > minimum)
        if not ok:
            bound = f"at least {minimum:g}" if allow_minimum else f"above {minimum:g}"
            raise argparse.ArgumentTypeError(f"must be a finite number of {unit} {bound}, got {text!r}")
        return value

    return parse
