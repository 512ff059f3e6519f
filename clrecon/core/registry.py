"""Registries: the one list of each kind of extension (interpolation methods, detectors, phantom
sources, output writers, ...). Every list a user sees -- CLI choices, scene checks, report and
figure order, export preference -- is read from its registry, so adding an entry is one module
that registers itself (``docs/extending.md``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Generic, TypeVar

from clrecon.core.errors import ClreconError

T = TypeVar("T")


class UnknownEntry(ClreconError, KeyError):
    """A name that is not registered; the message lists what is."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


class Registry(Mapping, Generic[T]):
    """Name -> entry, in registration order; ``kind`` names the registry in errors."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._entries: dict[str, T] = {}

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator (or call) registering ``entry`` under ``name``; a name registers once."""

        def add(entry: T) -> T:
            if name in self._entries:
                raise ValueError(f"{self.kind} {name!r} is registered twice")
            self._entries[name] = entry
            return entry

        return add

    def __getitem__(self, name: str) -> T:
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            raise UnknownEntry(f"unknown {self.kind} {name!r}; allowed: {', '.join(self._entries)}") from None

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def names(self) -> tuple[str, ...]:
        """Registered names in registration order."""
        return tuple(self._entries)
