"""The package is a stack: every module of ``dslearn/`` imports only its own layer or the layers below
(lazy imports inside functions count), no two folders or root modules import each other in a loop, no
two files do, and the library below the studies neither imports nor mentions the config machinery.

The import graph is read from the source with :mod:`ast` (nothing is imported): every ``import`` /
``from ... import`` anywhere in a module (module level, functions, ``TYPE_CHECKING`` blocks), relative
imports resolved, and ``importlib.import_module`` / ``__import__`` of a literal ``dslearn.`` name (or of
an f-string whose literal head names a ``dslearn`` package). A unit is a folder directly under
``dslearn/`` or a root module; :data:`LAYERS` places every unit, so a new folder or root module must be
placed before this test passes.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "dslearn"

#: the layers, bottom to top: a unit may import units of its own layer and of the layers below it only.
#: A folder is ``name/``, a root module its name without ``.py`` (``__init__`` = the package's face).
LAYERS: list[tuple[str, ...]] = [
    ("__init__", "errors", "types", "streams", "diagnostics", "linalg", "progress", "io", "conf_paths",
     "episodes", "network", "settings"),
    ("data/",),
    ("fusion/",),
    ("models/",),
    ("sim/",),
    ("association/",),
    ("filters/",),
    ("learning/",),
    ("methods/",),
    ("metrics/", "forecast"),
    ("studies/",),
    ("compose", "search_path"),
    ("schemas/",),
    ("reports/", "callbacks", "reference"),
    ("run", "app/", "report", "api", "bench", "train_lstm", "tools/"),
]

#: modules up to this layer (inclusive) take plain values and built objects: they neither import nor
#: mention the config machinery (the words below, case-insensitive, comments and docstrings included)
CONFIG_FREE_UP_TO = "studies/"
CONFIG_WORDS = re.compile(r"omegaconf|hydra", re.IGNORECASE)
#: units exempt from that rule (none: every study takes plain values and built parts)
CONFIG_WORD_EXCEPTIONS: tuple[str, ...] = ()

#: imports that run up the stack, each file -> file (none left; an entry that no longer exists fails the test)
KNOWN_UPWARD: frozenset[tuple[str, str]] = frozenset()


def _modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file of the package under ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        if path.relative_to(root).parts[0] == "conf":  # the packaged configs (an install's dslearn/conf): data
            continue
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The module that ``name`` (a module, or a name inside one) lives in."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _literal_head(node: ast.expr) -> str | None:
    """The literal text (or the literal head of an f-string) of an import call's argument."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr) and node.values and isinstance(node.values[0], ast.Constant):
        head = str(node.values[0].value)
        return head.rpartition(".")[0] if "." in head else None
    return None


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """``(imported module, line)`` for every import of a ``dslearn`` module in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from pkg import sub`` imports the submodule; ``from mod import name`` the module
            names = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
        elif isinstance(node, ast.Call) and node.args:
            fn = node.func
            called = fn.attr if isinstance(fn, ast.Attribute) else fn.id if isinstance(fn, ast.Name) else ""
            if called in ("import_module", "__import__"):
                head = _literal_head(node.args[0])
                names = [head] if head else []
        for name in names:
            if name == "dslearn" or name.startswith("dslearn."):
                target = _resolve(name, modules)
                if target is not None and target != module:
                    found.append((target, node.lineno))
    return found


def unit_of(module: str, modules: dict[str, Path]) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "__init__"
    if len(parts) == 2 and modules[module].name != "__init__.py":
        return parts[1]
    return parts[1] + "/"


def _rel(path: Path) -> str:
    return path.relative_to(PKG).as_posix()


def _graph():
    modules = _modules(PKG)
    edges = {(m, t): line for m, p in modules.items() for t, line in imports_of(m, p, modules)}
    return modules, edges


def _cycles(nodes, succ) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan), each sorted."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(succ.get(v, ())):
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

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def _layer_of() -> dict[str, int]:
    return {u: i for i, units in enumerate(LAYERS) for u in units}


def _checked_edges(modules, edges):
    """The edges the stack is held to: every import but the known upward ones."""
    return {(m, t): line for (m, t), line in edges.items()
            if (_rel(modules[m]), _rel(modules[t])) not in KNOWN_UPWARD}


def test_every_unit_is_placed_once_and_exists():
    modules = _modules(PKG)
    units = {unit_of(m, modules) for m in modules}
    placed = [u for layer in LAYERS for u in layer]
    assert len(placed) == len(set(placed)), "a unit is placed twice in LAYERS"
    assert not units - set(placed), f"place these in LAYERS (tests/test_layers.py): {sorted(units - set(placed))}"
    assert not set(placed) - units, f"LAYERS names units that do not exist: {sorted(set(placed) - units)}"


def test_every_import_goes_down_the_stack():
    modules, edges = _graph()
    layer = _layer_of()
    up = []
    for (m, t), line in sorted(_checked_edges(modules, edges).items()):
        a, b = unit_of(m, modules), unit_of(t, modules)
        if a != b and a in layer and b in layer and layer[a] < layer[b]:  # an unplaced unit: the test above
            up.append(f"{_rel(modules[m])}:{line} imports {_rel(modules[t])} ({a} is below {b})")
    assert not up, "imports that run up the stack:\n" + "\n".join(up)


def test_known_upward_imports_still_exist():
    """An entry of :data:`KNOWN_UPWARD` that the code no longer has must leave the list."""
    modules, edges = _graph()
    present = {(_rel(modules[m]), _rel(modules[t])) for m, t in edges}
    assert not KNOWN_UPWARD - present, f"no longer imported, drop from KNOWN_UPWARD: {sorted(KNOWN_UPWARD - present)}"


def test_no_cycle_between_units():
    modules, edges = _graph()
    succ = defaultdict(set)
    for m, t in _checked_edges(modules, edges):
        a, b = unit_of(m, modules), unit_of(t, modules)
        if a != b:
            succ[a].add(b)
    units = {unit_of(m, modules) for m in modules}
    assert _cycles(units, succ) == []


def test_no_cycle_between_files():
    modules, edges = _graph()
    succ = defaultdict(set)
    for m, t in _checked_edges(modules, edges):
        succ[m].add(t)
    cycles = [[_rel(modules[m]) for m in c] for c in _cycles(modules, succ)]
    assert cycles == []


def test_the_library_up_to_the_studies_names_no_config_machinery():
    modules = _modules(PKG)
    layer = _layer_of()
    top = layer[CONFIG_FREE_UP_TO]
    bad = []
    for m, path in modules.items():
        u = unit_of(m, modules)
        if layer.get(u, top + 1) > top or u in CONFIG_WORD_EXCEPTIONS:  # an unplaced unit: the placement test
            continue
        for i, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if CONFIG_WORDS.search(text):
                bad.append(f"{_rel(path)}:{i}: {text.strip()}")
    assert not bad, "the config machinery named in the library:\n" + "\n".join(bad)


# ---------------------------------------------------------------------------------------------------
# the reader itself, on a package written here: what it must see, and what it must not invent
def _write(root: Path, files: dict[str, str]) -> dict[str, Path]:
    for rel, text in files.items():
        p = root / "dslearn" / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return _modules(root / "dslearn")


def test_the_reader_sees_lazy_relative_and_dynamic_imports(tmp_path):
    modules = _write(tmp_path, {
        "__init__.py": "",
        "errors.py": "",
        "a/__init__.py": "from dslearn.a.x import f\n",
        "a/x.py": "def f():\n    from ..b import y\n    import dslearn.errors\n",
        "a/z.py": "from dslearn.a import x\nfrom . import x as again\n",
        "b/__init__.py": "",
        "b/y.py": "import importlib\nimportlib.import_module('dslearn.a.z')\nimportlib.import_module(f'dslearn.c.{1}')\n",
        "c/__init__.py": "from dslearn.b.y import Something\nfrom dslearn import errors\n",
    })
    seen = {m: sorted({t for t, _ in imports_of(m, p, modules)}) for m, p in modules.items()}
    assert seen == {
        "dslearn": [],
        "dslearn.errors": [],
        "dslearn.a": ["dslearn.a.x"],
        "dslearn.a.x": ["dslearn.b.y", "dslearn.errors"],
        "dslearn.a.z": ["dslearn.a.x"],
        "dslearn.b": [],
        "dslearn.b.y": ["dslearn.a.z", "dslearn.c"],
        "dslearn.c": ["dslearn.b.y", "dslearn.errors"],
    }
    assert [unit_of(m, modules) for m in ("dslearn", "dslearn.errors", "dslearn.a", "dslearn.a.x")] == \
        ["__init__", "errors", "a/", "a/"]


@pytest.mark.parametrize("succ, expected", [
    ({"a": {"b"}, "b": {"c"}}, []),
    ({"a": {"b"}, "b": {"a"}}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "b", "c"]]),
    ({"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"c"}}, [["a", "b"], ["c", "d"]]),
])
def test_the_cycle_finder(succ, expected):
    nodes = set(succ) | {v for vs in succ.values() for v in vs}
    assert sorted(_cycles(nodes, succ)) == expected
