"""The import graph of the three packages: layered and without cycles.

``ttlcore`` is the science library and must be usable without the bus: it imports neither
``streamer`` nor ``stages``; ``streamer`` (the plumbing) does not import ``stages`` (the
programs).  No module imports, directly or through others, a module that imports it back:
every import is followed, at module level and inside functions alike, so a cycle cannot be
hidden by moving an import into a function; only the imports under ``if TYPE_CHECKING:``,
which name types for the type checker and never run, are not part of the graph.  Imports inside functions are allowed only for
optional or heavy outside packages (figures, viewers, outside references).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ttlcore", "streamer", "stages")
#: outside packages that may be imported inside a function (optional, or slow to import)
LAZY_ALLOWED = {
    "matplotlib",
    "rerun",
    "rerun_cli",
    "lisainstrument",
    "lisaorbits",
    "lisagwresponse",
    "healpy",
    "pytdi",
    "dask",
    "distributed",
    "emcee",
    "tqdm",
    "rich",
    "cryptography",
}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__main__":
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_type_checking(node: ast.AST) -> bool:
    """An ``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``) block without ``else``."""
    if not isinstance(node, ast.If) or node.orelse:
        return False
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(modules: dict[str, Path]):
    """(module, imported internal module, line, inside a function) for every import."""
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        is_package = path.name == "__init__.py"
        in_function = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                in_function.update(id(n) for n in ast.walk(fn) if n is not fn)
        # `if TYPE_CHECKING:` imports name types for the type checker and never run
        type_only = {id(n) for block in ast.walk(tree) if _is_type_checking(block) for n in ast.walk(block)}
        for node in ast.walk(tree):
            if id(node) in type_only:
                continue
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(name, is_package, node)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            for target in targets:
                yield name, target, node.lineno, id(node) in in_function


def test_layers():
    modules = _modules()
    wrong = [
        f"{modules[m].relative_to(ROOT)}:{line} imports {t}"
        for m, t, line, _ in _imports(modules)
        if (m.split(".")[0] == "ttlcore" and t.split(".")[0] in ("streamer", "stages"))
        or (m.split(".")[0] == "streamer" and t.split(".")[0] == "stages")
    ]
    assert not wrong, "layering broken:\n" + "\n".join(wrong)


def test_no_cycles():
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for m, t, _, _ in _imports(modules):
        # importing a.b.c runs a/__init__ and a/b/__init__ first: those are edges too
        parts = t.split(".")
        for k in range(1, len(parts) + 1):
            target = ".".join(parts[:k])
            if target in modules and target != m and not m.startswith(target + "."):
                graph[m].add(target)
    # Tarjan's strongly connected components
    index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
                sccs.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not sccs, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in sccs)


def test_imports_at_the_top():
    modules = _modules()
    lazy = []
    for path in modules.values():
        tree = ast.parse(path.read_text(), str(path))
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Import):
                    heads = [a.name.split(".")[0] for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    heads = [(node.module or "").split(".")[0] if node.level == 0 else "(relative)"]
                else:
                    continue
                if any(h not in LAZY_ALLOWED for h in heads):
                    lazy.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not lazy, f"{len(lazy)} imports inside functions (move them to the top):\n" + "\n".join(lazy)


#: the floors of ttlcore, from the bottom (docs/architecture.md): a module may import its
#: own floor and those below, never one above, neither by an import statement nor by name
#: (a string naming a ttlcore module).  io and tdi share a floor (the readers interpolate;
#: TDI data are built from telemetry); the simulator, the effects and the GW sources share
#: one (the effects and sources are injections built on the simulator's parts - orbits,
#: noise streams, the injection protocol - and the simulator rebuilds them from their
#: descriptions); the orchestrators of the commands (app) drive the science and the
#: figures, and the command line (cli) parses the arguments and calls them.
FLOORS = {
    "ttlcore.conventions": 0,
    "ttlcore.errors": 0,
    "ttlcore._version": 0,
    "ttlcore._lazy": 0,
    "ttlcore.io": 1,
    "ttlcore.tdi": 1,
    "ttlcore.sim": 2,
    "ttlcore.effects": 2,
    "ttlcore.gw": 2,
    "ttlcore.estimate": 3,
    "ttlcore.diagnose": 4,
    "ttlcore.plots": 5,
    "ttlcore.app": 6,
    "ttlcore.cli": 7,
    "ttlcore": 7,
}


def _floor(module: str) -> int | None:
    parts = module.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in FLOORS:
            return FLOORS[".".join(parts[:k])]
    return None


def _imports_by_name(modules: dict[str, Path]):
    """(module, ttlcore module) for every string constant naming a ttlcore module: an
    ``importlib.import_module("ttlcore...")`` or a table of module names is an import too."""
    for name, path in modules.items():
        if not name.startswith("ttlcore"):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and node.value in modules
                and node.value.startswith("ttlcore.")
                and node.value != name
            ):
                yield name, node.value, node.lineno


def test_ttlcore_floors():
    modules = _modules()
    edges = [(m, t, line) for m, t, line, _ in _imports(modules)] + list(_imports_by_name(modules))
    upward = {}
    for m, t, line in edges:
        if not (m.startswith("ttlcore") and t.startswith("ttlcore")):
            continue
        fm, ft = _floor(m), _floor(t)
        if fm is not None and ft is not None and ft > fm:
            upward.setdefault((m, t), f"{modules[m].relative_to(ROOT)}:{line} (floor {fm}) imports {t} (floor {ft})")
    assert not upward, "imports up the floors of ttlcore:\n" + "\n".join(upward.values())
