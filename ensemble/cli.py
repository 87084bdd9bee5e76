"""Command line: a thin layer over ensemble.spec and ensemble.runner."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import __version__

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ensemble", description="Integrate ensembles of tops and spring chains; write NetCDF.")
    parser.add_argument("--version", action="version", version=f"ensemble {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = commands.add_parser("run", help="integrate a run file and write its dataset",
                              description="Integrate every member of a run file and write one NetCDF file.")
    run.add_argument("runfile", type=Path, help="run file (TOML), see runs/")
    run.add_argument("-o", "--output", type=Path, help="output file (default: results/<runfile stem>.nc)")
    run.add_argument("--force", action="store_true", help="replace an existing output file")
    run.add_argument("--chunk", type=int, help="members per chunk held in memory (default: about 32 MB of output)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    commands.add_parser("methods", help="list the integration methods",
                        description="List each method: order, symplectic or not, and the scenes it applies to.")
    return parser


def _error(message: str) -> int:
    print(f"ensemble: error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _run(args) -> int:
    from .runner import run
    from .spec import SpecError, load
    from .store import part_path

    try:
        spec = load(args.runfile)
    except SpecError as e:
        return _error(f"{args.runfile}: {e}")
    if args.chunk is not None and args.chunk < 1:
        return _error(f"--chunk: must be >= 1, got {args.chunk}")
    out = args.output or Path("results") / f"{args.runfile.stem}.nc"
    if out.exists() and not args.force:
        return _error(f"{out}: exists; use --force to replace it")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return _error(f"{out.parent}: cannot create output folder ({e.strerror})")
    try:
        summary = run(spec, out, chunk=args.chunk, progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"ensemble: interrupted; the members finished so far are in {part_path(out)} "
              f"(not a complete result)", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"wrote {out}: {summary}")
    return 0


def _methods() -> int:
    from .methods import METHODS

    width = max(len(name) for name in METHODS)
    print(f"{'method':<{width}} {'order':>5}  {'symplectic':<10}  {'scenes':<12} description")
    for m in METHODS.values():
        order = "exact" if m.order is None else str(m.order)
        print(f"{m.name:<{width}} {order:>5}  {'yes' if m.symplectic else 'no':<10}  {','.join(m.scenes):<12} "
              f"{m.summary}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "run":
        return _run(args)
    return _methods()
