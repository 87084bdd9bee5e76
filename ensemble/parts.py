"""Resumable runs: finished chunks recorded as immutable part files beside the output.

A run of OUT.nc writes its result as OUT.nc.tmp (ensemble.store.Writer) and
records what it finished in the folder OUT.nc.parts/:

    manifest.json                             the run's fingerprint (fingerprint): its run file, members' values,
                                              scene's and engine's sources, and the versions that make its bits
    members-J0-J1-CRC.nc                      members J0 .. J1 - 1 (12 digits each) are in OUT.nc.tmp: their
                                              per-member records; inside, the range and run file it is of and
                                              a checksum of each saved variable's samples of its members; CRC is
                                              the CRC-32 of the file's bytes (8 hex digits: it tells a torn or
                                              changed file, not a forged one)
    members-J0-J1.tmp                         a part being written; a resumed run deletes it
    segment-J0-J1-S0-S1-CRC.npz               a record run in segments (runner.segment_samples): members
                                              J0 .. J1 - 1 have samples S0 .. S1 - 1 in OUT.nc.tmp; inside,
                                              what their kernel and observation noise continue from, and the
                                              same range, run file and checksums as a part's. Deleted once
                                              those members' part is made (ensemble.segments)

A chunk's saved variables are written once, into OUT.nc.tmp. Its part is made
only after that: the result is flushed (HDF5's buffers, then fsync), then the
part is written under its .tmp name, checksummed and renamed. So a part with a
final name says its members' samples are on the disk in OUT.nc.tmp, unless its
own bytes changed since (or never reached the disk, when the machine went down
before the system wrote them out: parts are not fsynced), which its checksum
tells. Writing more members changes only their own bytes of OUT.nc.tmp (see
ensemble.store), so a run killed while writing a chunk leaves the finished ones
intact. A resume checks that OUT.nc.tmp opens and is this run's; if not, every
part is dropped and the run starts over. It then trusts a part only when the
range and run file inside it are its name's and this run's (a part renamed or
copied to another range is not), and when its members' samples in OUT.nc.tmp
still give the checksums it recorded (sample_sum); a part that fails is dropped,
and its members computed again. Segments are checked alike, and a member range
continues from the end of its unbroken run of good segments from sample 0. Only
once every member is in are the parts'
records written into the result (Parts.assemble), the result fsynced and renamed
into place, and the folder deleted.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

import netCDF4
import numpy as np

from .checksums import file_crc32, sample_sum, write_atomically
from .errors import EnsembleError
from .events import dimensions as event_dimensions
from .members import members_sha256, members_table
from .results import Status
from .segments import (  # noqa: F401 (SegmentLog: parts' API, built in segments)
    SEGMENT_NAME,
    Segment,
    SegmentLog,
    chains,
    inside_problem,
    segment_files,
    segments_left,
)
from .spec import Spec
from .store import (
    fsync_path,
    kernels_identity,
    member_variables,
    put_records,
    record_names,
    record_variables,
    temporary_path,
)
from .version import __version__

MANIFEST = "manifest.json"
PARTS_FORMAT = "2"  # 2: parts carry their range, run file and sample checksums (ensemble 0.5.0)
MEMBERS_AT_ONCE = 2**16  # members whose member variables assemble() draws and writes at a time
PART_NAME = re.compile(r"members-(\d{12})-(\d{12})-([0-9a-f]{8})\.nc")


def folder_of(out: Path) -> Path:
    """The folder that holds the parts of a run writing `out`."""
    return out.with_name(out.name + ".parts")


def fingerprint(spec: Spec) -> dict[str, str]:
    """What a part's bits depend on besides the member range: the run file's text, the members' values
    (members_sha256: those given member by member and those of the members checked before the start, which the
    run file's text, the seed and the versions below make), the sources of the scene (its file and the user's
    modules it imports) and of the engine's kernels, the device (--device may change the run file's; each
    rounds differently) and the versions of the packages that compute and store them. Neither the compile
    target nor the tuning is in it: every target with fused multiply-adds and every tuning choice give the same
    bits. Its size and cost do not grow with the members."""
    return {"run_file_sha256": run_file_sha256(spec), "members_sha256": members_sha256(spec),
            **{k: v for k, v in kernels_identity(spec).items() if k != "compile_target"},
            "ensemble": __version__, "numba": version("numba"), "numpy": np.__version__,
            "netCDF4": netCDF4.__version__, "device": f"{spec.device} {spec.precision}", "parts_format": PARTS_FORMAT}


def run_file_sha256(spec: Spec) -> str:
    """The SHA-256 of the run file's text, which the fingerprint, each part and each receipt name."""
    return hashlib.sha256(spec.text.encode()).hexdigest()


