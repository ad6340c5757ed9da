"""The import graph of the three packages: layered and without cycles.

``ttlcore`` is the science library and must be usable without the bus: it imports neither
``streamer`` nor ``stages``; ``streamer`` (the plumbing) does not import ``stages`` (the
programs).  No module imports, directly or through others, a module that imports it back:
every import is followed, at module level and inside functions alike, so a cycle cannot be
hidden by moving an import into a function.  Imports inside functions are allowed only for
optional or heavy outside packages (figures, viewers, outside references).

The imports under ``if TYPE_CHECKING:`` never run, but they are imports all the same: they
count for the layers and the floors (a type named from a floor above is a dependency on it),
and a circle they close is reported apart (:data:`KNOWN_TYPE_CYCLES`).  A module is also
imported *by name* (:func:`_imports_by_name`): a string naming a ttlcore module, a
``"ttlcore.pkg.mod:function"`` dispatch string, an f-string whose constant start names a
ttlcore package (``importlib.import_module(f"ttlcore.{kind}.report")``).

Each rule is checked twice: on the tree (``test_layers``, ``test_no_cycles``,
``test_type_checking_cycles``, ``test_ttlcore_floors``, ``test_streamer_wings``: streamer's five wings
are floors too, :data:`WINGS`) and on a small synthetic tree written to
``tmp_path`` in which one module breaks it (``test_checker_sees_*``), so that a rule which sees
nothing cannot pass unnoticed.
"""

from __future__ import annotations

import ast
import re
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


def _modules(root: Path = ROOT) -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (root / pkg).rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
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
    """(module, imported module, line, inside a function, under ``if TYPE_CHECKING:``) for
    every import statement."""
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        is_package = path.name == "__init__.py"
        in_function = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                in_function.update(id(n) for n in ast.walk(fn) if n is not fn)
        type_only = {id(n) for block in ast.walk(tree) if _is_type_checking(block) for n in ast.walk(block)}
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(name, is_package, node)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            for target in targets:
                yield name, target, node.lineno, id(node) in in_function, id(node) in type_only


def _where(modules: dict[str, Path], module: str, line: int) -> str:
    path = modules[module]
    root = path.parents[len(module.split(".")) - (path.name != "__init__.py")]
    return f"{path.relative_to(root)}:{line}"


def _layering_violations(root: Path = ROOT) -> list[str]:
    modules = _modules(root)
    return sorted(
        f"{_where(modules, m, line)} imports {t}" + (" (under TYPE_CHECKING)" if type_only else "")
        for m, t, line, _, type_only in _imports(modules)
        if (m.split(".")[0] == "ttlcore" and t.split(".")[0] in ("streamer", "stages"))
        or (m.split(".")[0] == "streamer" and t.split(".")[0] == "stages")
    )


def test_layers():
    wrong = _layering_violations()
    assert not wrong, "layering broken:\n" + "\n".join(wrong)


def _graph(root: Path, type_checking: bool) -> dict[str, set[str]]:
    """Module -> the modules it imports (of the imports that run, or with ``type_checking``
    of all, those under ``if TYPE_CHECKING:`` included)."""
    modules = _modules(root)
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for m, t, _, _, type_only in _imports(modules):
        if type_only and not type_checking:
            continue
        # importing a.b.c runs a/__init__ and a/b/__init__ first: those are edges too
        parts = t.split(".")
        for k in range(1, len(parts) + 1):
            target = ".".join(parts[:k])
            if target in modules and target != m and not m.startswith(target + "."):
                graph[m].add(target)
    return graph


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    sccs: list[list[str]] = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = [stack.pop()]
            while comp[-1] != v:
                comp.append(stack.pop())
            on.difference_update(comp)
            if len(comp) > 1:
                sccs.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sccs


def _cycles(root: Path = ROOT, type_checking: bool = False) -> list[list[str]]:
    """The import cycles of the modules under ``root``: of the imports that run, or with
    ``type_checking`` of all imports, those under ``if TYPE_CHECKING:`` included."""
    return _strongly_connected(_graph(root, type_checking))


def test_no_cycles():
    sccs = _cycles()
    assert not sccs, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in sccs)


