"""The house rules, read from the source (docs/architecture.md, section 2).

Floors with no back arrows: ``shared`` imports no service or tool; a service never imports
another service (the simulated vehicle reads control's scene and truth model, nothing of
its loop); the import graph, lazy imports included, has no circle; and no function runs
over 100 lines nor any class over 400.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("shared", "services", "tools")
SERVICES = ("embedding", "reasoner", "control", "dashboard", "sim")
# what one service may read of another: the scene and the truth it flies
BORROWED = {("sim", "services.control.scenario"), ("sim", "services.control.dynamics"),
            ("sim", "services.control.regions"), ("sim", "services.control.planning")}
MAX_FUNCTION_LINES = 100
MAX_CLASS_LINES = 400


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


MODULES = _modules()


def _type_checking_only(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _imports(name: str, path: Path) -> set[str]:
    """Every project module ``name`` imports, at the top or inside a function; what is
    imported only for type checking does not count."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    skipped = {id(n) for node in ast.walk(tree) if _type_checking_only(node)
               for n in ast.walk(node)}
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _service(module: str) -> str | None:
    parts = module.split(".")
    if len(parts) >= 2 and parts[0] == "services" and parts[1] in SERVICES:
        return parts[1]
    return None


def test_shared_imports_no_service_and_no_tool() -> None:
    bad = sorted((m, t) for m, targets in GRAPH.items() if m.startswith("shared")
                 for t in targets if not t.startswith("shared"))
    assert bad == []


def test_a_service_never_imports_another_service() -> None:
    bad = []
    for module, targets in GRAPH.items():
        own = _service(module)
        if own is None:
            continue
        for target in targets:
            other = _service(target)
            if other is not None and other != own and (own, target) not in BORROWED:
                bad.append((module, target))
        bad += [(module, t) for t in targets if t.startswith("tools")]
    assert sorted(bad) == []


def test_the_import_graph_has_no_circle() -> None:
    # packages import their own modules through __init__ re-exports; a module's edge to
    # the package that holds it is not a circle of design
    def edges(module: str) -> set[str]:
        return {t for t in GRAPH[module] if not module.startswith(t + ".")}

    state: dict[str, int] = {}
    circles: list[list[str]] = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for target in sorted(edges(module)):
            if state.get(target) == 1:
                circles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[module] = 2

    for module in sorted(GRAPH):
        if module not in state:
            visit(module, [module])
    assert circles == []


def _too_long() -> list[str]:
    found = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            lines = (node.end_lineno or node.lineno) - node.lineno + 1 \
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef) \
                else 0
            limit = MAX_CLASS_LINES if isinstance(node, ast.ClassDef) else MAX_FUNCTION_LINES
            if lines > limit:
                found.append(f"{name}.{node.name}: {lines} lines")  # type: ignore[attr-defined]
    return found


def test_no_function_over_100_lines_and_no_class_over_400() -> None:
    assert _too_long() == []


@pytest.mark.parametrize("module", ["services.embedding.embedders",
                                    "services.embedding.onnx_backend"])
def test_the_embedders_do_not_import_each_others_chooser(module: str) -> None:
    assert "services.embedding.loading" not in GRAPH[module]
