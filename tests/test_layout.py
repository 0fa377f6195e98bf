"""The layout of ``src/miss`` stays findable (README, Layout): rooms by concept, no import
cycle among miss's modules (imports inside functions count; those under ``TYPE_CHECKING``,
never run, do not), no room importing another's private names, few loose modules."""

from __future__ import annotations

import ast
from pathlib import Path

import miss

SRC = Path(miss.__file__).parent
#: Modules beside the packages in ``src/miss`` (``__init__`` and ``__main__`` not counted).
MAX_LOOSE = 12
#: The same in ``src/miss/server`` (24 before the server was grouped into ``core/``,
#: ``volumes/``, ``metrics/``, ``jobs/``, ``rooms/``, ``routes/`` and ``storage/``).
MAX_LOOSE_SERVER = 8


def _name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(p): p for p in SRC.rglob("*.py")}


def _type_checking(node: ast.AST) -> bool:
    test = getattr(node, "test", None)
    return isinstance(node, ast.If) and (
        (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING")
        or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")
    )


def _imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import in ``tree``, at any depth, except those under ``if TYPE_CHECKING``."""
    found, todo = [], [tree]
    while todo:
        node = todo.pop()
        if _type_checking(node):
            todo.extend(getattr(node, "orelse", []))
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        todo.extend(ast.iter_child_nodes(node))
    return found


def _absolute(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    package = module if MODULES[module].name == "__init__.py" else module.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{node.module}" if node.module else package


def _edges(module: str) -> list[tuple[str, str]]:
    """``(module imported, name imported or "")`` for each of ``module``'s imports of miss."""
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    out = []
    for node in _imports(tree):
        if isinstance(node, ast.Import):
            out += [(alias.name, "") for alias in node.names if alias.name in MODULES]
            continue
        source = _absolute(module, node)
        for alias in node.names:
            folder = SRC.parent.joinpath(*source.split("."))
            if list(folder.glob(f"{alias.name}.*.so")):  # a compiled extension, not Python
                continue
            if f"{source}.{alias.name}" in MODULES:  # a submodule
                out.append((f"{source}.{alias.name}", ""))
            elif source in MODULES:
                out.append((source, alias.name))
    return out


def _room(module: str) -> str:
    """``miss.surface`` for ``miss.surface.blocks``; a loose module is a room of its own."""
    return ".".join(module.split(".")[:2])


def _cycle() -> list[str] | None:
    graph = {m: sorted({t for t, _ in _edges(m) if t != m}) for m in MODULES}
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for t in graph[m]:
            if state.get(t) == 1:
                return [*path[path.index(t) :], t]
            if t not in state and (found := visit(t)):
                return found
        state[m] = 2
        path.pop()
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_the_checker_sees_imports_inside_functions() -> None:
    edges = _edges("miss.decimate")
    assert any(t.startswith("miss.measure") for t, _ in edges)


def test_no_import_cycle() -> None:
    assert _cycle() is None, " -> ".join(_cycle() or [])


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_imported_from_another_room() -> None:
    crossing = [
        f"{m} imports {name} from {t}"
        for m in MODULES
        for t, name in _edges(m)
        if _private(name) and _room(t) != _room(m)
    ]
    assert not crossing


def test_no_private_module_of_a_room_imported_from_another_room() -> None:
    # ``miss.measure._jit`` is the measure room's own; another room imports what it offers
    # from ``miss.measure`` (or a public module of it). Loose private modules at the top
    # (``miss._numba``) are the package's, shared by every room.
    crossing = [
        f"{m} imports {t}"
        for m in MODULES
        for t, _ in _edges(m)
        if _room(t) != _room(m) and any(map(_private, t.split(".")[2:]))
    ]
    assert not crossing


def test_few_loose_modules() -> None:
    loose = sorted(p.name for p in SRC.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    assert len(loose) <= MAX_LOOSE, loose


def test_few_loose_modules_in_the_server() -> None:
    server = SRC / "server"
    loose = sorted(p.name for p in server.glob("*.py") if p.name != "__init__.py")
    assert len(loose) <= MAX_LOOSE_SERVER, loose