#: the circles closed by an ``if TYPE_CHECKING:`` import, each with the reason it stays: the
#: modules of each circle (as a set) and why.  The list may only shrink: a circle that grows
#: (a module joins it) or a new one fails the test, and so does an entry no longer needed.
#: Fix a circle by naming the type where the lower module can see it (move the shared type
#: down, or a Protocol in the lower module, as ``ttlcore.effects.injection.InjectedEffect`` and
#: ``streamer.runtime.stage_cli.StageProgram`` do), not by a longer list.
KNOWN_TYPE_CYCLES: dict[frozenset[str], str] = {
    frozenset(
        f"ttlcore.diagnose.{m}"
        for m in (
            "evidence",
            "fitting",
            "glitches",
            "model_fit",
            "noise_model",
            "offset_search",
            "search",
            "search_result",
            "step_search",
            "whitened",
        )
    ): (
        # closed by whitened -> noise_model (TYPE_CHECKING): noise_model -> fitting -> glitches -> whitened
        "the diagnosis' data value names the model that fits it: Whitening.parameters (whitened.py) is a "
        "NoiseModel, a value defined in noise_model.py next to its fit, which stands above the data (it "
        "fits on them through fitting); a Protocol will not do, its readers (report.py, fitting.py) pass "
        "it on as a NoiseModel. The fix is a code move in the diagnosis - the NoiseModel value and its "
        "basis (PARAMETERS, NOMINAL, BOUNDS, basis_csds) into a module below whitened.py - left to its "
        "owners (issue 34)"
    ),
}


def _unexplained_type_cycles(sccs: list[list[str]], known: dict[frozenset[str], str]) -> list[str]:
    """The circles of ``sccs`` that are not in ``known`` as they are, and the known ones gone."""
    current = {frozenset(c) for c in sccs}
    wrong = []
    for c in sccs:
        if frozenset(c) in known:
            continue
        if any(frozenset(c) < k for k in known):
            wrong.append("smaller than the known circle (write it so in KNOWN_TYPE_CYCLES): " + " <-> ".join(c))
        elif any(frozenset(c) & k for k in known):
            wrong.append("larger than the known circle (a module joined it): " + " <-> ".join(c))
        else:
            wrong.append(" <-> ".join(c))
    wrong += [
        "no longer a circle (remove it from KNOWN_TYPE_CYCLES): " + " <-> ".join(sorted(k))
        for k in known
        if not any(c & k for c in current)
    ]
    return wrong


def test_type_checking_cycles():
    # the imports that run have no cycle (test_no_cycles); these close through a type-only one
    wrong = _unexplained_type_cycles(_cycles(type_checking=True), KNOWN_TYPE_CYCLES)
    assert not wrong, "import cycles through `if TYPE_CHECKING:` imports:\n" + "\n".join(wrong)


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
#: own floor and those below, never one above, neither by an import statement (under
#: ``if TYPE_CHECKING:`` too) nor by name (a string naming a ttlcore module).  io sits below
#: tdi (TDI data are built from telemetry; the Lagrange taps the readers and TDI share are on
#: floor 0, ``ttlcore._lagrange``); the simulator, the effects and the GW sources share one
#: floor (the effects and sources are injections built on the simulator's parts - orbits,
#: noise streams, the injection protocol - and the simulator rebuilds them from their
#: descriptions); the orchestrators of the commands (app) drive the science and the
#: figures, and the command line (cli) parses the arguments and calls them.
FLOORS = {
    "ttlcore.conventions": 0,
    "ttlcore.errors": 0,
    "ttlcore._version": 0,
    "ttlcore._lazy": 0,
    "ttlcore._lagrange": 0,
    "ttlcore.io": 1,
    "ttlcore.tdi": 2,
    "ttlcore.sim": 3,
    "ttlcore.effects": 3,
    "ttlcore.gw": 3,
    "ttlcore.estimate": 4,
    "ttlcore.diagnose": 5,
    "ttlcore.plots": 6,
    "ttlcore.app": 7,
    "ttlcore.cli": 8,
    "ttlcore": 8,
}


def _floor(module: str, floors: dict[str, int] = FLOORS) -> int | None:
    """The floor of ``module`` in ``floors``: that of its longest prefix listed, or None."""
    parts = module.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in floors:
            return floors[".".join(parts[:k])]
    return None


