"""clrecon: simulate helical CT of a breathing, beating thorax and reconstruct 5DCT.

The subpackages follow the pipeline; a package imports only those of an earlier level. The
order is ``[tool.clrecon.layers]`` in ``pyproject.toml`` (checked by ``tests/core/test_import_graph.py``;
why this order: ``docs/data-flow.md`` "Layering").

Notebook API: :func:`load_scene`, :func:`run`, :func:`open_run` (see ``docs/api.md``).
"""

from clrecon.core.versions import PROJECTOR_VERSION, __version__

#: The notebook API (:mod:`clrecon.api`), imported on first use so that ``import clrecon``
#: (and every command) stays light: ``from clrecon import load_scene, run, open_run``.
_API = ("load_scene", "run", "open_run", "RunResult")

__all__ = ["PROJECTOR_VERSION", "__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from clrecon import api

        return getattr(api, name)
    raise AttributeError(f"module 'clrecon' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
