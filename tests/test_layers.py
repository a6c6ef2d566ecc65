"""The package's architecture holds: its layers (pyproject.toml [tool.importlinter]: reports >
studies > stages > morph > mpm | render | plasticity > meshes > records > settings > base) are kept, checked by import-linter, and no physmorph module
imports itself around a circle. Both read every import statement, function-local ones included."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parent.parent


def _import_graph() -> grimp.ImportGraph:
    return grimp.build_graph("physmorph", cache_dir=None)


def _circles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The modules that import each other around a circle: each strongly connected component of
    more than one module (Tarjan's algorithm), plus any module that imports itself."""
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(module: str) -> None:
        order[module] = low[module] = len(order)
        stack.append(module)
        on_stack.add(module)
        for imported in graph.find_modules_directly_imported_by(module):
            if imported not in order:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], order[imported])
        if low[module] == order[module]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == module:
                    break
            if len(component) > 1 or module in graph.find_modules_directly_imported_by(module):
                found.append(sorted(component))

    for module in sorted(graph.modules):
        if module not in order:
            visit(module)
    return found


def test_the_layers_contract_is_kept():
    lint = Path(sys.executable).with_name("lint-imports")
    out = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml"), "--no-cache"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    report = out.stdout + out.stderr
    assert out.returncode == 0, report[-4000:]
    assert "Contracts: 1 kept, 0 broken." in report, report[-4000:]


def test_every_package_has_one_layer_and_no_import_is_let_through():
    """The contract names every package and top-level module of physmorph (exhaustive) once, lets
    no import through (no ignore_imports), and the top level holds at most six modules besides its
    packages: the tree shows the layers."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    (contract,) = config["contracts"]
    assert contract["type"] == "layers" and contract["exhaustive"] is True
    named = [m.strip() for layer in contract["layers"] for m in layer.replace("|", ":").split(":")]
    assert len(named) == len(set(named)), "a package is in two layers"
    # no import is let through: the layers hold without exceptions
    assert not contract.get("ignore_imports"), contract.get("ignore_imports")
    top = ROOT / "physmorph"
    packages = sorted(p.name for p in top.iterdir() if (p / "__init__.py").is_file())
    modules = sorted(p.stem for p in top.glob("*.py") if p.name != "__init__.py")
    assert sorted(named) == sorted(packages + modules)
    assert len(modules) <= 6, modules
    for package in packages:  # each says what it holds and what it may import
        doc = ast.get_docstring(ast.parse((top / package / "__init__.py").read_text()))
        assert doc and "import" in doc, f"physmorph/{package}/__init__.py: no docstring saying what it may import"


def test_no_physmorph_module_imports_itself_around_a_circle():
    graph = _import_graph()
    # function-local imports are in the graph (physmorph.stages imports the morph inside morph_stage)
    assert graph.direct_import_exists(importer="physmorph.stages", imported="physmorph.morph.loop")
    circles = _circles(graph)
    assert not circles, "modules importing each other around a circle:\n" + "\n".join(
        " -> ".join(c) for c in circles)


def test_no_module_over_600_lines_and_no_function_over_80():
    """The package's rooms stay a size a reader takes in: no file over 600 lines, no function over
    80 (a def's end_lineno - lineno + 1, nested defs counted in their outer function too)."""
    long_files, long_functions = [], []
    for path in sorted((ROOT / "physmorph").rglob("*.py")):
        text = path.read_text()
        if text.count("\n") > 600:
            long_files.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 80:
                long_functions.append(f"{path.relative_to(ROOT)}: {node.name} {node.end_lineno - node.lineno + 1} lines")
    assert not long_files and not long_functions, "\n".join(long_files + long_functions)


def test_no_class_over_250_lines_in_the_solver_the_morph_and_the_records():
    """The solver, the morph loop and the run files are split into parts a reader takes in: no
    class of physmorph/mpm/, physmorph/morph/ or physmorph/records/ over 250 lines."""
    long_classes = []
    for package in ("mpm", "morph", "records"):
        for path in sorted((ROOT / "physmorph" / package).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 250:
                    long_classes.append(f"{path.relative_to(ROOT)}: {node.name} {node.end_lineno - node.lineno + 1} lines")
    assert not long_classes, "\n".join(long_classes)
