"""Command line: a thin layer over ensemble.spec and ensemble.runner."""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
from pathlib import Path

# A run's threads are its kernels'. OpenBLAS (numpy's, and scipy's where a run loads it) starts threads of its
# own at import that spin for a while beside them: set before numpy loads; a user's own setting is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from . import __version__
from .arguments import OneLineParser, positive_int
from .errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED, DeviceUnavailable, EnsembleError


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
    run.add_argument("--device", choices=("cpu", "cuda"),
                     help="where the kernels run: this machine's cores, or an NVIDIA GPU (default: the run file's "
                          "device, else cpu); see docs/gpu.md")
    run.add_argument("--resume", action="store_true",
                     help="finish a run that stopped midway: keep the parts it finished (OUTPUT.parts/), compute "
                          "the rest")
    where = run.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="compute on an existing Dask cluster, e.g. tcp://HOST:8786 (needs the dask extra)")
    where.add_argument("--workers", type=positive_int, metavar="N",
                       help="compute on N Dask worker processes started here (needs the dask extra)")
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


def _on_device(args, spec):
    """(the spec on --device's device, or None) and why the run cannot start there (None if it can)."""
    if args.device:
        spec = dataclasses.replace(spec, device=args.device)
    if spec.precision == "float32" and spec.device != "cuda":
        return spec, f"{args.runfile}: precision: float32 runs on a GPU only (--device cuda)"
    if spec.device == "cuda":
        from .engine.gpu import require_gpu

        try:
            require_gpu()
        except DeviceUnavailable as e:
            return spec, f"{args.runfile}: {e}"
    return spec, None


