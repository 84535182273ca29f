"""The project's import graph: acyclic, and the config modules are leaves.

Read from the source (AST) rather than by importing: every import counts, also those inside
functions (a cycle broken by a function-level import is still a cycle), except under
`if TYPE_CHECKING:`. Importing a module also runs its packages' __init__, so those count for the
leaves too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

ROOT = Path(__file__).resolve().parents[1] / "plotmosaic"


def _name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _is_config(module: str) -> bool:
    return module == "plotmosaic.config" or module.startswith("plotmosaic.config.")


def _project(name: str) -> str | None:
    """The project module an import name loads (its longest known prefix)."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in MODULES:
            return ".".join(parts[:k])
    return None


def _imports(module: str, path: Path) -> list[tuple[str, int]]:
    """(project module, line) of every import in the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for n in ast.walk(node)
    }
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in MODULES]
            found += [(s, node.lineno) for s in subs]
            if len(subs) < len(node.names):  # names from the module itself
                found.append((base, node.lineno))
    return [(m, line) for name, line in found if (m := _project(name)) and m != module]


def _graph() -> nx.DiGraph:
    G = nx.DiGraph()
    for module, path in MODULES.items():
        G.add_node(module)
        for target, line in _imports(module, path):
            lines = G.edges[module, target]["lines"] if G.has_edge(module, target) else []
            G.add_edge(module, target, lines=sorted({*lines, line}))
    return G


def _where(module: str, lines: list[int]) -> str:
    return ", ".join(f"{MODULES[module].relative_to(ROOT.parent)}:{n}" for n in lines)


def test_scan_finds_the_imports_it_must():
    """The scanner itself: module-level, function-level and relative imports are all seen."""
    G = _graph()
    assert G.has_edge("plotmosaic.align.pair", "plotmosaic.align.scene")  # `from pkg import module`
    assert G.has_edge("plotmosaic.commands.align", "plotmosaic.align.pipeline")
    assert G.has_edge("plotmosaic.stages.register_plot", "plotmosaic.config.register")
    assert not G.has_edge("plotmosaic.config.register", "plotmosaic.stages.register_plot")


def test_import_graph_is_acyclic():
    G = _graph()
    cycles = sorted(nx.simple_cycles(G), key=lambda c: (len(c), c))
    described = [
        " -> ".join(f"{a} ({_where(a, G.edges[a, b]['lines'])})" for a, b in zip(c, c[1:] + c[:1]))
        for c in cycles[:10]
    ]
    assert not cycles, f"{len(cycles)} import cycles:\n" + "\n".join(described)


CONFIG_MODULES = sorted(m for m in MODULES if _is_config(m))


@pytest.mark.parametrize("module", CONFIG_MODULES)
def test_config_module_is_a_leaf(module):
    """A config module imports nothing of the project but other config modules, and importing it
    (with its packages' __init__) loads nothing else either."""
    G = _graph()
    parents = [".".join(module.split(".")[:k]) for k in range(1, module.count(".") + 1)]
    loaded = set()
    for start in [module, *parents]:
        loaded |= {start} | nx.descendants(G, start)
    packages = {m for m in loaded if MODULES[m].name == "__init__.py"}
    others = sorted(m for m in loaded - packages if not _is_config(m))
    edges = [
        f"{a} imports {b} ({_where(a, G.edges[a, b]['lines'])})"
        for a, b in G.edges
        if a in loaded and b in others
    ]
    assert not others, "\n".join(edges)


def test_all_config_modules_found():
    expected = {
        "plotmosaic.config.settings",
        "plotmosaic.config.align",
        "plotmosaic.config.coarse",
        "plotmosaic.config.judge",
        "plotmosaic.config.register",
        "plotmosaic.config.merge",
        "plotmosaic.config.report",
    }
    assert expected <= set(CONFIG_MODULES)
