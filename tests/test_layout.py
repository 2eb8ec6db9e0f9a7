"""The layout rule (docs/layout.md): no module over 400 lines, no import circle between modules
(counting imports inside functions and those under ``if TYPE_CHECKING:``), imports only downward
through the layers of subpackages, no private name imported from another package, and no module
that is empty or only passes on names imported from elsewhere."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "physmend"
MAX_LINES = 400
# Layers, lowest first: a module may import from its own layer's package and from lower layers.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("exceptions", "redact", "cpus", "prestart"),
    ("config", "config_check", "settings"),
    ("modeling",),
    ("data",),
    ("problem", "simulate", "device"),
    ("explain",),
    ("ude", "diagnosis"),
    ("symbolic", "proposal"),
    ("tracking",),
    ("sweep", "masking"),
    ("stages",),
    ("api",),
    ("errors", "cli", "__init__", "__main__"),
)


def _modules(root: Path = PACKAGE) -> dict[str, Path]:
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imported(
    tree: ast.Module, name: str, is_package: bool, *, type_checking: bool = True
) -> list[tuple[str, str | None, str]]:
    """Every ``physmend`` import of a module, anywhere in it, as (module, imported name or None, local name).

    ``from a.b import c as d`` gives ("a.b", "c", "d"), ``import a.b`` gives ("a.b", None, "a") and
    ``import a.b as m`` ("a.b", None, "m"); relative imports are resolved against the module's
    package. Imports under ``if TYPE_CHECKING:`` count unless ``type_checking`` is false.
    """
    package = name if is_package else name.rpartition(".")[0]
    found: list[tuple[str, str | None, str]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node) and not type_checking:
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.extend(
                (a.name, None, a.asname or a.name.split(".")[0]) for a in node.names if a.name.split(".")[0] == "physmend"
            )
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            if base.split(".")[0] == "physmend":
                found.extend((base, a.name, a.asname or a.name) for a in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _imports(path: Path, name: str, modules: dict[str, Path], *, type_checking: bool = True) -> set[str]:
    """physmend modules that ``path`` imports (anywhere: in functions too, and for type checking unless not asked)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[str] = set()
    for base, alias, _ in _imported(tree, name, path.name == "__init__.py", type_checking=type_checking):
        dotted = f"{base}.{alias}" if alias else base
        while dotted and dotted not in modules:
            dotted = dotted.rpartition(".")[0]
        if dotted and dotted != name:
            found.add(dotted)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(path, name, modules) for name, path in modules.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` as a list of module names, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (found := dfs(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := dfs(node)):
            return found
    return None


def _layer(module: str) -> int:
    top = module.split(".")[1] if "." in module else "__init__"
    for i, names in enumerate(LAYERS):
        if top in names:
            return i
    raise AssertionError(f"subpackage or module {top!r} of {module} is in no layer of tests/test_layout.py")


def _owner(module: str) -> str:
    """The package a module belongs to for privacy: ``physmend.<sub>`` (a top-level module is its own)."""
    return ".".join(module.split(".")[:2])


def _is_private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def _private_imports(name: str, source: str, is_package: bool = False) -> list[str]:
    """The private names (``_x``, or anything inside a ``_module``) that module ``name`` takes from another package.

    Both ``from physmend.a.b import _x`` and ``import physmend.a.b as m; m._x`` count.
    """
    tree = ast.parse(source)
    out = []
    aliases: dict[str, str] = {}  # local name bound to a physmend module (or a name in one) -> its dotted path
    for base, alias, local in _imported(tree, name, is_package):
        dotted = f"{base}.{alias}" if alias else base
        if _owner(dotted) != _owner(name) and any(_is_private(part) for part in dotted.split(".")[1:]):
            out.append(dotted)
        aliases[local] = dotted if alias or local != dotted.split(".")[0] else "physmend"
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _is_private(node.attr):
            chain = [node.attr]
            value = node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in aliases:
                dotted = ".".join([aliases[value.id], *reversed(chain)])
                if _owner(dotted) != _owner(name):
                    out.append(dotted)
    return sorted(set(out))


_PASSIVE = (ast.Import, ast.ImportFrom)


def _does_nothing(source: str) -> bool:
    """True when a module has no code of its own: only a docstring, imports and ``__all__``."""
    for node in ast.parse(source).body:
        if isinstance(node, _PASSIVE):
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            continue
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if all(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                continue
        if isinstance(node, ast.If) and _is_type_checking(node) and all(isinstance(n, _PASSIVE) for n in node.body):
            continue
        return False
    return True


def _unused_imports(source: str) -> list[str]:
    """Names a module imports and never uses: passed on to importers (a re-export), not used here."""
    tree = ast.parse(source)
    bound: dict[str, int] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                bound[a.asname or a.name.split(".")[0]] = node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            for a in node.names:
                if a.name != "*":
                    bound[a.asname or a.name] = node.lineno
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    used |= {n.value.id for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)}
    annotations = [n.annotation for n in ast.walk(tree) if isinstance(n, (ast.arg, ast.AnnAssign)) and n.annotation]
    annotations += [n.returns for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.returns]
    for annotation in annotations:  # a quoted annotation names its types in a string
        for node in ast.walk(annotation):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                try:
                    used |= {n.id for n in ast.walk(ast.parse(node.value, mode="eval")) if isinstance(n, ast.Name)}
                except SyntaxError:
                    pass
    return sorted(name for name in bound if name not in used)


def _long_modules(root: Path = PACKAGE, limit: int = MAX_LINES) -> dict[str, int]:
    """Modules under ``root`` longer than ``limit`` lines: path -> lines."""
    return {str(p.relative_to(root.parent)): n for p in sorted(root.rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > limit}


def test_no_module_is_longer_than_the_limit() -> None:
    long = _long_modules()
    assert not long, f"modules over {MAX_LINES} lines (split them by concern): {long}"


def test_there_is_no_import_circle() -> None:
    circle = _cycle(_graph())
    assert circle is None, "import circle (imports inside functions and for type checking count): " + " -> ".join(
        circle or []
    )


def test_imports_go_only_downward_through_the_layers() -> None:
    upward = sorted(
        f"{a} -> {b}"
        for a, targets in _graph().items()
        for b in targets
        if a != "physmend" and _layer(b) > _layer(a)
    )
    assert not upward, "imports from a higher layer: " + "; ".join(upward)


def test_no_private_name_is_imported_from_another_package() -> None:
    found = {
        name: private
        for name, path in _modules().items()
        if (private := _private_imports(name, path.read_text(), path.name == "__init__.py"))
    }
    assert not found, f"private names used across packages (give them a public name in their package): {found}"


def _idle(modules: dict[str, Path]) -> tuple[list[str], list[str]]:
    """Modules without code of their own (a package's ``__init__`` excepted: it may gather its public
    face), and packages without a module besides their ``__init__`` nor code in it."""
    idle = sorted(
        name for name, path in modules.items() if path.name != "__init__.py" and _does_nothing(path.read_text())
    )
    empty = sorted(
        name for name, path in modules.items()
        if path.name == "__init__.py" and name != "physmend"
        and not any(other.startswith(name + ".") for other in modules) and _does_nothing(path.read_text())
    )
    return idle, empty


def test_no_module_is_empty_or_only_passes_names_on() -> None:
    idle, empty = _idle(_modules())
    assert not idle, f"modules without code of their own: {idle}"
    assert not empty, f"empty packages: {empty}"


def test_no_module_passes_on_names_it_does_not_use() -> None:
    """Outside a package's ``__init__``, every name a module imports is used in it: no re-exports kept
    for old import paths (import from where the name is defined)."""
    passing_on = {
        name: unused for name, path in _modules().items()
        if path.name != "__init__.py" and (unused := _unused_imports(path.read_text()))
    }
    assert not passing_on, f"modules importing names they do not use (re-exports?): {passing_on}"


# The checks themselves, each shown to fail on a small made-up case.


@pytest.mark.parametrize(
    "graph, circle",
    [
        ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c", "a"]),
    ],
)
def test_the_circle_finder_finds_circles(graph: dict[str, set[str]], circle: list[str] | None) -> None:
    assert _cycle(graph) == circle


def test_imports_inside_functions_and_for_type_checking_make_circles(tmp_path: Path) -> None:
    pkg = tmp_path / "physmend"
    (pkg / "m").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "m" / "__init__.py").write_text("")
    (pkg / "m" / "a.py").write_text("from physmend.m.b import B\n")
    (pkg / "m" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from physmend.m.a import A\nB = 1\n"
    )
    (pkg / "m" / "c.py").write_text("from .a import A\n")
    (pkg / "m" / "d.py").write_text("def f():\n    from physmend.m import c\n")
    (pkg / "m" / "e.py").write_text("import physmend.m.d\n")
    modules = _modules(pkg)
    graph = {name: _imports(path, name, modules) for name, path in modules.items()}
    assert _cycle(graph) == ["physmend.m.a", "physmend.m.b", "physmend.m.a"]
    assert graph["physmend.m.c"] == {"physmend.m.a"} and graph["physmend.m.d"] == {"physmend.m.c"}
    assert graph["physmend.m.e"] == {"physmend.m.d"}
    run_time = {name: _imports(path, name, modules, type_checking=False) for name, path in modules.items()}
    assert _cycle(run_time) is None


def test_the_length_check_finds_long_modules(tmp_path: Path) -> None:
    pkg = tmp_path / "physmend"
    (pkg / "m").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "m" / "short.py").write_text("x = 1\n" * 400)
    (pkg / "m" / "long.py").write_text("x = 1\n" * 401)
    assert _long_modules(pkg, 400) == {"physmend/m/long.py": 401}
    assert MAX_LINES == 400 and "no module over 400 lines" in (SRC.parent / "docs" / "layout.md").read_text()


def test_the_idle_check_finds_empty_packages_and_modules(tmp_path: Path) -> None:
    pkg = tmp_path / "physmend"
    for sub in ("empty", "face", "busy"):
        (pkg / sub).mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "empty" / "__init__.py").write_text('"""Nothing yet."""\nfrom __future__ import annotations\n')
    (pkg / "face" / "__init__.py").write_text("from physmend.face.work import f\n__all__ = ['f']\n")
    (pkg / "face" / "work.py").write_text("def f() -> None: ...\n")
    (pkg / "face" / "old_path.py").write_text("from physmend.face.work import f  # noqa: F401\n")
    (pkg / "busy" / "__init__.py").write_text("X = 1\n")
    assert _idle(_modules(pkg)) == (["physmend.face.old_path"], ["physmend.empty"])


@pytest.mark.parametrize(
    "name, source, private",
    [
        ("physmend.stages.s", "from physmend.sweep.run import _drive, drive\n", ["physmend.sweep.run._drive"]),
        ("physmend.stages.s", "from physmend.symbolic._api import fit\n", ["physmend.symbolic._api.fit"]),
        ("physmend.stages.s", "def f():\n    from ..sweep import run as r\n    r._drive()\n", ["physmend.sweep.run._drive"]),
        ("physmend.stages.s", "import physmend.sweep.run as r\nr._drive()\n", ["physmend.sweep.run._drive"]),
        ("physmend.stages.s", "from physmend import sweep\nsweep.run._drive()\n", ["physmend.sweep.run._drive"]),
        ("physmend.sweep.loop", "from physmend.sweep.run import _drive\nfrom ._x import y\n", []),
        ("physmend.stages.s", "from physmend.sweep.run import drive\nx._private\n", []),
        ("physmend.cli", "from physmend.config import _compose\n", ["physmend.config._compose"]),
    ],
)
def test_the_private_import_finder_finds_them(name: str, source: str, private: list[str]) -> None:
    assert _private_imports(name, source) == private


@pytest.mark.parametrize(
    "source, idle, unused",
    [
        ('"""Doc."""\nfrom __future__ import annotations\n', True, []),
        ('"""Doc."""\nfrom a import b, c\n__all__ = ["b", "c"]\n', True, ["b", "c"]),
        ("from a import b  # noqa: F401\nfrom a import c\ndef f() -> c: ...\n", False, ["b"]),
        ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from a import T\nx: 'T | None' = None\n", False, []),
        ("import os.path\nX = os.path.sep\n", False, []),
    ],
)
def test_the_idle_module_finder_finds_them(source: str, idle: bool, unused: list[str]) -> None:
    assert _does_nothing(source) is idle
    assert _unused_imports(source) == unused
