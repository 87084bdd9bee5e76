"""Command line: a thin layer over ensemble.spec and ensemble.runner."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import __version__
from .arguments import EXIT_BAD_INPUT, EXIT_INTERRUPTED, OneLineParser


def _parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
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
    _inertia_parser(commands)
    return parser


def _inertia_parser(commands) -> None:
    from .inertia import SHAPES

    inertia = commands.add_parser(
        "inertia", help="inertia tensor, principal moments and axes of a body",
        description="Print the inertia tensor of a uniform body about a point, its principal moments (ascending) "
                    "and principal axes. Units: kg, m, kg m2. Laminae lie in the xy plane.")
    shapes = inertia.add_subparsers(dest="shape", required=True, metavar="SHAPE")
    polygon = shapes.add_parser("polygon", help="uniform lamina bounded by a simple polygon (origin: that of "
                                                "its vertices)")
    polygon.add_argument("--vertices", required=True, type=_pairs,
                         help='vertices in m, in order: "x1,y1 x2,y2 ..."')
    point_masses = shapes.add_parser("points", help="point masses (origin: that of their positions)")
    point_masses.add_argument("--points", required=True, type=_point_masses,
                              help='"m1,x1,y1,z1 m2,x2,y2,z2 ..." in kg and m')
    for name, shape in SHAPES.items():
        sub = shapes.add_parser(name, help=shape.summary)
        for length in shape.lengths:
            sub.add_argument(f"--{length.replace('_', '-')}", dest=length, type=float, required=True,
                             metavar="M", help=f"{length.replace('_', ' ')} (m)")
    for sub in (polygon, *(shapes.choices[name] for name in SHAPES)):
        sub.add_argument("--mass", type=float, required=True, metavar="KG", help="mass (kg)")
    for sub in shapes.choices.values():
        sub.add_argument("--origin", type=_numbers(3), default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
                         help="point the tensor is taken about (m; default: the shape's own origin)")
        sub.add_argument("--json", action="store_true",
                         help="print one JSON object: tensor, principal_moments, principal_axes (columns)")


def _numbers(count: int):
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(x) for x in text.split(","))
        except ValueError:
            values = ()
        if len(values) != count:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}")
        return values
    parse.__name__ = f"{count} comma-separated numbers"
    return parse


def _pairs(text: str) -> list[tuple[float, ...]]:
    return [_numbers(2)(item) for item in text.split()]


def _point_masses(text: str) -> list[tuple[float, ...]]:
    return [_numbers(4)(item) for item in text.split()]


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
        part = part_path(out)
        where = (f"the members finished so far are in {part} (not a complete result)" if part.exists()
                 else "before the output file was opened; nothing was written")
        print(f"ensemble: interrupted; {where}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"wrote {out}: {summary}")
    return 0


def _methods() -> int:
    from .methods import METHODS
    from .scenes import scenes_of

    width = max(len(name) for name in METHODS)
    scenes = {name: ",".join(scenes_of(m)) for name, m in METHODS.items()}
    across = max(len("scenes"), *map(len, scenes.values()))
    print(f"{'method':<{width}} {'order':>5}  {'symplectic':<10}  {'scenes':<{across}} description")
    for m in METHODS.values():
        order = "exact" if m.order is None else str(m.order)
        print(f"{m.name:<{width}} {order:>5}  {'yes' if m.symplectic else 'no':<10}  {scenes[m.name]:<{across}} "
              f"{m.summary}")
    return 0


def _inertia(args) -> int:
    import json

    import numpy as np

    from . import inertia

    try:
        if args.shape == "polygon":
            body = inertia.polygon(args.mass, args.vertices)
        elif args.shape == "points":
            table = np.array(args.points, dtype=float)
            body = inertia.points(table[:, 0], table[:, 1:])
        else:
            shape = inertia.SHAPES[args.shape]
            body = shape.build(args.mass, **{length: getattr(args, length) for length in shape.lengths})
    except inertia.ShapeError as e:
        problem = e.problem.replace("r_outer", "--r-outer")
        return _error(f"inertia {args.shape}: --{e.name.replace('_', '-')}: {problem}")
    tensor = body.tensor(args.origin)
    moments, axes = inertia.principal(tensor)
    if args.json:
        print(json.dumps({"tensor": tensor.tolist(), "principal_moments": moments.tolist(),
                          "principal_axes": axes.tolist()}))
        return 0
    scale = np.abs(tensor).max()

    def row(values, tiny):
        return "  ".join(f"{0.0 if abs(v) <= tiny else v:>15.10g}" for v in values)

    mass = float(np.sum(body.mass))
    print(f"{args.shape}: mass {mass:.10g} kg, centre of mass ({', '.join(f'{c:.10g}' for c in body.centre)}) m")
    print(f"inertia tensor about ({', '.join(f'{c:.10g}' for c in args.origin)}) m, kg m2:")
    for line in tensor:
        print("  " + row(line, 1e-14 * scale))
    print("principal moments, kg m2 (ascending):")
    print("  " + row(moments, 1e-14 * scale))
    print("principal axes (unit column vectors, in the order of the moments):")
    for line in axes:
        print("  " + row(line, 1e-14))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "run":
        return _run(args)
    if args.command == "inertia":
        return _inertia(args)
    return _methods()
