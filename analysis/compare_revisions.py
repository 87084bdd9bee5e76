"""Whole runs of two revisions of ensemble, alternated in the same minutes: a change's effect on a noisy host.

    python analysis/compare_revisions.py OLD [NEW] [--workload tops|chains] [--repeats 5]

Checks out OLD and NEW (default: the working tree) into temporary git
worktrees, each with a Numba cache of its own, runs the workload of
benchmark.py --whole once per revision untimed (compiling), then --repeats
rounds of one warm `ensemble run` process per revision, and prints each
revision's wall seconds and their medians, between two runs of the C limit
(limit.py). A host whose speed wanders moves both revisions alike, so the
ratio of the medians holds where either figure alone does not.
"""
from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmark import WORKLOADS, c_limit, print_limit
from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int

ROOT = Path(__file__).resolve().parent.parent


def one_run(tree: Path, cache: Path, runfile: Path, out: Path) -> float:
    """Wall seconds of one `ensemble run` process of the code in `tree`."""
    out.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(cache)}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--quiet"],
                          env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"compare_revisions: the run failed in {tree}: {done.stderr.strip().splitlines()[-1:]}")
    out.unlink(missing_ok=True)
    return seconds


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("old", help="a git revision")
    parser.add_argument("new", nargs="?", help="a git revision (default: the working tree)")
    parser.add_argument("--workload", choices=WORKLOADS, default="tops")
    parser.add_argument("--repeats", type=positive_int, default=5)
    args = parser.parse_args(argv)
    print(host(), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        trees = {}  # name -> its code's folder
        for label, revision in (("old", args.old), ("new", args.new)):
            if revision is None:
                trees["working tree"] = ROOT
                continue
            tree = folder / label
            added = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), revision],
                                   capture_output=True, text=True)
            if added.returncode != 0:
                parser.error(f"{revision}: not a revision of {ROOT} ({added.stderr.strip().splitlines()[-1]})")
            trees[revision] = tree
        try:
            runfile = folder / "run.toml"
            runfile.write_text(WORKLOADS[args.workload])
            caches = {name: folder / f"cache{k}" for k, name in enumerate(trees)}
            for name, tree in trees.items():
                one_run(tree, caches[name], runfile, folder / "out.nc")
            print_limit("C limit, before", c_limit())
            walls = {name: [] for name in trees}
            for _ in range(args.repeats):
                for name, tree in trees.items():
                    walls[name].append(one_run(tree, caches[name], runfile, folder / "out.nc"))
            print_limit("C limit, after", c_limit())
        finally:
            for tree in trees.values():
                if tree != ROOT:
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                                   capture_output=True)
    medians = {name: statistics.median(w) for name, w in walls.items()}
    for name, w in walls.items():
        print(f"{args.workload}, {name}: {medians[name]:.2f} s (median of {args.repeats}: "
              f"{', '.join(f'{x:.2f}' for x in w)})")
    old, new = medians.values()
    print(f"new / old: {new / old:.2f}")


if __name__ == "__main__":
    main()
