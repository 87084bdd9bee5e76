"""Numba's inliner without its two spare copies of each inlined function's IR.

Every kernel is written as functions inlined into its loops (njit(inline="always")), and Numba compiles each
call site by re-making the callee's IR, then deep-copying it twice in InlineWorker.inline_ir: once to mutate, once
to return an unmutated original that Numba's own callers discard (numba issue #8989, numba-cuda #688 and #689).
Those copies were up to a third of a kernel's compile time. `apply` edits two lines of the installed Numba's
inline_ir (and inline_function, whose IR is made for the one call): the original returned is the callee's IR as
it came, and IR made for the one call is not copied. The compiled code is the same to the byte
(tests/test_trust.py); a Numba whose lines differ, or whose passes keep that original, is left as it is
(`applied` False). Applied by ensemble.engine.kernels.load_source before it makes a kernel's module, unless
ENSEMBLE_NUMBA_INLINER=unedited (read once, before the process's first kernel is made; any other value than it
and 'edited' is an EnsembleError)."""
from __future__ import annotations

import inspect
import os
import re
import textwrap

from numba.core import inline_closurecall, typed_passes, untyped_passes

from .errors import EnsembleError

_WORKER = inline_closurecall.InlineWorker
ORIGINAL = {"inline_ir": _WORKER.inline_ir, "inline_function": _WORKER.inline_function}
_COPY = "    callee_ir = copy_ir(callee_ir)\n"
_SPARE = "    callee_ir_original = copy_ir(callee_ir)\n"
_KEPT = ("    callee_ir_original = callee_ir  # ensemble.inlining: as it came, not a copy\n"
         "    callee_ir = callee_ir if getattr(callee_ir, '_made_for_this_call', False) else copy_ir(callee_ir)\n")
applied = False
decided = False  # apply reads ENSEMBLE_NUMBA_INLINER once


def _edited_inline_ir():
    """Numba's inline_ir with the two edits, or None where its source is not the one they were made for."""
    try:
        source = textwrap.dedent(inspect.getsource(ORIGINAL["inline_ir"]))
    except (OSError, TypeError):
        return None
    if source.count(_COPY) != 1 or source.count(_SPARE) != 1:
        return None
    names = {}
    exec(compile(source.replace(_COPY, _KEPT).replace(_SPARE, ""), inline_closurecall.__file__, "exec"),
         vars(inline_closurecall), names)
    return names["inline_ir"]


def _inline_function(self, caller_ir, block, i, function, arg_typs=None):
    """Numba's InlineWorker.inline_function, its callee's IR marked as made for this one call."""
    callee_ir = self.run_untyped_passes(function)
    callee_ir._made_for_this_call = True
    return self.inline_ir(caller_ir, block, i, callee_ir, function.__code__.co_freevars, arg_typs=arg_typs)


def _statements(function) -> list[str]:
    """A function's source lines after its docstring, stripped, or [] where it has no source."""
    try:
        source = inspect.getsource(function)
    except (OSError, TypeError):
        return []
    return [line.strip() for line in source.split('"""')[-1].splitlines() if line.strip()]


def _inline_function_is_numbas() -> bool:
    """Whether the installed inline_function is the lines _inline_function repeats, and the IR it inlines is made
    anew for each call (run_untyped_passes ends by running the passes and returning their IR, cached nowhere)."""
    made = _statements(_WORKER.run_untyped_passes)
    return (_statements(ORIGINAL["inline_function"]) == [
        "callee_ir = self.run_untyped_passes(function)", "freevars = function.__code__.co_freevars",
        "return self.inline_ir(caller_ir, block, i, callee_ir, freevars,", "arg_typs=arg_typs)"]
        and made[-2:] == ["pm.run(state)", "return state.func_ir"] and not any("cache" in line for line in made))


def discards_the_original(source: str) -> bool:
    """Whether a module's source calls inline_worker.inline_ir or inline_function, each time throwing away the
    original they return first (`_, _, _, new_blocks = ...`)."""
    calls = re.findall(r"([^\n]*\n?[^\n]*)inline_worker\.inline_(?:ir|function)\(", source)
    return bool(calls) and all(re.search(r"_, _, _, new_blocks =\s*\\?\s*$", before) for before in calls)


def _callers_discard_the_original() -> bool:
    """Whether both of Numba's passes that inline (untyped_passes, typed_passes) discard that original."""
    try:
        return all(discards_the_original(inspect.getsource(module)) for module in (untyped_passes, typed_passes))
    except (OSError, TypeError):
        return False


def apply() -> bool:
    """Edit the installed Numba's inliner unless ENSEMBLE_NUMBA_INLINER=unedited, deciding at the first call only;
    whether it is edited."""
    global applied, decided
    if decided:
        return applied
    asked = os.environ.get("ENSEMBLE_NUMBA_INLINER") or "edited"
    if asked not in ("edited", "unedited"):
        raise EnsembleError(f"ENSEMBLE_NUMBA_INLINER={asked!r}: set it to 'unedited' to leave Numba's inliner as "
                            "it is, or to 'edited' (the default)")
    if asked == "edited":
        inline_ir = _edited_inline_ir()
        if inline_ir is not None and _inline_function_is_numbas() and _callers_discard_the_original():
            _WORKER.inline_ir, _WORKER.inline_function = inline_ir, _inline_function
            applied = True
    decided = True
    return applied
