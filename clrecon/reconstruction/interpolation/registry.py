"""The interpolation-method registry: the one list of methods (``docs/extending.md``).

Each method module registers its :class:`~clrecon.reconstruction.interpolation.base.Method`
with :func:`register_method`; the package ``__init__`` imports the modules, so registration
order (= ``recon.methods`` default order) is the import order there. The helpers below give
every derived list; nothing else in clrecon spells out method names as a list.
"""

from __future__ import annotations

from clrecon.core.registry import Registry
from clrecon.reconstruction.interpolation.base import Method

METHODS: Registry[Method] = Registry("interpolation method")


def register_method(*, name: str, label: str, neighbours: int | None, target_grid: str, axes: tuple,
                    five_d: bool, marker: str, rank: int, opt_in: bool = False,
                    stage: str | None = None, first_pass: str | None = None):
    """Decorator registering a ``weights`` function as method ``name`` (see :class:`Method`).

    A ``first_pass`` must be a 5-D method registered before ``name`` (its volumes are the
    (cardiac, amplitude) images the later stage starts from); ValueError otherwise."""
    if first_pass is not None and (first_pass not in METHODS.names or METHODS[first_pass].target_grid != "5d"):
        raise ValueError(f"method {name!r}: first_pass = {first_pass!r}: must be a 5-D method registered before "
                         f"it (registered: {', '.join(METHODS.names)})")

    def add(fn):
        METHODS.register(name)(Method(name=name, label=label, neighbours=neighbours, target_grid=target_grid,
                                      axes=tuple(axes), five_d=five_d, marker=marker, rank=rank, weights=fn,
                                      opt_in=opt_in, stage=stage, first_pass=first_pass))
        return fn

    return add


def method_names() -> tuple[str, ...]:
    """Every method, in registration order (the ``recon.methods`` default)."""
    return METHODS.names


def default_methods() -> tuple[str, ...]:
    """The ``recon.methods`` default: every method but the opt-in ones (``Method.opt_in``), in registration order."""
    return tuple(n for n, m in METHODS.items() if not m.opt_in)


def second_pass_methods(names=None) -> tuple[str, ...]:
    """The methods (of ``names``, default all) whose volumes a later stage makes (``Method.stage``),
    not ``reconstruct``."""
    return tuple(n for n in (METHODS.names if names is None else names) if METHODS[n].stage is not None)


def first_pass(name: str) -> str:
    """The method whose volumes ``name`` (a method with a ``stage``: :func:`second_pass_methods`) is
    made from (``Method.first_pass``); ValueError for a method the ``reconstruct`` stage makes."""
    fp = METHODS[name].first_pass
    if fp is None:
        raise ValueError(f"method {name!r} is made by the reconstruct stage: it has no first pass")
    return fp


def by_rank(names=None) -> tuple[str, ...]:
    """``names`` (default: all) that are registered, best first (report tables, export default)."""
    pool = METHODS.names if names is None else tuple(n for n in METHODS.names if n in set(names))
    return tuple(sorted(pool, key=lambda n: METHODS[n].rank))


def figure_order(names=None) -> tuple[str, ...]:
    """``names`` (default: all) that are registered, simplest first (figure columns)."""
    return tuple(reversed(by_rank(names)))


def five_d_methods() -> tuple[str, ...]:
    """The 5DCT methods, in registration order."""
    return tuple(n for n, m in METHODS.items() if m.five_d)


def resp_grid_methods() -> tuple[str, ...]:
    """Methods solved on the respiratory-only target grid (cardiac-blind, r4DCT-like)."""
    return tuple(n for n, m in METHODS.items() if m.target_grid == "resp")


def markers() -> dict[str, str]:
    """Figure marker per method."""
    return {n: m.marker for n, m in METHODS.items()}