def _longest_module(name: str, modules: dict[str, Path]) -> str | None:
    """The module a dotted name lies in: itself, or its longest prefix that is a module."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in modules:
            return ".".join(parts[:k])
    return None


#: ``"ttlcore.pkg.mod:function"`` (the form of an entry point or a command's handler; likewise
#: ``"streamer.wing.mod:function"``)
DISPATCH = re.compile(r"((?:ttlcore|streamer)(?:\.\w+)+):\w+(?:\.\w+)*")


def _named_by_fstring(node: ast.JoinedStr, modules: dict[str, Path], package: str = "ttlcore") -> list[str]:
    """The modules of ``package`` an f-string whose constant start is ``<package>.`` could name.

    Its constant parts are taken as they are and each ``{...}`` as any dotted name, up to a
    ``:`` (a dispatch string's function); every module that pattern matches is named, and
    when it matches none, the package its constant start names (``f"ttlcore.diagnose.{x}"``:
    ``ttlcore.diagnose``)."""
    first = node.values[0] if node.values else None
    if not (isinstance(first, ast.Constant) and isinstance(first.value, str) and first.value.startswith(package + ".")):
        return []
    pattern = ""
    for part in node.values:
        if isinstance(part, ast.Constant):
            text = str(part.value)
            if ":" in text:
                pattern += re.escape(text.split(":", 1)[0])
                break
            pattern += re.escape(text)
        else:
            pattern += r"[\w.]+"
    named = sorted(m for m in modules if re.fullmatch(pattern, m))
    if named:
        return named
    package = _longest_module(first.value.split(":", 1)[0].rsplit(".", 1)[0], modules)
    return [package] if package else []


def _imports_by_name(modules: dict[str, Path], package: str = "ttlcore"):
    """(module, module, line) for every string of a module of ``package`` that names a module
    of it: ``importlib.import_module("ttlcore...")`` or a table of module names, a
    ``"ttlcore.pkg.mod:function"`` dispatch string, an f-string (:func:`_named_by_fstring`)."""
    for name, path in modules.items():
        if name.split(".")[0] != package:
            continue
        tree = ast.parse(path.read_text(), str(path))
        in_fstring = {id(n) for f in ast.walk(tree) if isinstance(f, ast.JoinedStr) for n in ast.walk(f)}
        for node in ast.walk(tree):
            named: list[str | None] = []
            if isinstance(node, ast.JoinedStr):
                named = list(_named_by_fstring(node, modules, package))
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in in_fstring:
                if node.value in modules and node.value.startswith(package + "."):
                    named = [node.value]
                elif (match := DISPATCH.fullmatch(node.value)) and match.group(1).startswith(package + "."):
                    named = [_longest_module(match.group(1), modules)]
            for target in named:
                if target is not None and target != name:
                    yield name, target, node.lineno


def _upward(root: Path, package: str, floors: dict[str, int], word: str) -> list[str]:
    """The imports of ``package`` up its ``floors`` (a statement, ``TYPE_CHECKING`` or by name),
    one line per (module, imported module), the floor called ``word``."""
    modules = _modules(root)
    edges = [(m, t, line, " (under TYPE_CHECKING)" if tc else "") for m, t, line, _, tc in _imports(modules)]
    edges += [(m, t, line, " (by name)") for m, t, line in _imports_by_name(modules, package)]
    upward = {}
    for m, t, line, how in edges:
        fm, ft = _floor(m, floors), _floor(t, floors)
        if fm is not None and ft is not None and ft > fm:
            upward.setdefault((m, t), f"{_where(modules, m, line)} ({word} {fm}) imports {t} ({word} {ft}){how}")
    return sorted(upward.values())


def _upward_imports(root: Path = ROOT) -> list[str]:
    return _upward(root, "ttlcore", FLOORS, "floor")


def test_ttlcore_floors():
    upward = _upward_imports()
    assert not upward, "imports up the floors of ttlcore:\n" + "\n".join(upward)


#: the wings of streamer, from the bottom (``streamer/__init__.py``, docs/architecture.md): a
#: module may import its own wing and those below, never one above, neither by an import
#: statement (under ``if TYPE_CHECKING:`` too) nor by name (a ``"streamer.tools.cli:_cmd_run"``
#: dispatch string, a string or f-string naming a streamer module).  The bus carries the
#: messages; the recordings store them; the runtime is one stage process on both; the launcher
#: starts and supervises those processes; the tools (``ttl`` itself, inspect, refit, viewers)
#: stand on all of them.  Every module of streamer lies in a wing (no flat module).
WINGS = {
    "streamer.bus": 0,
    "streamer.recording": 1,
    "streamer.runtime": 2,
    "streamer.launch": 3,
    "streamer.tools": 4,
}


def _wing(module: str) -> int | None:
    return _floor(module, WINGS)


def _wing_violations(root: Path = ROOT) -> list[str]:
    modules = _modules(root)
    unplaced = [
        f"{_where(modules, m, 1)}: {m} is in no wing of streamer ({', '.join(WINGS)})"
        for m in modules
        if m.startswith("streamer.") and _wing(m) is None
    ]
    return sorted(unplaced + _upward(root, "streamer", WINGS, "wing"))


def test_streamer_wings():
    wrong = _wing_violations()
    assert not wrong, "imports up the wings of streamer:\n" + "\n".join(wrong)


# --- the checker on synthetic trees: each rule sees what it is there for -----------------------


def _tree(root: Path, files: dict[str, str]) -> Path:
    """A package tree under ``root``: ``{"ttlcore/io/reader.py": source}``, with an empty
    ``__init__.py`` in every package on the way and an empty ``streamer`` and ``stages``."""
    for rel, text in files.items():
        path = root / rel
        for parent in [*path.relative_to(root).parents][:-1]:
            (root / parent).mkdir(parents=True, exist_ok=True)
            (root / parent / "__init__.py").touch()
        path.write_text(text)
    for pkg in PACKAGES:
        (root / pkg).mkdir(exist_ok=True)
    return root


#: a module high up that the holes below reach: ttlcore.diagnose.report (floor 5)
HIGH = {"ttlcore/diagnose/report.py": "def main():\n    return 0\n"}


def test_checker_sees_fstring_module_names(tmp_path):
    tree = _tree(
        tmp_path,
        HIGH
        | {
            "ttlcore/io/reader.py": (
                "import importlib\n\n\ndef report(kind):\n"
                '    return importlib.import_module(f"ttlcore.{kind}.report")\n'
            ),
            # no module matches: the package its constant start names
            "ttlcore/io/hdf5.py": 'NAME = "x"\nMODULE = f"ttlcore.diagnose.{NAME}_missing"\n',
            # an f-string naming a floor below, and one that is not a module name: fine
            "ttlcore/tdi/data.py": 'K = "reader"\nA = f"ttlcore.io.{K}"\nB = f"ttlcore {K}"\n',
        },
    )
    upward = _upward_imports(tree)
    assert any(u.startswith("ttlcore/io/reader.py:5 (floor 1) imports ttlcore.diagnose.report") for u in upward)
    assert any(u.startswith("ttlcore/io/hdf5.py:2 (floor 1) imports ttlcore.diagnose (floor 5)") for u in upward)
    assert len(upward) == 2, upward


def test_checker_sees_dispatch_strings(tmp_path):
    tree = _tree(
        tmp_path,
        HIGH
        | {
            "ttlcore/io/reader.py": 'HANDLERS = {"report": "ttlcore.diagnose.report:main"}\n',
            # a function path to a module of the floor or below, and prose that mentions one: fine
            "ttlcore/tdi/data.py": 'H = "ttlcore.io.reader:read"\nDOC = "see ttlcore.diagnose.report:main"\n',
        },
    )
    upward = _upward_imports(tree)
    assert upward == ["ttlcore/io/reader.py:1 (floor 1) imports ttlcore.diagnose.report (floor 5) (by name)"]


def test_checker_sees_type_checking_imports(tmp_path):
    source = (
        "from __future__ import annotations\n\nfrom typing import TYPE_CHECKING\n\n"
        "if TYPE_CHECKING:\n    from ..diagnose.report import main\n"
    )
    tree = _tree(tmp_path, HIGH | {"ttlcore/io/reader.py": source, "ttlcore/io/hdf5.py": "import streamer\n"})
    assert _upward_imports(tree) == [
        "ttlcore/io/reader.py:6 (floor 1) imports ttlcore.diagnose.report (floor 5) (under TYPE_CHECKING)"
    ]
    (tree / "ttlcore/io/reader.py").write_text(source.replace("..diagnose.report import main", "streamer import x"))
    assert _layering_violations(tree) == [
        "ttlcore/io/hdf5.py:1 imports streamer",
        "ttlcore/io/reader.py:6 imports streamer (under TYPE_CHECKING)",
    ]


def test_checker_sees_io_importing_tdi(tmp_path):
    # io sits below tdi: the readers do not import TDI (the taps they share are on floor 0)
    tree = _tree(
        tmp_path,
        {
            "ttlcore/io/lisainstrument.py": "from ..tdi.interpolation import apply_taps\n",
            "ttlcore/io/reader.py": "from .._lagrange import apply_taps\n",
            "ttlcore/tdi/data.py": "from ..io.telemetry import Telemetry\n",
            "ttlcore/tdi/interpolation.py": "",
            "ttlcore/io/telemetry.py": "",
            "ttlcore/_lagrange.py": "",
        },
    )
    assert _upward_imports(tree) == [
        "ttlcore/io/lisainstrument.py:1 (floor 1) imports ttlcore.tdi.interpolation (floor 2)"
    ]


def test_checker_sees_cycles_through_type_checking(tmp_path):
    a_imports_b = "from .b import B\n\n\nclass A:\n    pass\n"
    b_names_a = (
        "from __future__ import annotations\n\nfrom typing import TYPE_CHECKING\n\n"
        "if TYPE_CHECKING:\n    from .a import A\n\n\nclass B:\n    a: A\n"
    )
    tree = _tree(
        tmp_path,
        {"ttlcore/sim/a.py": a_imports_b, "ttlcore/sim/b.py": b_names_a, "ttlcore/sim/c.py": "from .a import A\n"},
    )
    assert _cycles(tree) == []  # the imports that run have none
    sccs = _cycles(tree, type_checking=True)
    assert sccs == [["ttlcore.sim.a", "ttlcore.sim.b"]]
    assert _unexplained_type_cycles(sccs, {}) == ["ttlcore.sim.a <-> ttlcore.sim.b"]
    # a known circle may shrink, not grow; a known one that is gone must leave the list
    known = {frozenset({"ttlcore.sim.a", "ttlcore.sim.b"}): "why"}
    known_abc = frozenset({"ttlcore.sim.a", "ttlcore.sim.b", "ttlcore.sim.c"})
    assert _unexplained_type_cycles(sccs, known) == []
    assert _unexplained_type_cycles([["ttlcore.sim.a", "ttlcore.sim.b"]], {known_abc: "why"}) == [
        "smaller than the known circle (write it so in KNOWN_TYPE_CYCLES): ttlcore.sim.a <-> ttlcore.sim.b"
    ]
    (tree / "ttlcore/sim/b.py").write_text(
        b_names_a.replace("from .a import A", "from .a import A\n    from .c import C")
    )
    (tree / "ttlcore/sim/c.py").write_text("from .a import A\n\nC = A\n")
    grown = _cycles(tree, type_checking=True)
    assert _unexplained_type_cycles(grown, known) == [
        "larger than the known circle (a module joined it): ttlcore.sim.a <-> ttlcore.sim.b <-> ttlcore.sim.c"
    ]
    (tree / "ttlcore/sim/b.py").write_text("class B:\n    pass\n")
    assert _unexplained_type_cycles(_cycles(tree, type_checking=True), known) == [
        "no longer a circle (remove it from KNOWN_TYPE_CYCLES): ttlcore.sim.a <-> ttlcore.sim.b"
    ]


def test_checker_sees_streamer_wings(tmp_path):
    tree = _tree(
        tmp_path,
        {
            "streamer/tools/cli.py": "def _cmd_run():\n    return 0\n",
            "streamer/runtime/stage.py": "from ..bus.keys import K\nfrom ..recording.recorder import R\n",
            "streamer/bus/keys.py": "from ..runtime.stage import Stage\n",
            "streamer/bus/codec.py": (
                "from __future__ import annotations\n\nfrom typing import TYPE_CHECKING\n\n"
                "if TYPE_CHECKING:\n    from ..launch.launcher import Launcher\n"
            ),
            "streamer/recording/recorder.py": 'HANDLER = "streamer.tools.cli:_cmd_run"\n',
            "streamer/launch/launcher.py": 'import importlib\n\nM = importlib.import_module(f"streamer.tools.{1}")\n',
            "streamer/flat.py": "",
        },
    )
    assert _wing_violations(tree) == [
        "streamer/bus/codec.py:6 (wing 0) imports streamer.launch.launcher (wing 3) (under TYPE_CHECKING)",
        "streamer/bus/keys.py:1 (wing 0) imports streamer.runtime.stage (wing 2)",
        "streamer/flat.py:1: streamer.flat is in no wing of streamer (streamer.bus, streamer.recording, "
        "streamer.runtime, streamer.launch, streamer.tools)",
        "streamer/launch/launcher.py:3 (wing 3) imports streamer.tools.cli (wing 4) (by name)",
        "streamer/recording/recorder.py:1 (wing 1) imports streamer.tools.cli (wing 4) (by name)",
    ]