class PartsError(EnsembleError):
    """The parts folder cannot be used as asked: one line for the user (exit status 2)."""


def open_folder(folder: Path, spec: Spec, resume: bool) -> dict[str, str]:
    """Open the folder where a run keeps what it finished (parts, or a Zarr store's receipts), making it with the
    run's manifest if it is new; returns the run's fingerprint. PartsError if the folder holds what is not a
    run's, an unfinished run without `resume`, or another run's work (its manifest's fingerprint differs)."""
    ours = fingerprint(spec)
    manifest = folder / MANIFEST
    if folder.exists() and not manifest.exists() and any(folder.iterdir()):
        raise PartsError(f"{folder} exists and holds files that are not a run's parts (no {MANIFEST}); move them "
                         f"or choose another output")
    if folder.exists() and not resume:
        raise PartsError(f"{folder} holds the parts of an unfinished run; add --resume to finish it or --force to "
                         f"start over")
    if folder.exists() and manifest.exists():
        try:
            found = json.loads(manifest.read_text())
        except (OSError, ValueError) as e:
            raise PartsError(f"{manifest}: cannot be read ({e}); use --force to start over") from None
        if found != ours:
            changed = [key for key in ours if found.get(key) != ours[key]]
            verb = "differs" if len(changed) == 1 else "differ"
            raise PartsError(f"{folder} was made by another run ({', '.join(changed)} {verb}); --resume continues "
                             f"only the same run file, scene and versions; use --force to start over")
    else:
        folder.mkdir(parents=True, exist_ok=True)
        write_atomically(manifest, json.dumps(ours, indent=1).encode())
    return ours


def remove_folder(folder: Path, ours) -> None:
    """Delete the files of a run's folder (its manifest, and those whose name `ours` accepts), then the folder
    once nothing else is in it; in a folder without the manifest nothing is deleted."""
    if (folder / MANIFEST).is_file():
        for path in folder.iterdir():
            if (path.name == MANIFEST or ours(path.name)) and path.is_file():
                path.unlink()
    if folder.is_dir():
        try:
            folder.rmdir()
        except OSError:  # something of someone else's is in it
            pass


def gaps(done, members: int) -> list[tuple[int, int]]:
    """The member ranges [start, stop) of 0 .. members - 1 that none of `done` (each with .start and .stop, in
    order, without overlaps) holds, in order."""
    found, at = [], 0
    for item in done:
        if item.start > at:
            found.append((at, item.start))
        at = item.stop
    return found + ([(at, members)] if at < members else [])


@dataclass(frozen=True)
class Part:
    """A finished part: members start .. stop - 1 in the file `path`."""
    start: int
    stop: int
    path: Path


