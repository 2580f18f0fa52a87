"""The layout's rules, read from the source: imports point down the layers, and only the H-cell's
builder knows the H-cell.

Layers, lowest first: ``warp_hcell.core`` <- ``warp_hcell.mesostructures`` <- ``warp_hcell.dem``
<- ``warp_hcell.database`` (the entry points ``warp_hcell.generate``/``clean`` above them) <-
``training`` <- ``homogenization``. A module may import its own layer and the layers below;
every import counts, function-local ones included (docs/architecture.md).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("warp_hcell.core", "warp_hcell.mesostructures", "warp_hcell.dem", "warp_hcell.database", "warp_hcell",
          "training", "homogenization")
"""Lowest first; ``warp_hcell`` alone is its entry points (generate, clean)."""
HCELL_MODULE = "warp_hcell/mesostructures/hcell.py"
HCELL_TOKENS = ("is_h_cell", "h_reference_pairs", "pair_type", "H_TYPE1_PAIRS", "H_TYPE2_PAIRS", "TYPE1_PAIRS",
                "TYPE2_PAIRS", "H_GRAINS", "h_cell_alpha0", "plain_h_cell_alpha0", "hcell_observables",
                "HCELL_OBSERVABLES", "h_cell_reference", "h_cell_skeleton", "h_cell_starts", "type1", "type2")
"""Names of the H-cell's labels and geometry: identifiers and string constants outside its builder."""
FORMAT_KEYS = {("warp_hcell/mesostructures/mesostructure.py", "pair_type")}
"""(module, token) where a token is a file-format name, not code that knows the cell."""
MODULES = sorted(p for package in ("warp_hcell", "training", "homogenization") for p in (ROOT / package).rglob("*.py"))


def _name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> int:
    for rank in range(len(LAYERS) - 1, -1, -1):
        layer = LAYERS[rank]
        if module == layer or module.startswith(layer + "."):
            if layer == "warp_hcell" and module.split(".")[1:2] and f"warp_hcell.{module.split('.')[1]}" in LAYERS:
                continue
            return rank
    raise AssertionError(f"{module} is in no layer")


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            assert not node.level, f"{path}: relative import (the package imports by absolute names)"
            base = node.module or ""
            found += [(node.lineno, base)] + [(node.lineno, f"{base}.{a.name}") for a in node.names]
    return [(line, name) for line, name in found if name.split(".")[0] in ("warp_hcell", "training", "homogenization")]


def _is_module(name: str) -> bool:
    path = ROOT / Path(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_go_down_the_layers(path):
    mine = _layer(_name(path))
    upward = [f"line {line}: {name}" for line, name in _imports(path) if _is_module(name) and _layer(name) > mine]
    assert not upward, f"{_name(path)} ({LAYERS[mine]}) imports a higher layer: {upward}"


def test_the_core_imports_nothing_else_of_the_package():
    for path in (ROOT / "warp_hcell" / "core").rglob("*.py"):
        other = [name for _, name in _imports(path) if _is_module(name) and not name.startswith("warp_hcell.core")]
        assert not other, f"{path.name} imports {other}"



def _graph(paths) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (every import, function-local ones included)."""
    names = {_name(path) for path in paths}
    return {_name(path): {name for _, name in _imports(path) if name in names and name != _name(path)} for path in paths}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module of ``graph`` (iterative Tarjan): its import circles."""
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []
    for root in sorted(graph):
        if root in order:
            continue
        work = [(root, iter(sorted(graph[root])))]
        order[root] = low[root] = len(order)
        stack.append(root)
        while work:
            node, targets = work[-1]
            target = next(targets, None)
            if target is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == order[node]:
                    component = stack[stack.index(node):]
                    del stack[stack.index(node):]
                    if len(component) > 1:
                        found.append(sorted(component))
            elif target not in order:
                order[target] = low[target] = len(order)
                stack.append(target)
                work.append((target, iter(sorted(graph[target]))))
            elif target in stack:
                low[node] = min(low[node], order[target])
    return found


def test_no_import_circle_among_the_package_modules():
    circles = _cycles(_graph(MODULES))
    assert not circles, f"import circles (each a set of modules that import one another): {circles}"


def test_no_import_circle_among_the_folders_of_homogenization():
    """Each folder of ``homogenization`` (and each module at its top) as one node: no arrow back up between them."""
    folders: dict[str, set[str]] = {}
    for module, targets in _graph([p for p in MODULES if _name(p).startswith("homogenization.")]).items():
        part = module.split(".")[1]
        folders.setdefault(part, set()).update(t.split(".")[1] for t in targets if t.split(".")[1] != part)
    circles = _cycles({part: folders.get(part, set()) for part in set(folders).union(*folders.values())})
    assert not circles, f"import circles between the folders of homogenization: {circles}"


def test_the_circle_check_finds_a_circle_through_a_local_import(tmp_path):
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []
    source = tmp_path / "probe.py"
    source.write_text("def f():\n    from homogenization.learning.active import learn\n")
    assert (2, "homogenization.learning.active") in _imports(source)


def _defines_something(path: Path) -> bool:
    return any(isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) for node in ast.walk(ast.parse(path.read_text())))


