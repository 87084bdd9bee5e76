"""Command line: a thin layer over ensemble.spec and ensemble.runner."""
from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

# A run's threads are its kernels'. OpenBLAS (numpy's, and scipy's where a run loads it) starts threads of its
# own at import that spin for a while beside them: set before numpy loads; a user's own setting is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from . import __version__
from .arguments import OneLineParser, location, positive_int
from .errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EnsembleError
from .places import place


def _parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="ensemble", description="Integrate ensembles of tops, spring chains and free rigid bodies (or scenes of "
                                     "your own), write NetCDF, and fit the results against theory.")
    parser.add_argument("--version", action="version", version=f"ensemble {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = commands.add_parser("run", help="integrate a run file and write its dataset",
                              description="Integrate every member of a run file and write one NetCDF file (or a "
                                          "Zarr store).")
    run.add_argument("runfile", type=Path, help="run file (TOML), see runs/")
    run.add_argument("-o", "--output", help="output file (default: results/<runfile stem>.nc), or a Zarr store if it "
                                            "ends in .zarr (the zarr extra; docs/cluster.md)")
    run.add_argument("--force", action="store_true", help="replace an existing output file")
    run.add_argument("--chunk", type=int, help="members per chunk held in memory, rounded up to whole kernel blocks "
                                               "(default: about 32 MB of output)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--device", choices=("cpu", "cuda"),
                     help="where the kernels run: this machine's cores, or an NVIDIA GPU (default: the run file's "
                          "device, else cpu); see docs/gpu.md")
    run.add_argument("--precision", choices=("float64", "float32"),
                     help="the kernels' float type: float32 runs on a GPU only (default: the run file's "
                          "precision, else float64); see docs/gpu.md")
    run.add_argument("--resume", action="store_true",
                     help="finish a run that stopped midway: keep the parts it finished (OUTPUT.parts/), compute "
                          "the rest")
    where = run.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="compute on an existing Dask cluster, e.g. tcp://HOST:8786 (needs the dask extra)")
    where.add_argument("--workers", type=positive_int, metavar="N",
                       help="compute on N Dask worker processes started here (needs the dask extra)")
    methods = commands.add_parser("methods", help="list the integration methods",
                                  description="List each method: order, symplectic or not, and the scenes it "
                                              "applies to; with a scene (a built-in's name or a scene file of "
                                              "your own), the methods that apply to it.")
    methods.add_argument("scene", nargs="?", help="a scene: top, chain, body, or the path of a scene file")
    tune = commands.add_parser("tune", help="time this machine's kernel layouts and keep the fastest (once per "
                                            "machine, about a minute)",
                               description="Time the candidate kernel layouts on this machine (vector width, "
                                           "members per block, loop order, a chain's sweeps) and keep the winners "
                                           "for every later run; see docs/speed.md.")
    tune.add_argument("--dry-run", action="store_true", help="measure and print, but keep nothing")
    convert = commands.add_parser("convert", help="write a Zarr result as one NetCDF file",
                                  description="Write the Zarr store a run wrote (-o OUT.zarr) as one NetCDF file: the "
                                              "same variables, attributes and bits, in the layout `ensemble run` "
                                              "writes.")
    convert.add_argument("source", type=location, help="a Zarr store written by `ensemble run` (OUT.zarr)")
    convert.add_argument("target", type=Path, help="the NetCDF file to write (OUT.nc)")
    convert.add_argument("--force", action="store_true", help="replace an existing target")
    _analysis_parsers(commands)
    _inertia_parser(commands)
    return parser


def _analysis_parsers(commands) -> None:
    fit = commands.add_parser(
        "fit", help="fit a result and test it against theory",
        description="Fit every member of a result with its scene's fit (a top: tilt decay rate; a chain: normal-mode "
                    "frequencies; a body: growth rate, wobble frequency, flip period), print per sweep point the "
                    "mean against theory with z, and write the fits as RESULT_<fit>.nc beside the result.")
    fit.add_argument("--against", choices=("theory", "method"), default="theory",
                     help="compare with the physics (default) or with what the run's method shows at its step")
    fit.add_argument("--members", type=_indices, metavar="I,J,...",
                     help="members drawn in the per-member charts (default: six spread over the result; a chain's "
                          "spectrum: the first given, else member 0)")
    stability = commands.add_parser(
        "stability", help="where each method fails: measured growth per step against theory",
        description="From a stability scan (runs/stability_*.toml): per method and dimensionless step axis, the "
                    "theoretical limit beside the measured one; writes the map as RESULT_stability.nc.")
    stability.add_argument("--drift-step", type=float, default=0.5,
                           help="dimensionless step of the members in the energy-drift chart (default 0.5)")
    work = commands.add_parser(
        "work-precision", help="what each digit of accuracy costs, per method",
        description="From a run with [measure] error = true (and timing = true for the cost): per method its points "
                    "and measured convergence order; writes the table as RESULT_work_precision.nc.")
    for sub, passes in ((fit, "a fitted sweep point disagrees with its reference"),
                        (stability, "a measured limit disagrees with theory (the table's `agree` column)")):
        sub.add_argument("--check", action="store_true", help=f"exit 1 when {passes}")
    fit.add_argument("results", type=location, nargs="+", metavar="RESULT",
                     help="result files written by `ensemble run`; several (of one scene) are combined and fitted "
                          "together, their fits written beside the first")
    stability.add_argument("result", type=location, help="a result file written by `ensemble run`")
    work.add_argument("results", type=location, nargs="+", metavar="RESULT",
                      help="result files written by `ensemble run`, of one scene: several are charted together (a "
                           "line per method and precision or device where they differ); the table goes beside the "
                           "first")
    for sub in (fit, stability, work):
        sub.add_argument("--charts", type=Path, metavar="DIR",
                         help="draw the charts as PNG files in DIR (needs the plot extra)")