class Parts:
    """The parts folder of one run: what is finished, what is missing, writing new parts and assembling them.

    Parts(out, spec, resume) opens it: it makes a new folder (refusing one that exists unless `resume`); with
    `resume`, it checks the manifest against this run's fingerprint (PartsError when they differ), deletes
    leftover .tmp files and parts whose checksum fails, and keeps the rest if OUT.tmp can take them (all are
    deleted if not). `discard(out)` deletes a folder and OUT.tmp. The run sets `result`, the Writer of OUT.tmp
    (reopened when parts were kept), before the first part begins.
    """

    def __init__(self, out: Path, spec: Spec, resume: bool = False):
        self.folder = folder_of(out)
        self.spec = spec
        self.dropped: list[str] = []  # what a resume found broken and deleted, one phrase each
        self.fingerprint = open_folder(self.folder, spec, resume)
        self.parts = self._verified()
        segments, dropped = segment_files(self.folder, lambda start: any(p.start <= start < p.stop for p in self.parts))
        self.dropped += dropped
        problem = self._result_problem(temporary_path(out)) if self.parts or segments else None
        if problem:
            for file in [*self.parts, *segments]:
                file.path.unlink()
            lost = [f"{len(files)} {kind}(s)" for files, kind in ((self.parts, "part"), (segments, "segment")) if files]
            self.dropped.append(f"all {' and '.join(lost)} ({problem})")
            self.parts, segments = [], []
        elif self.parts:
            self.parts = self._vouched_for(temporary_path(out))
        # finished segments of member ranges that no part holds yet, by range, each an unbroken run from sample 0
        self.segments: dict[tuple[int, int], list[Segment]] = self._continuable(segments, temporary_path(out))
        self.result = None  # the result's Writer, set before the first part begins
        self.written: dict[int, dict[str, np.ndarray]] = {}  # records of the parts this run wrote, by first member
        # Parts are sealed (checksum, rename) on a thread of their own while the next chunk computes.
        self._sealing = ThreadPoolExecutor(1, thread_name_prefix="ensemble-parts")
        self._sealed: list[tuple[int, int, Future]] = []  # (start, stop, future of its Part)

    def settle(self) -> list[Part]:
        """Wait for the parts being sealed (re-raising a failure); returns every finished part, in order."""
        sealed, self._sealed = self._sealed, []
        self.parts = sorted([*self.parts, *(future.result() for _, _, future in sealed)], key=lambda p: p.start)
        return self.parts

    def close(self) -> list[Part]:
        """settle, then end the sealing thread; after a failure elsewhere, a failed seal only loses its part."""
        try:
            return self.settle()
        except (OSError, RuntimeError):
            return self.parts
        finally:
            self._sealing.shutdown()

    @staticmethod
    def left_complete(out: Path, spec: Spec) -> bool:
        """Whether `out` is this run's whole result with its parts still beside it: the run was stopped between
        renaming OUT.tmp into place and removing its parts (a resume then only removes them)."""
        manifest = folder_of(out) / MANIFEST
        if not out.is_file() or temporary_path(out).exists() or not manifest.is_file():
            return False
        try:
            with netCDF4.Dataset(out) as nc:
                whole = getattr(nc, "spec", None) == spec.text and getattr(nc, "members_written", -1) == spec.n_members
            return whole and json.loads(manifest.read_text()) == fingerprint(spec)
        except (OSError, ValueError):
            return False

    @staticmethod
    def discard(out: Path) -> None:
        """Delete the parts of `out` and its unfinished result, OUT.tmp: only the files a run writes in the parts
        folder (its manifest, parts and their .tmp files), and the folder once nothing else is in it. In a folder
        without our manifest nothing is deleted."""
        remove_folder(folder_of(out), lambda name: PART_NAME.fullmatch(name) or SEGMENT_NAME.fullmatch(name) or (
            name.startswith(("members-", "segment-")) and name.endswith(".tmp")))
        temporary_path(out).unlink(missing_ok=True)

    def _result_problem(self, path: Path) -> str | None:
        """Why the unfinished result `path` cannot take this run's parts' members (None when it can): it must
        exist, open, and be a result of this run file with its member count."""
        if not path.exists():
            problem = "is missing"
        else:
            try:
                with netCDF4.Dataset(path) as nc:
                    same = (getattr(nc, "spec", None) == self.spec.text and "member" in nc.dimensions
                            and nc.dimensions["member"].size == self.spec.n_members)
                problem = None if same else "is another run's"
            except OSError as e:
                problem = f"cannot be read: {e.strerror or e}"
        return problem and f"{path.name}, which holds their samples, {problem}"

    def _verified(self) -> list[Part]:
        """The parts whose bytes match their checksum, in member order, without overlaps; the rest deleted."""
        for path in self.folder.glob("*.tmp"):
            path.unlink()
            self.dropped.append(f"{path.name} (unfinished)")
        parts = []
        for path in sorted(self.folder.glob("members-*")):
            match = PART_NAME.fullmatch(path.name)
            start, stop = (int(match[1]), int(match[2])) if match else (0, 0)
            if not match or file_crc32(path) != match[3] or not 0 <= start < stop <= self.spec.n_members:
                path.unlink()
                self.dropped.append(f"{path.name} ({'checksum differs' if match else 'not a part'})")
            elif parts and start < parts[-1].stop:
                path.unlink()
                self.dropped.append(f"{path.name} (overlaps another part)")
            else:
                parts.append(Part(start, stop, path))
        return parts

    def _vouched_for(self, result: Path) -> list[Part]:
        """The parts whose recorded range and run file are their name's and this run's, and whose members'
        samples in `result` (OUT.tmp) give the checksums they recorded; the rest deleted."""
        kept = []
        with netCDF4.Dataset(result) as nc:
            nc.set_auto_mask(False)
            for part in self.parts:
                problem = self._part_problem(part, nc)
                if problem:
                    part.path.unlink()
                    self.dropped.append(f"{part.path.name} ({problem})")
                else:
                    kept.append(part)
        return kept

    def _part_problem(self, part: Part, result: netCDF4.Dataset) -> str | None:
        with netCDF4.Dataset(part.path) as nc:
            inside = {key: nc.getncattr(key) for key in nc.ncattrs()}
        return inside_problem(inside, self.fingerprint["run_file_sha256"], self.spec.save, part.start, part.stop, 0,
                              None, result.variables)

    def _continuable(self, segments: list[Segment], result: Path) -> dict[tuple[int, int], list[Segment]]:
        """Per member range, its segments that run on unbroken from sample 0 and whose samples in `result` give
        their checksums; every other segment deleted."""
        if not segments:
            return {}
        with netCDF4.Dataset(result) as nc:
            nc.set_auto_mask(False)
            found, dropped = chains(segments, lambda g, inside: inside_problem(
                inside, self.fingerprint["run_file_sha256"], self.spec.save, g.start, g.stop, g.first, g.end,
                nc.variables))
        self.dropped += dropped
        return found

    def missing(self) -> list[tuple[int, int]]:
        """The member ranges [start, stop) that no finished part holds, in order (see settle)."""
        return gaps(self.parts, self.spec.n_members)

    def continuing(self) -> list[tuple[int, int, int]]:
        """(first member, stop member, samples done) of each member range that continues from its segments."""
        return [(start, stop, chain[-1].end) for (start, stop), chain in self.segments.items()]

    @staticmethod
    def segments_left(out: Path) -> list[tuple[int, int, int]]:
        """As continuing(), read from the names of the segment files of `out`'s parts folder."""
        return segments_left(folder_of(out))

    def members_done(self) -> int:
        """Members in finished parts, counting those being sealed."""
        return sum(part.stop - part.start for part in self.parts) + sum(stop - start for start, stop, _ in
                                                                          self._sealed)

    def begin(self, start: int, stop: int) -> PartWriter:
        """A new part for members start .. stop - 1."""
        return PartWriter(self, start, stop)

    def assemble(self) -> np.ndarray:
        """Write every member's records into `result`, each record in one piece (the parts hold them; their
        samples are in the result already), and the member variables (store.member_variables: drawn again by
        ranges of MEMBERS_AT_ONCE, a pure function of the run file, so that each takes one write a range, not
        one a part); returns how many members ended in each Status. Call settle first: every part must be
        finished."""
        self._sealing.shutdown()
        assert not self._sealed and not self.missing(), "assemble needs every member, settled"
        names = record_names(self.spec)
        records = {name: [] for name in names}
        for part in self.parts:
            data = self.written.get(part.start)
            if data is None:  # an earlier run's part
                with netCDF4.Dataset(part.path) as nc:
                    nc.set_auto_mask(False)
                    data = {name: nc.variables[name][:] for name in names}
            for name in names:
                records[name].append(data[name])
        records = {name: np.concatenate(values) for name, values in records.items()}
        self.result.write(0, records)
        for start in range(0, self.spec.n_members, MEMBERS_AT_ONCE):
            stop = min(start + MEMBERS_AT_ONCE, self.spec.n_members)
            self.result.write(start, member_variables(self.spec, members_table(self.spec, start, stop), start))
        return np.bincount(records["status"], minlength=len(Status))


