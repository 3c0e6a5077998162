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
BORROWED = {("sim", "services.control.core.scenario"), ("sim", "services.control.core.dynamics"),
            ("sim", "services.control.core.regions"), ("sim", "services.control.core.planning")}
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


def _imports(name: str, path: Path, *, typing: bool = False, outside: bool = False
             ) -> set[str]:
    """Every project module ``name`` imports, at the top or inside a function; what is
    imported only for type checking counts only with ``typing``. ``outside``: the top-level
    names of what it imports from outside the project instead (``httpx``, ``zenoh``)."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    skipped = set() if typing else {id(n) for node in ast.walk(tree)
                                    if _type_checking_only(node) for n in ast.walk(node)}
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
        if outside:
            found |= {t.split(".")[0] for t in targets if t and not node_is_relative(node)
                      and t.split(".")[0] not in PACKAGES}
            continue
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def node_is_relative(node: ast.AST) -> bool:
    return isinstance(node, ast.ImportFrom) and node.level > 0


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


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    # packages import their own modules through __init__ re-exports; a module's edge to
    # the package that holds it is not a circle of design
    def edges(module: str) -> set[str]:
        return {t for t in graph.get(module, set()) if not module.startswith(t + ".")}

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

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    return circles


def test_the_import_graph_has_no_circle() -> None:
    assert _circles(GRAPH) == []


EMBEDDING = "services.embedding"
# The detector service's floors (docs/architecture.md, section 2): each folder imports only
# from itself and the floors named here; the service's shell (api, routes, service, worker
# and their helpers, directly in services/embedding) may import any of them, none of them
# the shell.
FLOORS = {"models": ("models",), "detector": ("detector", "models.base"),
          "storage": ("storage", "detector"), "fleet": ("fleet", "storage", "detector")}
# what a pure core never imports: the network, the bus, a database, a web framework, an
# event loop (files are allowed: an index's own files, a JSONL of labelled scenes)
IO = {"httpx", "zenoh", "fastapi", "starlette", "uvicorn", "psycopg", "psycopg_pool",
      "sqlite3", "socket", "requests", "asyncio", "subprocess", "threading"}
CORES = (f"{EMBEDDING}.detector", "services.control.core")


def _folder(module: str) -> str | None:
    rest = module.removeprefix(EMBEDDING + ".").split(".")
    return rest[0] if module.startswith(EMBEDDING + ".") and rest[0] in FLOORS else None


def test_the_detectors_folders_import_only_their_own_floor_and_those_below() -> None:
    bad = []
    for module in sorted(m for m in MODULES if m.startswith(EMBEDDING + ".")):
        folder = _folder(module)
        if folder is None:
            continue
        allowed = tuple(f"{EMBEDDING}.{floor}" for floor in FLOORS[folder])
        for target in _imports(module, MODULES[module], typing=True):
            inside = target.startswith(EMBEDDING + ".") or target == EMBEDDING
            if inside and not any(target == a or target.startswith(a + ".") for a in allowed):
                bad.append((module, target))
    assert bad == []


def test_controls_core_imports_nothing_of_the_loop_around_it() -> None:
    bad = sorted((m, t) for m, p in MODULES.items() if m.startswith("services.control.core")
                 for t in _imports(m, p, typing=True)
                 if t.startswith("services.control") and not t.startswith("services.control.core"))
    assert bad == []


def test_the_detectors_imports_have_no_circle_even_for_type_checking() -> None:
    graph = {m: _imports(m, p, typing=True) for m, p in MODULES.items()
             if m.startswith(EMBEDDING)}
    assert _circles(graph) == []


def test_a_pure_core_imports_no_network_bus_database_or_event_loop() -> None:
    bad = sorted((m, lib) for m, p in MODULES.items() if m.startswith(CORES)
                 for lib in _imports(m, p, typing=True, outside=True) & IO)
    assert bad == []


# What a tool may read of a service that has a pure core: the core, and the service's front:
# its client, route models and settings, its app (what ``aesop serve`` runs) and its
# in-process service (what a bench measures); of control also its runtime (the loop a bench
# ticks, no I/O) and its vehicle contract (what a simulated vehicle flies through). The rest
# of the shell (embedding's entries, worker, scorer, batching, review, routes ...) is its own.
FRONT = {EMBEDDING: ("client", "schemas", "settings", "api", "service",
                     "detector", "models", "storage", "fleet"),
         "services.control": ("client", "schemas", "settings", "api", "service", "loop",
                              "contract", "core")}


def _behind_the_front(target: str) -> bool:
    for service, front in FRONT.items():
        if target.startswith(service + "."):
            return target.removeprefix(service + ".").split(".")[0] not in front
    return False


def test_tools_use_a_services_front_or_its_core_never_its_shell() -> None:
    bad = sorted((m, t) for m, p in MODULES.items() if m.startswith("tools")
                 for t in _imports(m, p, typing=True) if _behind_the_front(t))
    assert bad == []


def test_controls_controller_holds_little() -> None:
    """Algorithm 1's ``Controller`` stays well under the class limit because the anomaly's
    life, the kept plan and the deadlines are values of their own (issue 45: <= 300)."""
    tree = ast.parse(MODULES["services.control.core.aesop"].read_text())
    node = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Controller")
    assert (node.end_lineno or 0) - node.lineno + 1 <= 300


def test_the_layout_rules_can_fail() -> None:
    """The rules above catch what they are for (a check that cannot fail is a defect): the
    shell's own imports would break each of them."""
    assert _circles({"a": {"b"}, "b": {"a"}}) == [["a", "b", "a"]]
    assert (_folder(f"{EMBEDDING}.detector.cache"), _folder(f"{EMBEDDING}.service")) == \
        ("detector", None)
    shell = f"{EMBEDDING}.service"
    assert {"asyncio"} <= _imports(shell, MODULES[shell], outside=True) & IO
    assert f"{EMBEDDING}.storage.store" in _imports(shell, MODULES[shell])
    assert _behind_the_front(f"{EMBEDDING}.worker") and _behind_the_front(f"{EMBEDDING}.entries")
    assert not _behind_the_front(f"{EMBEDDING}.detector.cache")
    assert not _behind_the_front("services.control.core.aesop")
    assert _behind_the_front("services.control.routes")
    assert not _behind_the_front("services.reasoner.worker")  # no core yet: not ruled
    review = f"{EMBEDDING}.review"  # its type-only imports count where typing=True
    assert _imports(review, MODULES[review], typing=True) >= _imports(review, MODULES[review])


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


@pytest.mark.parametrize("module", ["services.embedding.models.embedders",
                                    "services.embedding.models.onnx_backend"])
def test_the_embedders_do_not_import_each_others_chooser(module: str) -> None:
    assert "services.embedding.models.loading" not in GRAPH[module]


def test_the_readme_is_a_front_door_of_at_most_250_lines() -> None:
    """The README says what the stack is, the two commands and one paragraph per part with
    links into docs/ (the developers' guide caps it at about 250 lines)."""
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= 250, f"README.md has {lines} lines: move detail into docs/"
