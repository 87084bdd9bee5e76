"""Whole runs of two revisions of ensemble, alternated in the same minutes: a change's effect on a noisy host.

    python analysis/bench/compare_revisions.py OLD [NEW] [--workload tops|chains] [--members N] [--repeats 5]

Checks out OLD and NEW (default: the working tree) into temporary git
worktrees, each with a Numba cache of its own, runs the workload of
benchmark.py --whole once per revision untimed (compiling), then --repeats
rounds of one warm `ensemble run` process per revision, and prints each
revision's wall seconds and their medians, and the run's own seconds (what
`ensemble run` reports: start-up and loading the kernels left out), between
two runs of the C limit (limit.py). --members N replaces the workload's member
count. A host whose speed wanders moves both revisions alike, so the
ratio of the medians holds where either figure alone does not.
"""
from __future__ import annotations

import re
import statistics
import subprocess
import tempfile
from contextlib import contextmanager
from pathlib import Path

from benchmark import WORKLOADS, c_limit, print_limit, whole_run
from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int

ROOT = Path(__file__).resolve().parents[2]


def revision_env(tree: Path, cache: Path) -> dict[str, str]:
    """Environment variables under which `ensemble run` runs the code in `tree` with its own Numba cache.
    PYTHONSAFEPATH: without it Python puts the current folder first on sys.path, so run from a checkout every
    revision imported that checkout's ensemble."""
    return {"PYTHONPATH": str(tree), "PYTHONSAFEPATH": "1", "NUMBA_CACHE_DIR": str(cache)}


@contextmanager
def checked_out(parser, old: str, new: str | None, folder: Path):
    """Revisions old and new (None: the working tree) in git worktrees under `folder`, removed afterwards: yields
    {name: (its code's folder, its environment)}, each with a Numba cache of its own."""
    trees = {}
    try:
        for label, revision in (("old", old), ("new", new)):
            if revision is None:
                trees["working tree"] = ROOT
                continue
            tree = folder / label
            added = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), revision],
                                   capture_output=True, text=True)
            if added.returncode != 0:
                parser.error(f"{revision}: not a revision of {ROOT} ({added.stderr.strip().splitlines()[-1]})")
            trees[revision] = tree
        yield {name: (tree, revision_env(tree, folder / f"cache{k}")) for k, (name, tree) in enumerate(trees.items())}
    finally:
        for tree in trees.values():
            if tree != ROOT:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("old", help="a git revision")
    parser.add_argument("new", nargs="?", help="a git revision (default: the working tree)")
    parser.add_argument("--workload", choices=WORKLOADS, default="tops")
    parser.add_argument("--members", type=positive_int, help="replace the workload's member count")
    parser.add_argument("--repeats", type=positive_int, default=5)
    args = parser.parse_args(argv)
    print(host(), flush=True)
    with tempfile.TemporaryDirectory() as tmp, checked_out(parser, args.old, args.new, Path(tmp)) as trees:
        folder = Path(tmp)
        envs = {name: env for name, (_, env) in trees.items()}
        text = WORKLOADS[args.workload]
        if args.members:
            text = re.sub(r"(?m)^members = .*$", f"members = {args.members}", text)
        for env in envs.values():
            whole_run(text, folder, env=env)  # untimed: compiles
        print_limit("C limit, before", c_limit())
        walls, owns = {name: [] for name in trees}, {name: [] for name in trees}
        for _ in range(args.repeats):
            for name, env in envs.items():
                wall, work, rate, _ = whole_run(text, folder, env=env)
                walls[name].append(wall)
                owns[name].append(work / rate)
        print_limit("C limit, after", c_limit())
    workload = args.workload + (f" ({args.members} members)" if args.members else "")
    for label, seconds in (("wall", walls), ("the run's own", owns)):
        medians = {name: statistics.median(w) for name, w in seconds.items()}
        for name, w in seconds.items():
            print(f"{workload}, {name}, {label}: {medians[name]:.3g} s (median of {args.repeats}: "
                  f"{', '.join(f'{x:.3g}' for x in w)})")
        old, new = medians.values()
        print(f"{label} seconds, new / old: {new / old:.2f}")


if __name__ == "__main__":
    main()
