"""What is checked before a run starts, and what a run that stopped leaves: shared by `ensemble run` and
ensemble.run. Each check gives one line naming what is wrong, or None."""
from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

from .errors import DeviceUnavailable, EnsembleError
from .places import URL, is_remote, place
from .spec import DEVICES, PRECISIONS


def make_folder(folder: Path) -> list[Path]:
    """mkdir -p folder; returns the folders it made, innermost first (see remove_empty). None at a URL (an
    object store has no folders: its files make their prefixes)."""
    if is_remote(folder):
        return []
    made = []
    at = Path(folder)
    while not at.exists():
        made.append(at)
        at = at.parent
    folder.mkdir(parents=True, exist_ok=True)
    return made


def remove_empty(folders: list[Path]) -> None:
    """Remove those of `folders` (innermost first) that are still empty: a run refused leaves nothing behind."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


class RunRefused(EnsembleError):
    """A run refused before it started (nothing was computed or written); the message names what and where."""


def url_problem(output: str) -> str | None:
    """Why `output`, as the user wrote it, cannot be written (None if it can): a URL (s3://, gs://, file://, ...)
    of anything but a Zarr store, or without the zarr extra or the fsspec file system its scheme needs (a Path
    would quietly turn it into a folder named after its scheme)."""
    if not URL.match(output):
        return None
    from .zarr_store import is_zarr, zarr_problem

    if not is_zarr(output):
        return f"{output}: a URL takes a Zarr store (OUT.zarr); a NetCDF result is written to a path"
    problem = zarr_problem()
    if problem:
        return f"{output}: {problem}"
    try:
        place(output).fs
    except (ImportError, ValueError) as e:  # fsspec's: an unknown scheme, or its package missing
        return f"{output}: {str(e).splitlines()[0]}"
    return None


def check(spec, out: Path, runfile: Path | None, *, device: str | None, chunk: int | None, force: bool,
          resume: bool, chunk_option: str = "chunk", precision: str | None = None):
    """(the spec on `device` in `precision`, or the run file's; the chunk, rounded up to whole kernel blocks; why
    the run is refused before it starts, or None): on_device, then refusal, then whole_blocks."""
    spec, problem = on_device(spec, device, str(runfile or "the run"), precision)
    problem = problem or refusal(spec, out, runfile, chunk=chunk, force=force, resume=resume,
                                 chunk_option=chunk_option)
    return spec, (whole_blocks(spec, chunk) if chunk and not problem else chunk), problem


def whole_blocks(spec, chunk: int) -> int:
    """A chunk of members rounded up to whole kernel blocks (or every member): a kernel block computes all its
    members, so a chunk of 7 in a block of 128 costs what 128 do (a resume in chunks of 7 took 84 s, not 4.5)."""
    from .runner import run_block

    block = run_block(spec)
    return min(-(-chunk // block) * block, max(chunk, spec.n_members))


def on_device(spec, device: str | None, where: str, precision: str | None = None):
    """The spec on `device` in `precision` (None: the run file's), and why it cannot run there (None if it
    can)."""
    if device is not None and device not in DEVICES:
        return spec, f"device: {device!r} is not one of {', '.join(DEVICES)}"
    if precision is not None and precision not in PRECISIONS:
        return spec, f"precision: {precision!r} is not one of {', '.join(PRECISIONS)}"
    if device:
        spec = dataclasses.replace(spec, device=device)
    if precision:
        spec = dataclasses.replace(spec, precision=precision)
    if spec.precision == "float32" and spec.device != "cuda":
        return spec, f"{where}: precision: float32 runs on a GPU only (--device cuda)"
    if spec.device == "cuda":
        from .engine.gpu import require_gpu

        try:
            require_gpu()
        except DeviceUnavailable as e:
            return spec, f"{where}: {e}"
    return spec, None


def refusal(spec, out: Path, runfile: Path | None, *, chunk: int | None, force: bool, resume: bool,
            chunk_option: str = "chunk") -> str | None:
    """Why the run is refused before it starts, in one line naming the run file, the output or the chunk option
    (as the caller spells it); None if it is not. runfile: the run file's path (None for text or a dict)."""
    if chunk is not None and chunk < 1:
        return f"{chunk_option}: must be >= 1, got {chunk}"
    problem = memory_problem(spec)
    if problem:
        return f"{runfile or 'the run'}: {problem}"
    from .parts import Parts
    from .zarr_store import Receipts, is_zarr, zarr_problem

    if resume and (Receipts if is_zarr(out) else Parts).left_complete(out, spec):
        return None  # the run finished and was stopped before removing its parts: the resume removes them
    problem = zarr_problem() if is_zarr(out) else None
    problem = problem or output_problem(out, runfile, force) or space_problem(out, spec, resume)
    return f"{out}: {problem}" if problem else None


def scratch_problem(out: Path, runfile: Path | None) -> str | None:
    """Why a run of `out` would destroy the run file (None if it would not): the run file is one of the
    output's scratch paths (OUT.tmp, OUT.lock) or lies in its parts folder, which a run writes, replaces and
    deletes."""
    from .parts import folder_of
    from .store import temporary_path

    if runfile is None or not runfile.exists() or is_remote(out):
        return None
    runfile = runfile.resolve()
    for scratch in (temporary_path(out), OutputLock.path_of(out)):
        if scratch.resolve() == runfile:
            return f"its scratch file {scratch} is the run file, which the run would overwrite; choose another output"
    if folder_of(out).resolve() in runfile.parents:
        return f"the run file lies in {folder_of(out)}, the folder a run of it writes and deletes; move the run file"
    return None


def output_problem(out: Path, runfile: Path | None, force: bool) -> str | None:
    """Why `out` cannot be written (None if it can): the run file itself, a folder, an existing file without
    --force or not written by ensemble, a folder that cannot be made or written."""
    if is_remote(out):
        return remote_problem(out, force)
    if out.exists() and runfile is not None and runfile.exists() and out.resolve() == runfile.resolve():
        return "is the run file itself; choose another output"
    problem = scratch_problem(out, runfile)
    if problem:
        return problem
    if out.is_dir() and not is_result(out):
        return "is a folder; give the output file's name (or a Zarr store's, OUT.zarr)"
    if out.exists() and not force:
        return "exists; use --force to replace it"
    if out.exists() and not is_result(out):
        return "exists and is not a result written by ensemble; not replacing it, even with --force"
    existing = existing_folder(out.parent)
    if not existing.is_dir():
        return f"cannot create the folder {out.parent} ({existing} is not a folder)"
    if not os.access(existing, os.W_OK):
        what = "write in" if existing == out.parent else "create"
        return f"cannot {what} the folder {out.parent} (permission denied in {existing})"
    return None


def remote_problem(out, force: bool) -> str | None:
    """output_problem of a URL's store: one that cannot be reached, or exists without --force or not written by
    ensemble. Its folders are not checked: an object store has none."""
    from .zarr_store import exists

    try:
        here = exists(out)
    except Exception as e:  # noqa: BLE001 (each file system raises its own: credentials, network, permissions)
        return f"cannot be reached ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
    if here and not force:
        return "exists; use --force to replace it (at a URL, the old store is deleted when the run starts)"
    if here and not is_result(out):
        return "exists and is not a result written by ensemble; not replacing it, even with --force"
    return None


def existing_folder(folder: Path) -> Path:
    """The folder itself if it exists, else its nearest ancestor that does (nothing is created before a run
    starts)."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder


def memory_problem(spec) -> str | None:
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


def space_problem(out: Path, spec, resume: bool = False) -> str | None:
    """The disk's free space against what the run will take: the result, and a NetCDF result's parts (a copy of
    the per-member records) until they are deleted (a full disk midway costs the run; a Zarr store's receipts are
    a few hundred bytes a range). A resumed run counts only what is still to come: OUT.tmp took its whole space
    when it was made, and the parts kept hold their records."""
    from .parts import folder_of
    from .store import output_bytes, record_values, temporary_path
    from .zarr_store import is_zarr

    if is_remote(out):  # no free-space figure at a URL
        return None
    need = output_bytes(spec) + (0 if is_zarr(out) else 8 * record_values(spec) * spec.n_members)
    if resume:
        made = [temporary_path(out), *(folder_of(out).iterdir() if folder_of(out).is_dir() else ())]
        made += list(temporary_path(out).rglob("*")) if temporary_path(out).is_dir() else []  # a store's chunks
        need = max(0, need - sum(path.stat().st_size for path in made if path.is_file()))
    free = shutil.disk_usage(existing_folder(out.parent)).free
    if need > free:
        return f"the result needs about {need / 1e6:.4g} MB and {out.parent} has {free / 1e6:.4g} MB free"
    return None


def is_result(path: Path) -> bool:
    """A NetCDF file or Zarr store whose `source` attribute says ensemble wrote it."""
    import json

    import netCDF4

    from .zarr_store import is_zarr

    if is_zarr(path):
        try:
            return str(json.loads((path / "zarr.json").read_text())["attributes"]["source"]).startswith("ensemble")
        except (OSError, ValueError, KeyError, TypeError):
            return False
    try:
        with netCDF4.Dataset(path) as nc:
            return str(getattr(nc, "source", "")).startswith("ensemble")
    except OSError:
        return False


FULL = 1 << 20  # bytes: a disk with less free than this after a failed write counts as full


def cause(error: Exception, out: Path, spec) -> str:
    """Why writing `out` failed, in a few words. netCDF4 reports HDF5's failures as "NetCDF: HDF error", whatever
    their cause: then a disk left (nearly) full, or a result of `spec` past the process's file size limit (ulimit
    -f), is named."""
    import resource

    from .store import output_bytes

    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    if is_remote(out):
        return str(error).splitlines()[0] if str(error) else type(error).__name__
    folder = existing_folder(out.parent)
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if shutil.disk_usage(folder).free < FULL:
        return f"no space left on the device of {folder}"
    if limit != resource.RLIM_INFINITY and output_bytes(spec) > limit:
        return (f"the result of about {output_bytes(spec) / 1e6:.3g} MB is past the file size limit of {limit} "
                f"bytes (ulimit -f)")
    return str(error).splitlines()[0] if str(error) else type(error).__name__


def left_behind(out: Path, resume: str) -> str:
    """What an interrupted or failed run leaves, and how to finish it."""
    from .parts import Parts, folder_of
    from .store import temporary_path
    from .zarr_store import Receipts, is_zarr, unfinished

    folder = folder_of(out)
    finished = len([*folder.glob("members-*.nc"), *folder.glob("receipt-*.json")]) if folder.exists() else 0
    going = (Receipts if is_zarr(out) else Parts).segments_left(out) if folder.exists() else []
    if not finished and not going:
        return "no chunk had finished; nothing was kept"
    kept = [f"the {finished} chunk(s) finished so far"] if finished else []
    kept += [f"samples 0 to {end - 1} of members {start} to {stop - 1}" for start, stop, end in going]
    result = (unfinished if is_zarr(out) else temporary_path)(out)
    return f"{' and '.join(kept)} are kept in {result} and {folder}; {resume} finishes the run"


class OutputLocked(EnsembleError):
    """Another process holds the output's lock."""


class OutputLock:
    """An exclusive lock on OUT (the file OUT.lock, locked with flock: the lock ends with its process, so a
    killed run leaves no stale lock), so that two runs never write the same output at once. A URL's store has
    none: an object store has no lock (docs/cluster.md)."""

    def __init__(self, out: Path):
        self.path = None if is_remote(out) else self.path_of(out)

    @staticmethod
    def path_of(out: Path) -> Path:
        return out.with_name(out.name + ".lock")

    def __enter__(self):
        import fcntl

        if self.path is None:
            return self
        self.file = open(self.path, "w")
        try:
            fcntl.flock(self.file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self.file.close()
            raise OutputLocked from None
        return self

    def __exit__(self, *exc):
        if self.path is None:
            return False
        self.path.unlink(missing_ok=True)
        self.file.close()
        return False


