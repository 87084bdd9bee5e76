"""The code's house rules: ruff's checks pass, no function in the package runs over 60 lines nor any module over
600, no code hides in a string, and no module imports itself through others (imports inside functions count)."""
import ast
import graphlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LONGEST = 60
LONGEST_MODULE = 600


def test_ruff_finds_nothing():
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", str(ROOT)], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_no_function_is_longer_than_60_lines():
    long = []
    for path in sorted((ROOT / "ensemble").rglob("*.py")):
        where = str(path.relative_to(ROOT))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > LONGEST:
                    long.append(f"{where}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long


def test_no_module_is_longer_than_600_lines():
    long = [f"{path.relative_to(ROOT)} ({lines} lines)" for path in sorted((ROOT / "ensemble").rglob("*.py"))
            if (lines := len(path.read_text().splitlines())) > LONGEST_MODULE]
    assert not long, long


def test_no_string_literal_holds_a_loop():
    """Kernel code is Python that ruff reads (a kernel's file copies it: ensemble.engine.sources.copied_code), not
    text in a string: no string but a docstring holds a line that opens a for or while loop."""
    loop = re.compile(r"^\s*(for|while)\s.*:\s*(#.*)?$", re.M)
    found = []
    for path in sorted((ROOT / "ensemble").rglob("*.py")):
        tree = ast.parse(path.read_text())
        docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                      if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                      and node.body and isinstance(node.body[0], ast.Expr)
                      and isinstance(node.body[0].value, ast.Constant)}
        found += [f"{path.relative_to(ROOT)}:{node.lineno}" for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings
                  and loop.search(node.value)]
    assert not found, found


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(node, importer: str, is_package: bool, modules: set[str]) -> set[str]:
    """The package's modules an import statement of module `importer` names (`from . import x` names x when x is
    a module, else the package)."""
    if isinstance(node, ast.Import):
        return {alias.name for alias in node.names} & modules
    base = importer if is_package else importer.rpartition(".")[0]
    for _ in range(node.level - 1):
        base = base.rpartition(".")[0]
    base = ".".join(part for part in (base if node.level else "", node.module or "") if part)
    return {f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names} & modules


def package_imports() -> dict[str, set[str]]:
    """Each module of the package and the package's modules it imports, anywhere in its text."""
    paths = {module_name(path): path for path in (ROOT / "ensemble").rglob("*.py")}
    graph = {}
    for name, path in paths.items():
        nodes = [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, (ast.Import, ast.ImportFrom))]
        graph[name] = set().union(*(imported(n, name, path.name == "__init__.py", set(paths)) for n in nodes)) - {name}
    return graph


def test_no_module_imports_itself_through_others():
    """The package's imports form no circle, imports inside functions included: a module can be read (and
    imported) knowing only what it imports."""
    graph = package_imports()
    assert {"ensemble.engine.kernels", "ensemble.engine.blocks"} <= graph["ensemble.engine.launch"]  # imports read
    try:
        graphlib.TopologicalSorter(graph).prepare()
    except graphlib.CycleError as error:
        pytest.fail(f"import circle: {' -> '.join(error.args[1])}")
