"""The code's house rules: ruff's checks pass, and no function in the package runs over 60 lines but the kernels."""
import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LONGEST = 60
# Kernel factories whose compiled body is one loop nest: split into functions, its stages would no longer be
# unrolled and fused by LLVM in one place (see engine/blocks.py).
KERNEL_BODIES = {
    "ensemble/scenes/chain/kernels.py": {"_fixed_kernel", "_adaptive_kernel", "kernel"},
}


def test_ruff_finds_nothing():
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", str(ROOT)], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_no_function_is_longer_than_60_lines_but_the_kernels():
    long = []
    for path in sorted((ROOT / "ensemble").rglob("*.py")):
        where = str(path.relative_to(ROOT))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > LONGEST and node.name not in KERNEL_BODIES.get(where, ()):
                    long.append(f"{where}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long
