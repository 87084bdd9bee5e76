"""Resumable runs: finished chunks kept as immutable part files beside the output, then assembled.

A run of OUT.nc keeps what it finished in the folder OUT.nc.parts/:

    manifest.json                             the run's fingerprint: its run file and the versions that make
                                              its bits (ensemble, numba, numpy, netCDF4)
    members-J0-J1-CRC.nc                      members J0 .. J1 - 1 (12 digits each): their saved variables and
                                              per-member records; CRC is the CRC-32 of the file's bytes (8 hex
                                              digits: it tells a torn or changed file, not a forged one, at less
                                              than half SHA-256's cost)
    members-J0-J1.tmp                         a part being written; a resumed run deletes it

A part is written under its .tmp name, checksummed and renamed, so a part
with a final name is complete unless its bytes changed since (or never
reached the disk, when the machine went down before the system wrote them
out), which its checksum tells: parts are not fsynced, because a resume
checks every one. What a run computes goes into its part and, at the same
time, into the result (ensemble.store.Writer, `OUT.nc.tmp`); parts an earlier
run left are copied in at the end. Only once every member is in is the
result fsynced and renamed into place, and the folder deleted. Until then
the disk holds the parts and the result: about twice the result's size.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import zlib
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

import netCDF4
import numpy as np

from . import __version__
from .scenes import SCENES
from .spec import Spec
from .store import RUN_RECORDS, fsync_path, put_records, put_samples, record_names

MANIFEST = "manifest.json"
PART_NAME = re.compile(r"members-(\d{12})-(\d{12})-([0-9a-f]{8})\.nc")


def folder_of(out: Path) -> Path:
    """The folder that holds the parts of a run writing `out`."""
    return out.with_name(out.name + ".parts")


def fingerprint(spec: Spec) -> dict[str, str]:
    """What a part's bits depend on besides the member range: the run file's text and the versions of the
    packages that compute and store them."""
    return {"run_file_sha256": hashlib.sha256(spec.text.encode()).hexdigest(), "ensemble": __version__,
            "numba": version("numba"), "numpy": np.__version__, "netCDF4": netCDF4.__version__}


class PartsError(Exception):
    """The parts folder cannot be used as asked: one line for the user (exit status 2)."""


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
    leftover .tmp files and parts whose checksum fails, and keeps the rest. `discard(out)` deletes a folder.
    """

    def __init__(self, out: Path, spec: Spec, resume: bool = False):
        self.folder = folder_of(out)
        self.spec = spec
        self.dropped: list[str] = []  # what a resume found broken and deleted, one phrase each
        manifest = self.folder / MANIFEST
        if self.folder.exists() and not resume:
            raise PartsError(f"{self.folder} holds the parts of an unfinished run; add --resume to finish it or "
                             f"--force to start over")
        if self.folder.exists() and manifest.exists():
            try:
                found = json.loads(manifest.read_text())
            except (OSError, ValueError) as e:
                raise PartsError(f"{manifest}: cannot be read ({e}); use --force to start over") from None
            if found != fingerprint(spec):
                changed = ", ".join(key for key in fingerprint(spec) if found.get(key) != fingerprint(spec)[key])
                raise PartsError(f"{self.folder} was made by another run ({changed} differs); --resume continues "
                                 f"only the same run file with the same versions; use --force to start over")
        else:
            self.folder.mkdir(parents=True, exist_ok=True)
            _write_atomically(manifest, json.dumps(fingerprint(spec), indent=1).encode())
        self.parts = self._verified()
        self.result = None  # the result's Writer, set before the first part begins: parts are written into it too
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
    def discard(out: Path) -> None:
        shutil.rmtree(folder_of(out), ignore_errors=True)

    def _verified(self) -> list[Part]:
        """The parts whose bytes match their checksum, in member order, without overlaps; the rest deleted."""
        for path in self.folder.glob("*.tmp"):
            path.unlink()
            self.dropped.append(f"{path.name} (unfinished)")
        parts = []
        for path in sorted(self.folder.glob("members-*")):
            match = PART_NAME.fullmatch(path.name)
            start, stop = (int(match[1]), int(match[2])) if match else (0, 0)
            if not match or _checksum(path) != match[3] or not 0 <= start < stop <= self.spec.n_members:
                path.unlink()
                self.dropped.append(f"{path.name} ({'checksum differs' if match else 'not a part'})")
            elif parts and start < parts[-1].stop:
                path.unlink()
                self.dropped.append(f"{path.name} (overlaps another part)")
            else:
                parts.append(Part(start, stop, path))
        return parts

    def missing(self) -> list[tuple[int, int]]:
        """The member ranges [start, stop) that no finished part holds, in order (see settle)."""
        gaps, at = [], 0
        for part in self.parts:
            if part.start > at:
                gaps.append((at, part.start))
            at = part.stop
        return gaps + ([(at, self.spec.n_members)] if at < self.spec.n_members else [])

    def members_done(self) -> int:
        """Members in finished parts, counting those being sealed."""
        return sum(part.stop - part.start for part in self.parts) + sum(stop - start for start, stop, _ in
                                                                          self._sealed)

    def begin(self, start: int, stop: int, segment: int | None = None) -> PartWriter:
        """A new part for members start .. stop - 1; HDF5 chunks of `segment` samples (default: whole)."""
        return PartWriter(self, start, stop, segment or self.spec.n_save)

    def assemble(self, segment: int) -> dict[str, np.ndarray]:
        """Copy the parts not yet in `result` (an earlier run's), `segment` samples at a time; returns the
        per-member records of every member, in member order. Call settle first: every part must be finished."""
        self._sealing.shutdown()
        assert not self._sealed and not self.missing(), "assemble needs every member, settled"
        names = record_names(self.spec)
        records = {name: [] for name in names}
        for part in self.parts:
            data = self.written.get(part.start)
            if data is None:  # an earlier run's part
                with netCDF4.Dataset(part.path) as nc:
                    nc.set_auto_mask(False)
                    for first in range(0, self.spec.n_save, segment):
                        self.result.write_samples(part.start, first, {
                            name: nc.variables[name][:, first:first + segment] for name in self.spec.save})
                    data = {name: nc.variables[name][:] for name in names}
                self.result.write(part.start, data)
            for name in names:
                records[name].append(data[name])
        return {name: np.concatenate(values) for name, values in records.items()}


