"""Lorenz-96 over n sites, x_i' = (x_{i+1} - x_{i-2}) x_{i-1} - x_i + F (indices around the ring), as a scene of
your own: one state variable per site, so a scene of many values is generated rather than typed.

    python examples/lorenz96.py 40 > lorenz96.py    # then scene = "lorenz96.py" in a run file

The state variables are x0_ .. x{n-1}_ (each starts at its parameter x{i}_0, default 0) and the forcing F is a
parameter. See docs/scenes.md ("A large state").
"""
from __future__ import annotations

import sys


def state_names(n: int) -> list[str]:
    """The state variables' names: x0_ .. x{n-1}_ (so that x1_0 starts x1_ and no other)."""
    return [f"x{i}_" for i in range(n)]


def scene_text(n: int) -> str:
    """The scene file's text for n sites: one rhs of n + 2 arguments."""
    names = state_names(n)
    return "\n".join([
        "from ensemble import Parameter",
        "",
        "STATE = {" + ", ".join(f"'{v}': ('1', 'site {i}')" for i, v in enumerate(names)) + "}",
        "PARAMETERS = {'F': Parameter('1', 'forcing'), "
        + ", ".join(f"'{v}0': Parameter('1', 'site at t = 0', default=0.0)" for v in names) + "}",
        "",
        "",
        f"def rhs(t, {', '.join(names)}, F):",
        "    return (" + ", ".join(f"({names[(i + 1) % n]} - {names[i - 2]}) * {names[i - 1]} - {names[i]} + F"
                               for i in range(n)) + ",)",
        ""])


if __name__ == "__main__":
    if len(sys.argv) != 2 or not sys.argv[1].isdigit() or int(sys.argv[1]) < 4:
        print("usage: python examples/lorenz96.py N   (N >= 4 sites)", file=sys.stderr)
        sys.exit(2)
    print(scene_text(int(sys.argv[1])), end="")
