"""Config sections that validate themselves: the base every stage's settings are built on.

A section is a frozen, keyword-only dataclass whose fields carry their own check and a human
description of what is allowed (:func:`field_of`). Construction coerces what TOML and Python
users naturally pass (a list for a tuple, an int for a float) and then checks every field, so
``ScannerConfig(sid_mm=-1.0)`` raises :class:`~clrecon.core.errors.SceneError` naming the key,
the value and what is allowed, exactly as a scene file with that value would. The TOML loader
(:mod:`clrecon.config.scene`) only maps keys onto sections.
"""

from __future__ import annotations

import math
from dataclasses import field, fields
from typing import Any, ClassVar

from clrecon.core.errors import SceneError


def _pos(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _nonneg(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x >= 0


def _num(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _posint(x):
    return isinstance(x, int) and not isinstance(x, bool) and x > 0


def _nonnegint(x):
    return isinstance(x, int) and not isinstance(x, bool) and x >= 0


def _bool(x):
    return isinstance(x, bool)


def _frac(x):
    return _num(x) and 0 <= x <= 1


#: (what is allowed, check) pairs for the common kinds of value.
POS = ("a number > 0", _pos)
NONNEG = ("a number >= 0", _nonneg)
NUM = ("a finite number", _num)
POSINT = ("an integer > 0", _posint)
NONNEGINT = ("an integer >= 0", _nonnegint)
BOOL = ("true or false", _bool)
FRAC = ("a number in [0, 1]", _frac)


def _why(unit: str, why: str) -> str:
    return (f" {unit}" if unit else "") + (f" ({why})" if why else "")


def number_in(lo: float, hi: float, unit: str = "", why: str = ""):
    """A finite number in [lo, hi]; ``unit`` and ``why`` (the physical reason for the range) join the message."""
    return (f"a number in [{lo:g}, {hi:g}]{_why(unit, why)}", lambda x: _num(x) and lo <= x <= hi, (lo, hi))


def zero_or_in(lo: float, hi: float, unit: str = "", why: str = ""):
    """0 (a key's "off" or "derive it" value) or a finite number in [lo, hi]."""
    return (f"0 or a number in [{lo:g}, {hi:g}]{_why(unit, why)}",
            lambda x: _num(x) and (x == 0 or lo <= x <= hi), (lo, hi))


def integer_in(lo: int, hi: int, why: str = ""):
    """An integer in lo..hi (not a bool)."""
    return (f"an integer in {lo}..{hi}{_why('', why)}",
            lambda x: isinstance(x, int) and not isinstance(x, bool) and lo <= x <= hi, (lo, hi))


def numbers_in(n: int, lo: float, hi: float, unit: str = "", why: str = ""):
    """A list of ``n`` finite numbers, each in [lo, hi]."""
    return (f"a list of {n} numbers in [{lo:g}, {hi:g}]{_why(unit, why)}",
            lambda v: isinstance(v, tuple) and len(v) == n and all(_num(x) and lo <= x <= hi for x in v), (lo, hi))


#: Seeds: what NumPy's SeedSequence, HDF5 attributes and JSON readers all hold (a signed 64-bit integer).
SEED = integer_in(0, 2 ** 63 - 1, "a signed 64-bit seed")


def one_of(names):
    """One of the given names (e.g. a registry's ``names``)."""
    names = tuple(names)
    return ("one of " + ", ".join(names), lambda x: x in names)


def field_of(default, allowed: str, check, doc: str = "", value_range: tuple | None = None):
    """A dataclass field carrying its check, the text of what is allowed, its doc and (for a number
    in a range) the range ``(lo, hi)``, which the tests run at both ends (tests/support/hostile_scenes.py)."""
    return field(default=default, metadata={"allowed": allowed, "check": check, "doc": doc, "range": value_range})


def F(default, kind, doc: str = ""):
    """:func:`field_of` with an ``(allowed, check)`` or ``(allowed, check, (lo, hi))`` kind such as :data:`POS`
    or :func:`number_in`'s."""
    return field_of(default, kind[0], kind[1], doc, kind[2] if len(kind) > 2 else None)


def value_ranges(cls) -> dict[str, tuple]:
    """``{key: (lo, hi)}`` of a section's keys that are numbers in a range."""
    return {f.name: f.metadata["range"] for f in fields(cls) if f.metadata.get("range") is not None}


def _coerce(default: Any, value: Any) -> Any:
    """What a TOML table or a Python caller gives -> the field's type (list -> tuple, int -> float,
    a table -> the nested section of a section-valued field, e.g. ``[recon.mc]``)."""
    if isinstance(default, Section) and isinstance(value, dict):
        return type(default).from_table(value)
    if isinstance(value, list):
        value = tuple(value)
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if (isinstance(default, tuple) and isinstance(value, tuple) and value and default
            and isinstance(default[0], float)
            and all(isinstance(x, int) and not isinstance(x, bool) for x in value)):
        return tuple(float(x) for x in value)
    return value


class Section:
    """Base of a frozen, keyword-only config dataclass that validates itself at construction.

    Subclasses set ``SECTION`` (the TOML table name used in messages) and declare their
    fields with :func:`F` / :func:`field_of`.
    """

    SECTION: ClassVar[str] = ""

    def __post_init__(self) -> None:
        for f in fields(self):
            if "check" not in f.metadata:
                continue
            value = _coerce(f.default, getattr(self, f.name))
            object.__setattr__(self, f.name, value)
            if not f.metadata["check"](value):
                shown = list(value) if isinstance(value, tuple) else value  # as the TOML list it came from
                raise SceneError(f"{self.SECTION}.{f.name} = {shown!r}: must be {f.metadata['allowed']}")
        self.check()

    @classmethod
    def from_table(cls, raw: dict):
        """The section from a TOML table (a nested section's); an unknown key is refused in one line."""
        names = [f.name for f in fields(cls)]
        for key in raw:
            if key not in names:
                raise SceneError(f"{cls.SECTION}.{key}: unknown key; allowed: {', '.join(names)}")
        return cls(**raw)

    def check(self) -> None:
        """Checks across this section's fields (override); raise :class:`SceneError`."""