class PartWriter:
    """Members start .. stop - 1 of a run: their samples written to the parts' result, their records to a .tmp
    file (and to the result by Parts.assemble, once every member is in); finish() makes it a part, abandon()
    deletes it. Same write_samples and write as ensemble.store.Writer, with the run's member indices."""

    def __init__(self, parts: Parts, start: int, stop: int):
        self.parts, self.start, self.stop = parts, start, stop
        self.temporary = parts.folder / f"members-{start:012d}-{stop:012d}.tmp"
        self._nc = None
        self.sums = {name: 0 for name in parts.spec.save}  # sample_sum of each saved variable's samples
        self.logs: list[SegmentLog] = []
        self.done = False  # finish() was called: the part is on its way to being sealed

    @property
    def nc(self) -> netCDF4.Dataset:
        """The part's file, made at the first write (on the thread that writes it)."""
        if self._nc is None:
            self._nc = nc = netCDF4.Dataset(self.temporary, "w", format="NETCDF4")
            nc.set_fill_off()  # as the result's (ensemble.store.Writer)
            spec = self.parts.spec
            nc.createDimension("member", self.stop - self.start)
            if spec.events:  # (spec.model checks a user's scene is unedited: a run without events need not)
                for dim, size in {**spec.model.sizes(spec.constants), **event_dimensions(spec.events)}.items():
                    nc.createDimension(dim, size)
            for name, (kind, dims, *_) in record_variables(spec).items():
                nc.createVariable(name, kind, dims, fill_value=np.nan if kind == "f8" else None)
        return self._nc

    def write_samples(self, start: int, first: int, data: dict[str, np.ndarray]) -> None:
        self.parts.result.write_samples(start, first, data)
        for name, values in data.items():
            self.sums[name] = (self.sums[name] + sample_sum(values, start, first)) % 2**64

    def log(self, start: int, stop: int) -> SegmentLog:
        """The segment log of members start .. stop - 1 (a range of the part's members that runs together)."""
        kept = [segment.path for segment in self.parts.segments.pop((start, stop), [])]
        self.logs.append(SegmentLog(self, start, stop, kept))
        return self.logs[-1]

    @property
    def segment_folder(self) -> Path:
        return self.parts.folder

    @property
    def run_file_sha256(self) -> str:
        return self.parts.fingerprint["run_file_sha256"]

    def make_durable(self) -> None:
        """The result's samples so far onto the disk (before a segment file says they are there)."""
        self.parts.result.sync()
        fsync_path(self.parts.result.temporary)

    def write(self, start: int, data: dict[str, np.ndarray]) -> None:
        """The records of every member of the part (start is the part's) into its file (the member variables
        beside them in `data` are written by Parts.assemble)."""
        self.records = {name: data[name] for name in record_names(self.parts.spec)}
        put_records(self.nc.variables, start - self.start, self.records)

    def finish(self) -> None:
        """Close the file, flush the result, and have the result fsynced and then the part sealed (checksum,
        rename to the part's name) on the parts' own thread: the part is complete once Parts.settle returns."""
        self.nc.setncatts({"first_member": self.start, "stop_member": self.stop,
                           "run_file_sha256": self.parts.fingerprint["run_file_sha256"],
                           **{f"samples_sum_{name}": f"{value:016x}" for name, value in self.sums.items()}})
        self.nc.close()
        self.parts.written[self.start] = self.records
        self.parts.result.sync()
        # the part's members to the disk, before the part says they are there
        self.parts._sealing.submit(fsync_path, self.parts.result.temporary, release=True)
        future = self.parts._sealing.submit(self._seal)
        self.parts._sealed.append((self.start, self.stop, future))
        self.done = True

    def _seal(self) -> Part:
        path = self.parts.folder / f"members-{self.start:012d}-{self.stop:012d}-{file_crc32(self.temporary)}.nc"
        os.replace(self.temporary, path)
        for log in self.logs:  # the part holds their members now
            log.discard()
        return Part(self.start, self.stop, path)

    def abandon(self) -> None:
        try:
            if self._nc is not None:
                self._nc.close()
        except (OSError, RuntimeError):
            pass  # a write failed already (a full disk); that error is the one to report
        self.temporary.unlink(missing_ok=True)