def _run(args) -> int:
    _skip_numba_blas_probe()
    _quiet_numpy()
    from .errors import Incomplete
    from .parts import PartsError
    from .runner import run
    from .scenes import SceneError
    from .spec import SpecError, load

    try:
        spec = load(args.runfile)
    except SpecError as e:
        return _error(f"{args.runfile}: {e}")
    except KeyboardInterrupt:  # drawing members (mode starts solve eigenproblems) can take a while
        print("ensemble: interrupted while reading the run file; nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    out = args.output or Path("results") / f"{args.runfile.stem}.nc"
    spec, refusal = _on_device(args, spec)
    refusal = refusal or _refusal(args, spec, out)
    if refusal:
        return _error(refusal)
    # the command that finishes an interrupted run: a run that replaces an earlier result needs --force again
    resume = f"ensemble run {args.runfile} -o {out} --resume{' --force' if out.exists() else ''}"
    client = None
    try:
        if args.scheduler or args.workers:  # before anything is made: a cluster that cannot be had leaves nothing
            from .cluster import ClusterError, connect

            try:
                client = connect(args.scheduler, args.workers)
            except ClusterError as e:
                return _error(str(e))
        out.parent.mkdir(parents=True, exist_ok=True)
        with OutputLock(out):
            summary = run(spec, out, chunk=args.chunk, progress=not args.quiet, force=args.force,
                          resume=args.resume, command=args.command_line, client=client)
    except OutputLocked:
        return _error(f"{out}: another run is writing it now; wait for it or choose another output")
    except (PartsError, DeviceUnavailable) as e:  # a GPU that went away after the check
        return _error(str(e))
    except SceneError as e:  # a user's scene whose functions do not compile: found before any chunk ran
        return _error(f"{args.runfile}: scene: {e}")
    except KeyboardInterrupt:
        print(f"ensemble: interrupted; {_left_behind(out, resume)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Incomplete as e:
        print(f"ensemble: error: {e}; {_left_behind(out, resume)}", file=sys.stderr)
        return EXIT_FAILED
    except (OSError, RuntimeError) as e:  # netCDF4 reports HDF5 write failures as RuntimeError
        print(f"ensemble: error: {out}: writing failed ({_cause(e, out, spec)}); "
              f"{_left_behind(out, resume)}", file=sys.stderr)
        return EXIT_FAILED
    finally:
        if client is not None:
            from .cluster import close

            close(client)
    print(f"wrote {out}: {summary}")
    return 0


def _refusal(args, spec, out: Path) -> str | None:
    """Why the run is refused before it starts, in one line naming the run file or the output; None if it is not."""
    if args.chunk is not None and args.chunk < 1:
        return f"--chunk: must be >= 1, got {args.chunk}"
    problem = _memory_problem(spec)
    if problem:
        return f"{args.runfile}: {problem}"
    problem = _output_problem(out, args.runfile, args.force) or _space_problem(out, spec, args.resume)
    return f"{out}: {problem}" if problem else None


def _scratch_problem(out: Path, runfile: Path) -> str | None:
    """Why a run of `out` would destroy the run file (None if it would not): the run file is one of the
    output's scratch paths (OUT.tmp, OUT.lock) or lies in its parts folder, which a run writes, replaces and
    deletes."""
    from .parts import folder_of
    from .store import temporary_path

    if not runfile.exists():
        return None
    runfile = runfile.resolve()
    for scratch in (temporary_path(out), OutputLock.path_of(out)):
        if scratch.resolve() == runfile:
            return f"its scratch file {scratch} is the run file, which the run would overwrite; choose another output"
    if folder_of(out).resolve() in runfile.parents:
        return f"the run file lies in {folder_of(out)}, the folder a run of it writes and deletes; move the run file"
    return None


def _output_problem(out: Path, runfile: Path, force: bool) -> str | None:
    """Why `out` cannot be written (None if it can): the run file itself, a folder, an existing file without
    --force or not written by ensemble, a folder that cannot be made or written."""
    if out.exists() and runfile.exists() and out.resolve() == runfile.resolve():
        return "is the run file itself; choose another output"
    problem = _scratch_problem(out, runfile)
    if problem:
        return problem
    if out.is_dir():
        return "is a folder; give the output file's name"
    if out.exists() and not force:
        return "exists; use --force to replace it"
    if out.exists() and not _is_result(out):
        return "exists and is not a result written by ensemble; not replacing it, even with --force"
    existing = _existing(out.parent)
    if not existing.is_dir():
        return f"cannot create the folder {out.parent} ({existing} is not a folder)"
    if not os.access(existing, os.W_OK):
        what = "write in" if existing == out.parent else "create"
        return f"cannot {what} the folder {out.parent} (permission denied in {existing})"
    return None


def _existing(folder: Path) -> Path:
    """The folder itself if it exists, else its nearest ancestor that does (nothing is created before a run
    starts)."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder


def _memory_problem(spec) -> str | None:
    """The smallest chunk's memory against what this machine has available (Linux; no check elsewhere)."""
    from .runner import member_bytes, smallest_chunk

    try:
        available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
    members = smallest_chunk(spec)
    need = members * member_bytes(spec)
    if need > available:
        growth = ", or measure no growth" if spec.measure["growth"] else ""  # its fit holds the whole record
        return (f"{members} members holding {spec.n_save} saved times each need {need / 1e9:.3g} GB "
                f"of memory and {available / 1e9:.3g} GB is available; save less often (save_dt) or fewer "
                f"variables{growth}")
    return None


def _space_problem(out: Path, spec, resume: bool = False) -> str | None:
    """The disk's free space against what the run will take: the result, and its parts (a copy of the per-member
    records) until they are deleted (a full disk midway costs the run). A resumed run counts only what is still
    to come: OUT.tmp took its whole space when it was made, and the parts kept hold their records."""
    from .parts import folder_of
    from .store import output_bytes, record_names, temporary_path

    need = output_bytes(spec) + 8 * len(record_names(spec)) * spec.n_members
    if resume:
        made = [temporary_path(out), *(folder_of(out).iterdir() if folder_of(out).is_dir() else ())]
        need = max(0, need - sum(path.stat().st_size for path in made if path.is_file()))
    free = shutil.disk_usage(_existing(out.parent)).free
    if need > free:
        return f"the result needs about {need / 1e6:.4g} MB and {out.parent} has {free / 1e6:.4g} MB free"
    return None


def _is_result(path: Path) -> bool:
    """A NetCDF file whose `source` attribute says ensemble wrote it."""
    import netCDF4

    try:
        with netCDF4.Dataset(path) as nc:
            return str(getattr(nc, "source", "")).startswith("ensemble")
    except OSError:
        return False


FULL = 1 << 20  # bytes: a disk with less free than this after a failed write counts as full


def _cause(error: Exception, out: Path, spec) -> str:
    """Why writing `out` failed, in a few words. netCDF4 reports HDF5's failures as "NetCDF: HDF error", whatever
    their cause: then a disk left (nearly) full, or a result of `spec` past the process's file size limit (ulimit
    -f), is named."""
    import resource

    from .store import output_bytes

    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    folder = _existing(out.parent)
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if shutil.disk_usage(folder).free < FULL:
        return f"no space left on the device of {folder}"
    if limit != resource.RLIM_INFINITY and output_bytes(spec) > limit:
        return (f"the result of about {output_bytes(spec) / 1e6:.3g} MB is past the file size limit of {limit} "
                f"bytes (ulimit -f)")
    return str(error).splitlines()[0] if str(error) else type(error).__name__


def _left_behind(out: Path, resume: str) -> str:
    """What an interrupted or failed run leaves, and how to finish it."""
    from .parts import folder_of
    from .store import temporary_path

    folder = folder_of(out)
    finished = len(list(folder.glob("members-*.nc"))) if folder.exists() else 0
    if not finished:
        return "no chunk had finished; nothing was kept"
    return (f"the {finished} chunk(s) finished so far are kept in {temporary_path(out)} and {folder}; {resume} "
            f"finishes the run")


class OutputLocked(EnsembleError):
    """Another process holds the output's lock."""


class OutputLock:
    """An exclusive lock on OUT (the file OUT.lock, locked with flock: the lock ends with its process, so a
    killed run leaves no stale lock), so that two runs never write the same output at once."""

    def __init__(self, out: Path):
        self.path = self.path_of(out)

    @staticmethod
    def path_of(out: Path) -> Path:
        return out.with_name(out.name + ".lock")

    def __enter__(self):
        import fcntl

        self.file = open(self.path, "w")
        try:
            fcntl.flock(self.file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self.file.close()
            raise OutputLocked from None
        return self

    def __exit__(self, *exc):
        self.path.unlink(missing_ok=True)
        self.file.close()
        return False


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
    import shlex

    args = _parser().parse_args(argv)
    args.command_line = shlex.join(["ensemble", *(sys.argv[1:] if argv is None else argv)])
    if args.command == "run":
        return _run(args)
    if args.command == "inertia":
        return _inertia(args)
    return _methods()
