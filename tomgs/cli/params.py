"""The CLI's numeric option types: every number a command takes is checked here, at parse time,
before any work or heavy import. A value that is not a number, not finite, or outside its range is
one line (exit 2) naming the option, the value and the range:

    Error: --budget inf: not a finite number; give seconds in 1..1e7

    Number(low, high)      a finite float (or, integer=True, an int) in [low, high]; low_open /
                           high_open exclude an end
    Numbers(counts, ...)   comma-separated finite floats, as many as one of `counts`, each in range
    Colour()               r,g,b each in [0, 1]
    Size()                 WIDTHxHEIGHT, each side 1..tomgs.cameras.MAX_SIDE

The ranges are the library's where it has one (frame sides, frame rates); elsewhere they are wide
enough for any real use and keep every later computation finite.
"""

from __future__ import annotations

import math

import click

from tomgs.constants import MAX_SIDE
from tomgs.io.writer import FPS_RANGE

COORDINATE_MAX = 1e6  # scene units: translations, centres, offsets (float32 keeps ~0.1 units there)
SCALE_RANGE = (1e-6, 1e6)  # scale factors of an edit
SEED_MAX = 2**63 - 1  # torch's generators take 64 bits; seed + rank offsets stay below 2**64


class ParamFailure(click.ClickException):
    """A bad option value: one line, exit 2 (click's own BadParameter prints the usage text too)."""

    exit_code = 2


def _name(param) -> str:
    if param is None:
        return "value"
    opts = [o for o in getattr(param, "opts", []) if o.startswith("--")] or list(getattr(param, "opts", []))
    return opts[0] if opts else param.human_readable_name


def _show(x: float, integer: bool = False) -> str:
    """A range end as people write it: 16384, 0.1, 1e6, 9223372036854775807 (an integer's in full)."""
    if integer or (float(x).is_integer() and abs(x) < 1e5):
        return str(int(x))
    return f"{x:g}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def _printable(value) -> str:
    """`value` as a message shows it: quoted when it holds what a terminal would not print as is."""
    text = str(value)
    return text if text.isprintable() and text.strip() == text and text else repr(text)


def _number(text, integer: bool):
    """`text` (or a number) as a float or int; ValueError when it is not one."""
    if isinstance(text, bool):
        raise ValueError
    if integer:
        if isinstance(text, int):
            return text
        if isinstance(text, float):
            if not text.is_integer():
                raise ValueError
            return int(text)
        return int(str(text).strip())
    return float(text) if isinstance(text, (int, float)) else float(str(text).strip())


class Number(click.ParamType):
    """A finite float (or int, `integer=True`) in [low, high]; `low_open` / `high_open` leave an end
    out; `what` says what the number counts (seconds, pixels) in messages."""

    def __init__(self, low: float | None = None, high: float | None = None, *, integer: bool = False,
                 low_open: bool = False, high_open: bool = False, what: str = ""):
        self.low, self.high, self.integer = low, high, integer
        self.low_open, self.high_open, self.what = low_open, high_open, what
        self.name = "integer" if integer else "number"

    def range_text(self) -> str:
        what = f"{self.what} " if self.what else ("an integer " if self.integer else "a number ")
        if self.low is not None and self.high is not None:
            left, right = "(" if self.low_open else "", ")" if self.high_open else ""
            if left or right:
                return f"{what}in {left or '['}{_show(self.low)}, {_show(self.high)}{right or ']'}"
            return f"{what}in {_show(self.low, self.integer)}..{_show(self.high, self.integer)}"
        if self.low is not None:
            return f"{what}{'above' if self.low_open else 'of at least'} {_show(self.low, self.integer)}"
        if self.high is not None:
            return f"{what}{'below' if self.high_open else 'of at most'} {_show(self.high, self.integer)}"
        return what.strip()

    def bounds_text(self) -> str:
        """The range alone: 1..1e7, (0, 1e6]."""
        text = self.range_text()
        return text[text.index("in ") + 3:] if "in " in text else text

    def get_metavar(self, param, ctx=None) -> str:  # noqa: ARG002 - click's signature
        return f"{'INTEGER' if self.integer else 'NUMBER'} {self.bounds_text()}"

    def check(self, value, name: str, whole=None):
        """`value` as a number in range, else ParamFailure naming `name` (and `whole`, the option's
        text, when `value` is one part of it)."""
        said = f"{name} {_printable(value)}:" if whole is None else f"{name} {_printable(whole)}: {_printable(value)}"
        try:
            number = _number(value, self.integer)
        except (ValueError, TypeError, OverflowError):
            kind = "an integer" if self.integer else "a number"
            raise ParamFailure(f"{said} {'is ' if whole is not None else ''}not {kind}; give {self.range_text()}") \
                from None
        if not self.integer and not math.isfinite(number):
            raise ParamFailure(f"{said} {'is ' if whole is not None else ''}not a finite number; give "
                               f"{self.range_text()}")
        low_bad = self.low is not None and (number <= self.low if self.low_open else number < self.low)
        high_bad = self.high is not None and (number >= self.high if self.high_open else number > self.high)
        if low_bad or high_bad:
            raise ParamFailure(f"{said} {'is ' if whole is not None else ''}out of range; give {self.range_text()}")
        return number

    def convert(self, value, param, ctx):
        return self.check(value, _name(param))


