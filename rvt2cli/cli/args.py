"""Command-line argument types that check their range while parsing, and a parser whose errors are one
line (`rvt2 CMD: error: ...`, exit code 2), like every other user error of rvt2."""

import argparse
import math
import sys


class Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line naming the option and the fix, not the usage block."""

    def error(self, message: str):
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def integer(minimum: int | None = None, maximum: int | None = None):
    """An int within [minimum, maximum]."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"{value} is below the minimum {minimum}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"{value} is above the maximum {maximum}")
        return value

    parse.__name__ = "integer"
    return parse


def number(minimum: float | None = None, maximum: float | None = None, exclusive_minimum: bool = False):
    """A finite float within [minimum, maximum] (or (minimum, maximum] with `exclusive_minimum`)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if minimum is not None and (value < minimum or (exclusive_minimum and value == minimum)):
            raise argparse.ArgumentTypeError(f"{value:g} must be {'above' if exclusive_minimum else 'at least'} {minimum:g}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"{value:g} is above the maximum {maximum:g}")
        return value

    parse.__name__ = "number"
    return parse


def numbers(count: int):
    """`count` comma-separated finite floats, e.g. scene bounds."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {count} comma-separated numbers") from None
        if len(values) != count or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"{text!r} is not {count} comma-separated finite numbers")
        return values

    parse.__name__ = "numbers"
    return parse


def names(text: str) -> tuple[str, ...]:
    """A comma-separated list of names (empty entries dropped)."""
    return tuple(t.strip() for t in text.split(",") if t.strip())


def weights(text: str) -> dict[str, float]:
    """Comma-separated NAME=W pairs with finite positive weights, e.g. insert_peg=3,plug_charger=3."""
    out = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        name, sep, value = item.partition("=")
        try:
            weight = float(value)
        except ValueError:
            weight = math.nan
        if not sep or not name.strip() or not math.isfinite(weight) or weight <= 0:
            raise argparse.ArgumentTypeError(f"{item!r} is not NAME=WEIGHT with a positive weight (e.g. insert_peg=3)")
        out[name.strip()] = weight
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r} names no task (e.g. insert_peg=3,plug_charger=3)")
    return out


def task_expert(text: str) -> tuple[str, str]:
    """TASK=module:function: a task's scripted expert other than its own (`--expert`)."""
    name, sep, spec = text.partition("=")
    if not sep or ":" not in spec:
        raise argparse.ArgumentTypeError(f"{text!r}: give TASK=module:function")
    return name.strip(), spec.strip()


POSITIVE = number(0.0, exclusive_minimum=True)  # lengths, times, thresholds, learning rates
COUNT = integer(minimum=1)          # episodes, steps, workers, batch size, ...
NON_NEGATIVE = integer(minimum=0)   # seeds, frames, held-out episodes, ...
SEED = integer(minimum=0, maximum=2**31 - 1)