@pytest.mark.parametrize("path", [p for p in MODULES if _name(p).startswith("homogenization.")
                                  and not _name(p).startswith("homogenization.cli")],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_only_the_python_m_entries_import_the_command_layer(path):
    """A module of ``homogenization`` outside ``cli/`` that imports ``homogenization.cli`` is a
    ``python -m`` entry: it defines no function or class, it only starts a command."""
    commands = sorted({name for _, name in _imports(path) if name.startswith("homogenization.cli")})
    assert not commands or not _defines_something(path), (
        f"{_name(path)} is a library module and imports the command layer {commands}")



def _library_at_top(folder: Path) -> list[str]:
    """Modules directly in ``folder`` (its ``__init__`` aside) that are not ``python -m`` entries:
    each defines something or imports no command (``homogenization.cli``)."""
    return sorted(path.name for path in folder.glob("*.py") if path.name != "__init__.py"
                  and (_defines_something(path)
                       or not any(name.startswith("homogenization.cli") for _, name in _imports(path))))


def test_the_top_of_homogenization_holds_only_the_python_m_entries():
    """The library sits in the folders of its parts (docs/architecture.md); the top level keeps the
    ``python -m homogenization.COMMAND`` names users type, each only starting its command."""
    library = _library_at_top(ROOT / "homogenization")
    assert not library, f"library modules at the top of homogenization/: {library}; move them into their part's folder"


def test_the_layout_check_sees_a_library_module_at_the_top(tmp_path):
    (tmp_path / "entry.py").write_text("from homogenization.cli.sweep import main\n")
    assert _library_at_top(tmp_path) == []
    (tmp_path / "helper.py").write_text("from homogenization.cli.sweep import main\ndef f():\n    return main\n")
    (tmp_path / "plain.py").write_text("from homogenization.element_test import driver\n")
    assert _library_at_top(tmp_path) == ["helper.py", "plain.py"]

def _tokens(path: Path) -> set[tuple[int, str]]:
    """Identifiers and non-docstring string constants of a module, with their line."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    out = set()
    for node in ast.walk(tree):
        words: list[str] = []
        if isinstance(node, ast.Name):
            words = [node.id]
        elif isinstance(node, ast.Attribute):
            words = [node.attr]
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)):
            words = [node.name]
        elif isinstance(node, ast.arg):
            words = [node.arg]
        elif isinstance(node, ast.keyword) and node.arg:
            words = [node.arg]
        elif isinstance(node, ast.alias):
            words = [node.name.split(".")[-1], node.asname or ""]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            words = re.findall(r"\w+", node.value)
        out.update((getattr(node, "lineno", 0), w) for w in words if w)
    return out


@pytest.mark.parametrize("path", [p for p in MODULES if p.relative_to(ROOT).as_posix() != HCELL_MODULE],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_only_the_h_cell_builder_knows_the_h_cell(path):
    relative = path.relative_to(ROOT).as_posix()
    found = sorted((line, token) for line, token in _tokens(path) if token in HCELL_TOKENS
                   and (relative, token) not in FORMAT_KEYS)
    assert not found, f"{relative} names the H-cell's labels or geometry: {found}"


def test_the_token_check_sees_what_it_looks_for(tmp_path):
    source = tmp_path / "probe.py"
    source.write_text('"""is_h_cell in a docstring is prose."""\nx = meso.is_h_cell\ny = {"type1": 1}\n')
    tokens = {token for _, token in _tokens(source)}
    assert {"is_h_cell", "type1"} <= tokens
    source.write_text('"""is_h_cell in a docstring is prose."""\n')
    assert "is_h_cell" not in {token for _, token in _tokens(source)}


def test_the_import_walk_sees_local_imports_and_ranks_the_layers(tmp_path):
    probe = ROOT / "warp_hcell" / "dem" / "cell.py"
    assert any(name.startswith("warp_hcell.core") for _, name in _imports(probe))
    source = tmp_path / "probe.py"
    source.write_text("def f():\n    from homogenization.element_test.driver import run\n")
    assert (2, "homogenization.element_test.driver") in _imports(source)
    order = [_layer(m) for m in ("warp_hcell.core.cli", "warp_hcell.mesostructures.hcell", "warp_hcell.dem.cell",
                                 "warp_hcell.database.format", "warp_hcell.generate", "training.train",
                                 "homogenization.element_test.driver")]
    assert order == sorted(order) and len(set(order)) == len(order)


MAX_FUNCTION_LINES = 120
"""Longest function of the package, its docstring and nested definitions included [lines]."""


def _long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``name (lines)`` of every function or method of ``path`` longer than ``limit`` lines."""
    return [f"{node.name} at line {node.lineno} ({node.end_lineno - node.lineno + 1} lines)"
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > limit]


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_function_is_longer_than_the_limit(path):
    long = _long_functions(path)
    assert not long, f"{path.relative_to(ROOT)}: split {long} into functions with one job each"


def test_the_length_check_counts_nested_definitions_and_methods(tmp_path):
    source = tmp_path / "probe.py"
    source.write_text("class A:\n    def f(self):\n        def g():\n" + "            x = 1\n" * 4 + "        return g\n")
    assert _long_functions(source, limit=6) == ["f at line 2 (7 lines)"]
    assert _long_functions(source, limit=4) == ["f at line 2 (7 lines)", "g at line 3 (5 lines)"]


COMMAND_MODULES = ("warp_hcell.generate", "warp_hcell.clean")
"""The command modules of ``warp_hcell`` (``python -m``): the only ones that import the command
helpers ``warp_hcell.core.cli`` (argparse, progress bars, status lines); library code raises
``warp_hcell.core.errors.UserError`` and takes a progress callback."""


def _imports_the_command_helpers(path: Path) -> bool:
    return any(name == "warp_hcell.core.cli" or name.startswith("warp_hcell.core.cli.") for _, name in _imports(path))


@pytest.mark.parametrize("path", [p for p in MODULES if _name(p).startswith("warp_hcell.")
                                  and _name(p) not in (*COMMAND_MODULES, "warp_hcell.core.cli")],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_library_modules_of_warp_hcell_do_not_import_the_command_helpers(path):
    assert not _imports_the_command_helpers(path), f"{_name(path)} is a library module and imports warp_hcell.core.cli"


LIBRARY_WITH_COMMAND_HELPERS = {"homogenization.calibration.report": "reads the calibrate command's argparse "
                                                                      "options and silences Warp itself"}
"""Library modules of ``homogenization`` that still import ``warp_hcell.core.cli``, with why; to be emptied."""


def _homogenization_library() -> list[Path]:
    """Modules of ``homogenization``'s part folders (not ``cli/``, not the ``python -m`` entries at its top)."""
    return [p for p in MODULES if _name(p).count(".") >= 2 and _name(p).startswith("homogenization.")
            and not _name(p).startswith("homogenization.cli.")]


@pytest.mark.parametrize("path", [p for p in _homogenization_library() if _name(p) not in LIBRARY_WITH_COMMAND_HELPERS],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_library_modules_of_homogenization_do_not_import_the_command_helpers(path):
    """The element test, the backends and every other part take progress callbacks and raise ``UserError``;
    progress bars, argparse and status lines are drawn by ``homogenization.cli``."""
    assert not _imports_the_command_helpers(path), f"{_name(path)} is a library module and imports warp_hcell.core.cli"


def test_the_library_list_holds_the_element_test_and_the_backends():
    names = {_name(p) for p in _homogenization_library()}
    assert {"homogenization.element_test.driver", "homogenization.element_test.stages",
            "homogenization.backends.analytical"} <= names and not any(n.startswith("homogenization.cli") for n in names)


def test_the_command_modules_of_warp_hcell_are_the_python_m_entries():
    for module in COMMAND_MODULES:
        path = ROOT / Path(*module.split(".")).with_suffix(".py")
        assert _imports_the_command_helpers(path) and "__main__" in path.read_text(), module


DIMENSION_BRANCH = re.compile(r"n?dim == [23]")
"""The layout's count of branches on the dimension: ``dim == 2``/``3`` (or ``ndim``) written in the source."""
DIMENSION_BRANCHES_MAX = 15
"""At most this many, each in a module whose job is the dimension (docs/architecture.md)."""


def _dimension_branches(paths) -> list[str]:
    """Each line of ``paths`` that branches on the dimension, as 'path:line'."""
    return [f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}:{number}" for path in paths
            for number, line in enumerate(path.read_text().splitlines(), 1) if DIMENSION_BRANCH.search(line)]


def test_the_dimension_is_data_not_branches():
    branches = _dimension_branches(MODULES)
    assert len(branches) <= DIMENSION_BRANCHES_MAX, "\n".join(branches)


def test_the_branch_count_sees_a_branch(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f(dim):\n    return 1 if dim == 3 else 2\nx = a.ndim == 2\ny = dim >= 2\n")
    assert len(_dimension_branches([module])) == 2
