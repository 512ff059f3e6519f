"""The package's imports go one way: no cycles, and no imports inside functions to hide one.

The graph is read from the source with ``ast`` (nothing is imported). An import of
``clrecon.a.b`` is an edge to that module and to the package ``clrecon.a`` whose
``__init__`` runs first, except a module's own enclosing packages (they are already running
when it is imported). Imports inside functions count too: a cycle hidden behind one is still a
cycle. Lazy imports are allowed only of optional heavy packages outside ``clrecon`` (pyvista,
pydicom, nibabel, ...), for the CLI's subcommands, which are imported on demand so that
``clrecon --help`` stays fast, and for the package's notebook API (``LAZY_OK``).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10: the backport the package depends on there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("clrecon",)
#: modules allowed to import clrecon modules inside functions, and why
LAZY_OK = {
    "clrecon.cli": "each subcommand imports its stage on demand (fast --help)",
    "clrecon": "the notebook API is imported on first attribute access (PEP 562), so `import clrecon` stays light",
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _imports(path: Path, name: str, known: set[str]):
    """(target module, lineno, inside a function) for every import of a project module."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out = []

    def walk(node, in_func):
        for child in ast.iter_child_nodes(node):
            f = in_func or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for a in child.names:
                    out.append((a.name, child.lineno, in_func))
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = base[:len(base) - child.level + 1]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module or ""
                for a in child.names:
                    sub = f"{mod}.{a.name}"
                    out.append((sub if sub in known else mod, child.lineno, in_func))
            elif isinstance(child, ast.If) and _is_type_checking(child.test):
                continue  # annotations only: never executed
            walk(child, f)

    walk(tree, False)
    return [(t, ln, f) for t, ln, f in out if t.split(".")[0] in PACKAGES]


def _is_type_checking(test) -> bool:
    return isinstance(test, ast.Name) and test.id == "TYPE_CHECKING"


def _graph():
    mods = _modules()
    known = set(mods)
    edges: dict[str, set[str]] = {m: set() for m in mods}
    lazy = []
    for m, path in mods.items():
        ancestors = {".".join(m.split(".")[:i]) for i in range(1, m.count(".") + 1)}
        for target, lineno, in_func in _imports(path, m, known):
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                t = ".".join(parts[:i])
                if t in known and t != m and t not in ancestors:
                    edges[m].add(t)
            if in_func and m not in LAZY_OK:
                lazy.append(f"{path.relative_to(ROOT)}:{lineno} imports {target} inside a function")
    return edges, lazy


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_graph_is_read_from_the_real_tree():
    edges, _ = _graph()
    truth = "clrecon.pipeline.stages.truth"
    assert truth in edges and "clrecon.evaluation.groundtruth" in edges[truth]


def test_no_import_cycles():
    edges, _ = _graph()
    assert _cycles(edges) == []


def test_cycle_detector_sees_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_project_imports_inside_functions():
    _, lazy = _graph()
    assert lazy == []


# ----------------------------------------------------------------------------------------
# packages: the folders stand in the order pyproject.toml's [tool.clrecon.layers] gives
def _drawn_levels() -> list[list[str]]:
    """``[tool.clrecon.layers] order`` of pyproject.toml: the levels of package names, first to last."""
    with open(ROOT / "pyproject.toml", "rb") as fh:
        order = tomllib.load(fh).get("tool", {}).get("clrecon", {}).get("layers", {}).get("order")
    assert order, "pyproject.toml has no [tool.clrecon.layers] order"
    return [[str(p) for p in level] for level in order]


def _package(module: str) -> str:
    """``clrecon.scan.table`` -> ``scan``; ``clrecon.viewer.app`` -> ``viewer``;
    ``clrecon``/``clrecon.__main__`` -> ``""``."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] == "__main__":
        return ""  # the package root: PEP 562 lazy API and `python -m clrecon`, above everything
    return parts[1]


def _backward_package_edges(edges: dict[str, set[str]], levels: list[list[str]]) -> list[str]:
    """Module imports from a package to one at the same or a later level (peers do not import each other)."""
    rank = {p: i for i, level in enumerate(levels) for p in level}
    bad = []
    for m, targets in sorted(edges.items()):
        a = _package(m)
        for t in sorted(targets):
            b = _package(t)
            if not a or a == b or not b:
                continue
            if a not in rank or b not in rank:
                missing = a if a not in rank else b
                bad.append(f"{m} -> {t}: package {missing!r} is not in pyproject.toml's [tool.clrecon.layers]")
            elif rank[b] >= rank[a]:
                bad.append(f"{m} -> {t}: {a} (level {rank[a]}) may import only packages drawn before it, "
                           f"not {b} (level {rank[b]})")
    return bad


def test_the_data_flow_note_draws_the_same_levels():
    """docs/data-flow.md "Layering" draws the levels for a reader; it must say what pyproject.toml says."""
    for line in (ROOT / "docs" / "data-flow.md").read_text().splitlines():
        if line.startswith("core -> "):
            assert [[p.strip() for p in lv.split(",")] for lv in line.split("->")] == _drawn_levels()
            return
    raise AssertionError("docs/data-flow.md has no layering line starting 'core -> '")


def test_every_package_is_drawn_once():
    levels = _drawn_levels()
    drawn = [p for level in levels for p in level]
    assert len(drawn) == len(set(drawn))
    on_disk = {_package(m) for m in _modules()} - {""}
    assert on_disk == set(drawn), f"drawn {sorted(drawn)}, on disk {sorted(on_disk)}"


def test_packages_import_only_earlier_packages():
    edges, _ = _graph()
    assert _backward_package_edges(edges, _drawn_levels()) == []


def test_package_check_sees_a_backward_import():
    levels = [["core"], ["config"], ["reconstruction"]]
    edges = {"clrecon.config.scene": {"clrecon.reconstruction.filters", "clrecon.core.errors"},
             "clrecon.reconstruction.rebin": {"clrecon.config.scene"}, "clrecon.core.errors": set()}
    bad = _backward_package_edges(edges, levels)
    assert len(bad) == 1 and bad[0].startswith("clrecon.config.scene -> clrecon.reconstruction.filters")
    peers = _backward_package_edges({"clrecon.api": {"clrecon.cli"}}, [["api", "cli"]])
    assert len(peers) == 1
