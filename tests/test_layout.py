"""The tree's rules, read from the sources with ``ast`` (nothing is imported).

- the import graph between subpackages has no cycle;
- ``common`` imports neither the pipeline nor the tracker; ``pipeline`` never imports ``tracker``;
- ``tracker`` reaches the pipeline only through ``pipeline.prior``, and its study layer (``tracker.study``,
  which joins learning and tracking) also through ``pipeline.learn``;
- nothing outside ``tests/`` imports ``tests``;
- every subpackage (and ``common``) declares ``__all__`` in its ``__init__.py`` and each listed name is
  bound there, or exported lazily from a submodule that defines it.

Imports inside functions count (a lazy import is still a dependency); imports under
``if TYPE_CHECKING:`` do not, since they never run.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "pipeline", "tracker")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST, module: str, is_package: bool) -> set[str]:
    """Absolute names of every module ``tree`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.add(name)
            found.update(f"{name}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _sources() -> dict[str, tuple[Path, ast.AST]]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            out[_module_name(path)] = (path, ast.parse(path.read_text(), str(path)))
    return out


SOURCES = _sources()
MODULES = set(SOURCES)
IMPORTS = {m: _imports(tree, m, path.name == "__init__.py") for m, (path, tree) in SOURCES.items()}


def _project_module(name: str) -> str | None:
    """The longest project module that ``name`` names (``pipeline.prior.TerrainPrior`` → ``pipeline.prior``)."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        candidate = ".".join(parts[:k])
        if candidate in MODULES:
            return candidate
    return None


def _unit(module: str) -> str:
    """The layout unit of a module: its subpackage (``tracker.gating``) or, for a top-level module of a
    package (``tracker.cli``), the module itself."""
    parts = module.split(".")
    if len(parts) >= 2 and f"{parts[0]}.{parts[1]}" in MODULES and (
        ROOT / parts[0] / parts[1] / "__init__.py"
    ).exists():
        return f"{parts[0]}.{parts[1]}"
    return module


def _edges() -> dict[tuple[str, str], list[str]]:
    edges: dict[tuple[str, str], list[str]] = {}
    for m, names in IMPORTS.items():
        for name in names:
            target = _project_module(name)
            if target is None:
                continue
            a, b = _unit(m), _unit(target)
            if a != b and b != m.split(".")[0]:
                edges.setdefault((a, b), []).append(f"{m} imports {name}")
    return edges


def test_no_cycle_between_subpackages():
    edges = _edges()
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := dfs(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := dfs(node)):
            why = [edges[(a, b)][0] for a, b in zip(cycle, cycle[1:], strict=False)]
            pytest.fail("import cycle " + " -> ".join(cycle) + ":\n  " + "\n  ".join(why))


def _offences(prefix: str, allowed) -> list[str]:
    return sorted(
        f"{m} imports {name}"
        for m, names in IMPORTS.items() if m == prefix or m.startswith(prefix + ".")
        for name in names if not allowed(name)
    )


def test_common_imports_neither_pipeline_nor_tracker():
    assert _offences("common", lambda n: n.split(".")[0] not in ("pipeline", "tracker")) == []


def test_pipeline_never_imports_tracker():
    assert _offences("pipeline", lambda n: n.split(".")[0] != "tracker") == []


STUDY = "tracker.study"
"""The one tracker layer that may also import ``pipeline.learn``: it joins learning and tracking (issue 16)."""


def _in_package(name: str, package: str) -> bool:
    """``name`` is ``package`` or one of its modules or names (``from pipeline.prior import TerrainPrior`` records
    pipeline.prior and pipeline.prior.TerrainPrior)."""
    target = _project_module(name)
    return name == package or (name.startswith(package + ".") and target is not None
                               and (target == package or target.startswith(package + ".")))


def _tracker_may_import(module: str, name: str) -> bool:
    """Whether tracker ``module`` may import ``name``: anything outside the pipeline, ``pipeline.prior``, and in
    the study layer also ``pipeline.learn``."""
    if name.split(".")[0] != "pipeline":
        return True
    if _in_package(name, "pipeline.prior") and _project_module(name) == "pipeline.prior":
        return True
    return (module == STUDY or module.startswith(STUDY + ".")) and _in_package(name, "pipeline.learn")


def test_tracker_reaches_the_pipeline_only_through_pipeline_prior():
    """Everything in the tracker but the study layer imports only ``pipeline.prior``; the study layer also
    ``pipeline.learn``, nothing else of the pipeline."""
    bad = sorted(
        f"{m} imports {name}"
        for m, names in IMPORTS.items() if m == "tracker" or m.startswith("tracker.")
        for name in names if not _tracker_may_import(m, name)
    )
    assert bad == []


def test_the_tracker_rule_refuses_in_both_directions():
    """The study layer may import pipeline.learn and the rest of the tracker may not; neither may import other
    pipeline packages or pipeline.prior's submodules."""
    assert _tracker_may_import("tracker.study.heldout", "pipeline.learn")
    assert _tracker_may_import("tracker.study.heldout", "pipeline.learn.PriorEstimator")
    assert _tracker_may_import("tracker.study", "pipeline.learn.run")
    assert _tracker_may_import("tracker.gating.gate", "pipeline.prior.TerrainPrior")
    assert not _tracker_may_import("tracker.association.greedy", "pipeline.learn")
    assert not _tracker_may_import("tracker.cli", "pipeline.learn.PriorEstimator")
    assert not _tracker_may_import("tracker.studyx", "pipeline.learn")
    assert not _tracker_may_import("tracker.study.heldout", "pipeline.gis.targets")
    assert not _tracker_may_import("tracker.study.heldout", "pipeline.build.region")
    assert not _tracker_may_import("tracker.study.heldout", "pipeline.prior.terrain")
    # The permission is used (the rule is not vacuous): the study layer does import pipeline.learn.
    assert any(_in_package(n, "pipeline.learn") for m, names in IMPORTS.items() if m.startswith(STUDY) for n in names)


def _outside_tests_sources():
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in ("tests", ".venv", ".git") or "site-packages" in rel.parts:
            continue
        yield rel, path.read_text()
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        nb = json.loads(path.read_text())
        code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
        # IPython magics are not Python; drop those lines before parsing.
        yield path.relative_to(ROOT), "\n".join(
            line for line in code.splitlines() if not line.lstrip().startswith(("%", "!"))
        )


def test_nothing_outside_tests_imports_tests():
    bad = []
    for rel, text in _outside_tests_sources():
        names = _imports(ast.parse(text, str(rel)), "", False)
        bad += [f"{rel} imports {n}" for n in sorted(names) if n.split(".")[0] == "tests"]
    assert bad == []


def _names(value: ast.expr, literals: dict[str, ast.expr]) -> list[str]:
    """The names an ``__all__`` value lists: a literal, or ``sorted(NAME)`` / ``list(NAME)`` of a module-level
    dict or list literal (a lazy-export table)."""
    if isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id in ("sorted", "list") \
            and len(value.args) == 1 and isinstance(value.args[0], ast.Name):
        value = literals[value.args[0].id]
    found = ast.literal_eval(value)
    return list(found)


def _defines(module: str, name: str) -> bool:
    """Whether the project module's source binds ``name`` at top level (def, class, assignment or import)."""
    tree = SOURCES[module][1]
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)) and node.name == name:
            return True
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                return True
        if isinstance(node, ast.ImportFrom | ast.Import) and any((a.asname or a.name) == name for a in node.names):
            return True
    return False


def _lazily_bound(package: str, name: str, tree: ast.Module, literals: dict[str, ast.expr]) -> bool:
    """A name exported through ``__getattr__`` from a ``{name: submodule}`` table: that submodule defines it."""
    has_getattr = any(
        isinstance(node, ast.Assign) and any(
            getattr(e, "id", None) == "__getattr__" for t in node.targets for e in getattr(t, "elts", [t]))
        for node in tree.body
    ) or any(isinstance(n, ast.FunctionDef) and n.name == "__getattr__" for n in tree.body)
    if not has_getattr:
        return False
    for value in literals.values():
        if isinstance(value, ast.Dict):
            table = ast.literal_eval(value)
            if name in table and f"{package}.{table[name]}" in SOURCES:
                return _defines(f"{package}.{table[name]}", name)
    return False


def test_every_subpackage_exports_its_public_names():
    problems = []
    for m, (path, tree) in SOURCES.items():
        if path.name != "__init__.py" or m in ("pipeline", "tracker"):  # those two hold subpackages only
            continue
        exported = None
        bound: set[str] = set()
        literals = {t.id: node.value for node in tree.body if isinstance(node, ast.Assign)
                    for t in node.targets if isinstance(t, ast.Name)}
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
                exported = _names(node.value, literals)
            elif isinstance(node, ast.ImportFrom):
                bound.update(a.asname or a.name for a in node.names)
            elif isinstance(node, ast.Import):
                bound.update((a.asname or a.name).split(".")[0] for a in node.names)
            elif isinstance(node, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)):
                bound.add(node.name)
            elif isinstance(node, ast.Assign):
                bound.update(t.id for t in node.targets if isinstance(t, ast.Name))
        if exported is None:
            problems.append(f"{path.relative_to(ROOT)}: no __all__")
            continue
        missing = [n for n in exported if n not in bound and not _lazily_bound(m, n, tree, literals)]
        if missing:
            problems.append(f"{path.relative_to(ROOT)}: __all__ names {missing} are not bound")
    assert problems == []


def test_the_rules_see_real_edges():
    """Guard against a checker that passes because it reads nothing: known edges are found."""
    edges = _edges()
    assert ("tracker.association", "tracker.gating") in edges
    assert ("pipeline.build", "pipeline.features") in edges
    assert any(a.startswith("tracker") and b == "pipeline.prior" for a, b in edges)