def _indices(text: str) -> list[int]:
    try:
        found = [int(item) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected member numbers I,J,..., got {text!r}") from None
    if min(found) < 0:
        raise argparse.ArgumentTypeError(f"member numbers are >= 0, got {min(found)}")
    return found


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


def _skip_numba_blas_probe() -> None:
    """Import Numba's array functions with its BLAS probe failing fast.

    Loading its first kernel, Numba imports scipy.linalg only to learn whether its np.vdot may call BLAS
    (numba.np.arraymath._HAVE_BLAS); that import is about 0.2 s of a 1 s small run here. ensemble's kernels
    call no BLAS, and Numba's np.dot and np.linalg still import scipy.linalg when a kernel that uses them
    compiles: only this probe is skipped, and scipy.linalg imports normally afterwards."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    sys.modules["scipy.linalg.cython_blas"] = None  # `import scipy.linalg.cython_blas` raises ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules["scipy.linalg.cython_blas"]


def _quiet_numpy() -> None:
    """Overflow in a value derived from extreme input (lambda1 = 1e-320, spin0 = 1e308) is judged by the checks
    and the members' status, each reported in one line: numpy's own warnings would add lines of their own."""
    import numpy as np

    np.seterr(all="ignore")


def _run(args) -> int:
    _skip_numba_blas_probe()
    _quiet_numpy()
    from . import interrupts, preflight

    interrupts.remember()
    from .runner import run
    from .scenes import SceneError
    from .spec import SpecError, load
    from .zarr_store import exists

    try:
        spec = load(args.runfile)
    except SpecError as e:
        return _error(f"{args.runfile}: {e}")
    except KeyboardInterrupt:  # drawing members (mode starts solve eigenproblems) can take a while
        print("ensemble: interrupted while reading the run file; nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    if args.output and (url := preflight.url_problem(args.output)):
        return _error(url)
    out = place(args.output) if args.output else Path("results") / f"{args.runfile.stem}.nc"
    try:
        spec, chunk, refusal = preflight.check(spec, out, args.runfile, device=args.device, chunk=args.chunk,
                                               force=args.force, resume=args.resume, chunk_option="--chunk",
                                               precision=args.precision)
    except EnsembleError as e:  # a kernel folder that is not the user's, a scene that does not compile
        return _error(f"{args.runfile}: {e}" if isinstance(e, SceneError) else str(e))
    if refusal:
        return _error(refusal)
    if chunk != args.chunk and not args.quiet:
        print(f"ensemble: --chunk {args.chunk} is rounded up to {chunk}: whole kernel blocks (or every member), as a "
              f"block computes all its members however few the chunk has", file=sys.stderr)
    # the command that finishes an interrupted run: a run that replaces an earlier result needs --force again
    resume = f"ensemble run {args.runfile} -o {out} --resume{' --force' if exists(out) else ''}"
    client, made = None, []
    try:
        if args.scheduler or args.workers:  # before anything is made: a cluster that cannot be had leaves nothing
            from .cluster import ClusterError, connect

            try:
                client = connect(args.scheduler, args.workers)
            except ClusterError as e:
                return _error(str(e))
        made = preflight.make_folder(out.parent)
        with preflight.OutputLock(out):
            summary = run(spec, out, chunk=chunk, progress=not args.quiet, force=args.force,
                          resume=args.resume, command=args.command_line, client=client)
    except (preflight.OutputLocked, EnsembleError, KeyboardInterrupt, OSError, RuntimeError) as e:
        status = _stopped(e, args.runfile, out, resume, spec)
        if status == EXIT_BAD_INPUT:  # nothing run or written: nor a folder made for it
            preflight.remove_empty(made)
        return status
    finally:
        if client is not None:
            from .cluster import close

            with interrupts.HeldInterrupts():  # a Ctrl-C while the cluster closes would leave its traceback
                close(client)
    print(f"{'' if summary.complete_already else 'wrote '}{out}: {summary}")
    return 0


def _stopped(error: BaseException, runfile: Path, out: Path, resume: str, spec) -> int:
    """One line on stderr for a run that stopped, and its exit status: refused (2), interrupted (130; the
    result may have been complete already), failed midway (3: what it left and the command that finishes it)."""
    from . import preflight
    from .interrupts import LateInterrupt
    from .scenes import SceneError

    if isinstance(error, preflight.OutputLocked):
        return _error(f"{out}: another run is writing it now; wait for it or choose another output")
    if isinstance(error, SceneError) and error.exit_status == EXIT_BAD_INPUT:  # found before any chunk ran
        return _error(f"{runfile}: scene: {error}")
    if isinstance(error, EnsembleError) and error.exit_status == EXIT_BAD_INPUT:  # parts of another run, no GPU
        return _error(str(error))
    if isinstance(error, LateInterrupt):
        print(f"ensemble: interrupted once the result was complete: wrote {out}: {error.summary}", file=sys.stderr)
        return EXIT_INTERRUPTED
    left = preflight.left_behind(out, resume)
    if isinstance(error, KeyboardInterrupt):
        print(f"ensemble: interrupted; {left}", file=sys.stderr)
        return EXIT_INTERRUPTED
    if isinstance(error, EnsembleError):  # Incomplete: chunks that kept failing on a cluster
        print(f"ensemble: error: {error}; {left}", file=sys.stderr)
        return EXIT_FAILED
    # netCDF4 reports HDF5 write failures as RuntimeError
    print(f"ensemble: error: {out}: writing failed ({preflight.cause(error, out, spec)}); {left}", file=sys.stderr)
    return EXIT_FAILED


def _convert(args) -> int:
    from .preflight import is_result
    from .zarr_store import convert, is_zarr

    if not is_zarr(args.source) or not args.source.is_dir():
        return _error(f"{args.source}: not a Zarr store (a folder named OUT.zarr, written by `ensemble run`)")
    if args.target.suffix != ".nc":
        return _error(f"{args.target}: the target is a NetCDF file, named OUT.nc")
    if args.target.exists() and not (args.force and is_result(args.target)):
        return _error(f"{args.target}: exists" + ("; use --force to replace it" if is_result(args.target) else
                                                   " and is not a result written by ensemble; not replacing it"))
    try:
        convert(args.source, args.target)
    except EnsembleError as e:
        return _error(str(e))
    print(f"wrote {args.target} from {args.source}")
    return EXIT_OK


def _tune(args) -> int:
    from . import tuner, tuning

    print(f"tuning this machine: {tuning.host_key()['cpu']}")
    try:
        chosen, measured = tuner.tune(say=lambda line: print(line, flush=True))
        print(f"chosen: {chosen.summary()}")
        if args.dry_run:
            print("kept nothing (--dry-run)")
        else:
            print(f"wrote {tuning.save(chosen, measured)}: every later `ensemble run` here uses it")
    except (RuntimeError, OSError) as e:  # a measurement that failed, a cache folder that cannot be written
        print(f"ensemble: error: tune: {e}; nothing was kept", file=sys.stderr)
        return EXIT_FAILED
    return 0


def _methods(scene: str | None = None) -> int:
    from .methods import METHODS
    from .scenes import SceneError, absolute, applies, resolve, scenes_of

    chosen = list(METHODS.values())
    if scene is not None:
        try:
            model = resolve(absolute(scene, Path.cwd()))
        except SceneError as e:
            return _error(str(e))
        chosen = [m for m in chosen if applies(m, model)]
        print(f"methods for {model.NAME} ({scene}):")
    width = max(len(name) for name in METHODS)
    scenes = {name: ",".join(scenes_of(m)) for name, m in METHODS.items()}
    across = max(len("scenes"), *map(len, scenes.values()))
    print(f"{'method':<{width}} {'order':>5}  {'symplectic':<10}  {'scenes':<{across}} description")
    for m in chosen:
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


def entry() -> None:
    """The `ensemble` command (and python -m ensemble): main, then exit with its status. After an interrupt the
    process only ends, and a second Ctrl-C would cut that short with a traceback: it is ignored from there."""
    try:
        status = main()
    except KeyboardInterrupt:  # before a run started or after it ended (a run reports its own)
        print("ensemble: interrupted", file=sys.stderr)
        status = EXIT_INTERRUPTED
    except BrokenPipeError:  # `ensemble fit ... | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's flush at exit must not raise
        status = EXIT_OK
    if status == EXIT_INTERRUPTED:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise SystemExit(status)


def main(argv: list[str] | None = None) -> int:
    import shlex

    args = _parser().parse_args(argv)
    args.command_line = shlex.join(["ensemble", *(sys.argv[1:] if argv is None else argv)])
    if args.command == "run":
        return _run(args)
    if args.command == "inertia":
        return _inertia(args)
    if args.command == "tune":
        return _tune(args)
    if args.command == "convert":
        return _convert(args)
    if args.command in ("fit", "stability", "work-precision"):
        from . import report

        if report.charts_problem(args.charts):
            return _error(f"--charts {args.charts}: {report.charts_problem(args.charts)}")
        _quiet_numpy()
        return {"fit": report.fit_command, "stability": report.stability_command,
                "work-precision": report.work_precision_command}[args.command](args)
    return _methods(args.scene)