class Numbers(click.ParamType):
    """Comma-separated finite numbers, as many as one of `counts`, each checked by `each` (a Number);
    a tuple of floats."""

    name = "numbers"

    def __init__(self, counts=(3,), each: Number | None = None, shape: str | None = None):
        self.counts, self.each = tuple(counts), each or Number()
        self.shape = shape or " or ".join(",".join("xyz"[:n]) if n > 1 else "s" for n in self.counts)

    def get_metavar(self, param, ctx=None) -> str:  # noqa: ARG002 - click's signature
        return self.shape.upper().replace(" OR ", "|")

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        name = _name(param)
        parts = str(value).split(",")
        if len(parts) not in self.counts:
            counts = " or ".join(map(str, self.counts))
            raise ParamFailure(f"{name} {_printable(value)}: give {counts} comma-separated numbers ({self.shape}), "
                               f"each {self.each.range_text()}")
        return tuple(float(self.each.check(part, name, value)) for part in parts)


class Colour(Numbers):
    """r,g,b each in [0, 1]."""

    def __init__(self):
        super().__init__((3,), Number(0.0, 1.0, what="a number"), "r,g,b")


class Size(click.ParamType):
    """WIDTHxHEIGHT in pixels, each side 1..MAX_SIDE: (width, height)."""

    name = "size"

    def get_metavar(self, param, ctx=None) -> str:  # noqa: ARG002 - click's signature
        return "WIDTHxHEIGHT"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        name, side = _name(param), Number(1, MAX_SIDE, integer=True, what="pixels")
        parts = str(value).lower().split("x")
        if len(parts) != 2:
            raise ParamFailure(f"{name} {_printable(value)}: give WIDTHxHEIGHT like 320x180, each side "
                               f"{side.range_text()}")
        return tuple(side.check(part, name, value) for part in parts)


# the numbers commands share, by what they mean
FPS = Number(*FPS_RANGE, what="frames per second")
SIDE = Number(16, MAX_SIDE, integer=True, what="pixels")
FOCAL = Number(1.0, 1e6, what="pixels")
SEED = Number(0, SEED_MAX, integer=True)
SH_DEGREE = Number(0, 3, integer=True)
COORDINATES = Numbers((3,), Number(-COORDINATE_MAX, COORDINATE_MAX, what="scene units"))
SCALES = Numbers((1, 3), Number(*SCALE_RANGE, what="a factor"))
CELL = Number(0.0, COORDINATE_MAX, low_open=True, what="scene units")


__all__ = ["CELL", "COORDINATES", "COORDINATE_MAX", "Colour", "FOCAL", "FPS", "Number", "Numbers",
           "ParamFailure", "SCALES", "SCALE_RANGE", "SEED", "SEED_MAX", "SH_DEGREE", "SIDE", "Size"]
