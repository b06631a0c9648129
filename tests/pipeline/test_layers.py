"""The house's shape (issue 53): layers with arrows in one direction, no import circle, short files.

Read from the modules' own source (every ``import`` statement, those inside functions included, those
under ``if TYPE_CHECKING:`` left out: they never run), so a lazy import inside a function counts as much
as one at the top of a module.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: The engine's layers, lowest first; a module may import its own layer's modules and lower ones only.
#: Every other module of ``pipeline`` is a front end, above them all.
LAYERS = (
    ("store", ("pipeline.engine.store",)),
    ("config", ("pipeline.engine.config", "pipeline.engine.compose")),
    ("plan", ("pipeline.engine.registry", "pipeline.engine.plan", "pipeline.engine.edits", "pipeline.engine.lookup")),
    ("execute", ("pipeline.engine.execute", "pipeline.engine.kernels")),
)
#: Longest file allowed in pipeline/ and stages/ (lines).
MAX_LINES = 500


def module_files(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Dotted module name → file, for every ``.py`` file below the given top-level packages."""
    out = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of the statements under ``if TYPE_CHECKING:`` (never run)."""
    skipped = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return skipped


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module → the modules of ``modules`` it imports (``from package import name`` of a sub-module
    counts as importing that sub-module; of anything else, as importing the package)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        skipped = _type_checking_nodes(tree)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in skipped:
                continue
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parent = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join([*parent, *([base] if base else [])])
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in modules and "." in target:
                    target = target.rpartition(".")[0]
                if target in modules and target != name:
                    found.add(target)
        graph[name] = found
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def layer_of(module: str) -> int | None:
    """The engine layer of a ``pipeline`` module (its index in :data:`LAYERS`), None for a front end."""
    for i, (_, prefixes) in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    return None


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """``a -> b`` for each import of a higher layer (or of a front end) by an engine module."""
    bad = []
    for module, imported in sorted(graph.items()):
        if not module.startswith("pipeline.engine"):
            continue
        mine = layer_of(module)
        for other in sorted(imported):
            if not other.startswith("pipeline"):
                continue
            theirs = layer_of(other)
            if theirs is None and other not in ("pipeline", "pipeline.engine"):
                bad.append(f"{module} -> {other} (a front end)")
            elif theirs is not None and mine is not None and theirs > mine:
                bad.append(f"{module} -> {other} ({LAYERS[theirs][0]} is above {LAYERS[mine][0]})")
    return bad


@pytest.fixture(scope="module")
def graph():
    return import_graph(module_files(ROOT, ("pipeline", "stages")))


def test_no_import_circle_in_pipeline_or_stages(graph):
    assert import_circles(graph) == []


def test_the_engine_imports_no_front_end_and_no_layer_above_its_own(graph):
    assert layer_violations(graph) == []
    # every engine module belongs to a layer: a new one is placed on purpose
    assert [m for m in graph if m.startswith("pipeline.engine.") and layer_of(m) is None
            and m not in ("pipeline.engine.execute", "pipeline.engine.kernels")] == []


def test_no_file_over_500_lines_in_pipeline_or_stages():
    long = {str(p.relative_to(ROOT)): n for p in module_files(ROOT, ("pipeline", "stages")).values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_the_checks_fail_on_a_circle_and_on_an_engine_module_that_imports_a_front_end(tmp_path):
    """The checks above can fail: a made-up tree with both faults, one of them behind a lazy import."""
    files = {
        "pipeline/__init__.py": "",
        "pipeline/cli.py": "from pipeline.engine.execute.batch import run\n",
        "pipeline/engine/__init__.py": "",
        "pipeline/engine/store.py": "def save():\n    from pipeline.engine.plan import Task\n",
        "pipeline/engine/plan.py": "from pipeline.engine import store\nclass Task: ...\n",
        "pipeline/engine/execute/__init__.py": "",
        "pipeline/engine/execute/batch.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                             "    from pipeline import inspect\n"
                                             "def run():\n    from pipeline.cli import main\n"),
        "pipeline/inspect.py": "",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    made_up = import_graph(module_files(tmp_path, ("pipeline",)))
    assert import_circles(made_up) == [["pipeline.cli", "pipeline.engine.execute.batch"],
                                       ["pipeline.engine.plan", "pipeline.engine.store"]]
    assert layer_violations(made_up) == [
        "pipeline.engine.execute.batch -> pipeline.cli (a front end)",
        "pipeline.engine.store -> pipeline.engine.plan (plan is above store)"]


def test_the_launcher_and_the_early_child_import_the_standard_library_only(graph):
    """``polyvec`` forks its keypoints child before its own imports: what it imports until then
    (the launcher, the early child's module and the process settings it reads) is the standard
    library alone, so the fork happens while the process has no threads and the child starts at once."""
    import sys

    for module in ("pipeline.launch", "pipeline.engine.execute.early_child", "pipeline.engine.execute.process"):
        tree = ast.parse(module_files(ROOT, ("pipeline",))[module].read_text())
        top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
        names = [a.name for n in top if isinstance(n, ast.Import) for a in n.names]
        names += [n.module for n in top if isinstance(n, ast.ImportFrom) and n.module]
        outside = [m for m in names if m.split(".")[0] not in sys.stdlib_module_names
                   and m not in ("__future__", "pipeline.engine.execute.process")]
        assert outside == [], module