class PartWriter:
    """Members start .. stop - 1 of a run, written to a .tmp file and to the parts' result; finish() makes it a
    part, abandon() deletes it. Same write_samples and write as ensemble.store.Writer, with the run's member
    indices."""

    def __init__(self, parts: Parts, start: int, stop: int, segment: int):
        self.parts, self.start, self.stop, self.segment = parts, start, stop, segment
        self.temporary = parts.folder / f"members-{start:012d}-{stop:012d}.tmp"
        self._nc = None

    @property
    def nc(self) -> netCDF4.Dataset:
        """The part's file, made at the first write (on the thread that writes it)."""
        if self._nc is None:
            spec, scene = self.parts.spec, SCENES[self.parts.spec.scene]
            self._nc = nc = netCDF4.Dataset(self.temporary, "w", format="NETCDF4")
            nc.set_fill_off()  # as the result's (ensemble.store.Writer)
            sizes = {"member": self.stop - self.start, "t": spec.n_save, **scene.sizes(spec.constants)}
            for name in spec.save:
                dims = scene.OBSERVABLES[name][0]
                for dim in dims:
                    if dim not in nc.dimensions:
                        nc.createDimension(dim, sizes[dim])
                chunks = tuple({**sizes, "t": min(self.segment, spec.n_save)}[d] for d in dims)
                nc.createVariable(name, "f8", dims, chunksizes=chunks, fill_value=np.nan)
            for name in record_names(spec):
                kind = RUN_RECORDS[name][0]
                nc.createVariable(name, kind, ("member",), fill_value=np.nan if kind == "f8" else None)
        return self._nc

    def write_samples(self, start: int, first: int, data: dict[str, np.ndarray]) -> None:
        put_samples(self.nc.variables, start - self.start, first, data)
        self.parts.result.write_samples(start, first, data)

    def write(self, start: int, data: dict[str, np.ndarray]) -> None:
        """The records of every member of the part (start is the part's)."""
        put_records(self.nc.variables, start - self.start, data)
        self.parts.result.write(start, data)
        self.records = data

    def finish(self) -> None:
        """Close the file and have it sealed (checksum, rename to the part's name) on the parts' own thread: the
        part is complete once Parts.settle returns."""
        self.nc.close()
        self.parts.written[self.start] = self.records
        # what is written of the result goes to the disk now, while the run goes on, not all at its end
        self.parts._sealing.submit(fsync_path, self.parts.result.temporary)
        future = self.parts._sealing.submit(self._seal)
        self.parts._sealed.append((self.start, self.stop, future))

    def _seal(self) -> Part:
        path = self.parts.folder / f"members-{self.start:012d}-{self.stop:012d}-{_checksum(self.temporary)}.nc"
        os.replace(self.temporary, path)
        return Part(self.start, self.stop, path)

    def abandon(self) -> None:
        try:
            if self._nc is not None:
                self._nc.close()
        except (OSError, RuntimeError):
            pass  # a write failed already (a full disk); that error is the one to report
        self.temporary.unlink(missing_ok=True)


def _checksum(path: Path) -> str:
    """The CRC-32 of a file's bytes, 8 hex digits."""
    crc = 0
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(2**20), b""):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def _write_atomically(path: Path, data: bytes) -> None:
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "wb") as file:
        file.write(data)
        file.flush()
        os.fsync(file.fileno())
    os.replace(temporary, path)
    fsync_path(path.parent)
