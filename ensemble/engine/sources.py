"""The engine's files whose code the CPU kernels compile in, relative to this folder: every kernel's file holds a
hash of them (blocks.HELPERS), and so does this machine's tuning (tuning.engine_hash); and the code a kernel's file
copies from a module of the engine (`copied_code`). No Numba here, so that reading a tuning imports none."""
import ast
from functools import cache
from pathlib import Path

ENGINE_SOURCES = ("blocks.py", "tuples.py", "frames.py", "runge_kutta.py", "adaptive.py", "control.py",
                  "splitting.py", "events.py", "../results.py")
CODE_LINE = "# ---------------------------------------------------------------- CODE"


@cache
def copied_code(name: str) -> tuple[str, str]:
    """(imports, code) of the engine's file `name` (ensemble.engine.sites_kernels, say) for a kernel's file: its
    import statements, and its text from its CODE_LINE on, both unchanged."""
    text = (Path(__file__).parent / name).read_text()
    imports = [ast.get_source_segment(text, node) for node in ast.parse(text).body
               if isinstance(node, (ast.Import, ast.ImportFrom))]
    return "\n".join(imports), text[text.index(CODE_LINE):]
