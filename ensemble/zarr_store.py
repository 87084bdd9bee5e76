"""Zarr output (the `zarr` extra): a result written by whoever computes it, resumable from receipts.

A run of OUT.zarr writes a Zarr v3 store, OUT.zarr.tmp, with the NetCDF
result's contract (ensemble.store.Description: names, units, CF attributes,
flags, provenance). Its client writes the template: metadata and the coordinates
that are not over member. Members (their parameters, samples and records) then
arrive by task ranges, each whole chunks (or one shard, where a range outgrows a
chunk), written by the process that computed them
(this one, or a Dask worker: never two writers in a chunk or shard), and each
finished range leaves a receipt in OUT.zarr.parts/:

    manifest.json                    the run's fingerprint (ensemble.parts.fingerprint)
    receipt-J0-J1.json               members J0 .. J1 - 1 are in the store: the range, the run file it is of, a
                                     checksum of each variable's values there (ensemble.checksums.sample_sum) and
                                     the counts the run's summary needs
    segments/segment-J0-J1-S0-S1-CRC.npz
                                     a record run in segments: members J0 .. J1 - 1 have samples S0 .. S1 - 1 in
                                     the store, and what they continue from (ensemble.segments); deleted with
                                     the receipt of their range (a folder of their own: a range looks for its
                                     segments there, not among every receipt)

A resume trusts a range only by its receipt, and a receipt only when the store
still gives its checksums (a chunk of fill values is not stored, and a torn
write may leave a chunk behind): the rest is computed again, a range in
segments from its last segment whose samples the store still gives. Once every member
is in, the metadata is consolidated and OUT.zarr.tmp renamed to OUT.zarr.
Every chunk and shard index carries a CRC32C codec.

At an fsspec URL (ensemble.places: an object store has no rename) the store is
written where it will stay, OUT.zarr itself, its template without the result's
attributes, then without its root's metadata, which waits in
OUT.zarr.parts/group.json: until the run is whole, OUT.zarr opens as no result,
and a run finishes by writing it there and consolidating.
"""
from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .checksums import record_sum, sample_sum, write_atomically
from .errors import EnsembleError
from .parts import MANIFEST, fingerprint, folder_of, gaps, open_folder, remove_folder, run_file_sha256
from .places import is_remote, place, remove_tree, zarr_location
from .segments import SEGMENT_NAME, Segment, SegmentLog, chains, inside_problem, segment_files, segments_left
from .spec import Spec
from .store import TIMES_AT_ONCE, described, fsync_path, temporary_path, written_by_ranges
from .summary import counts

SUFFIX = ".zarr"
CHUNK_BYTES = 2**24  # at most, a chunk: what a reader fetches at once; a task's range above it is sharded
RECEIPT = "receipt-{:012d}-{:012d}.json"
ROOT = "group.json"  # in the receipts folder: a URL's store's root metadata, until the store is whole


def is_zarr(path: str | Path) -> bool:
    """Whether `path` names a Zarr store (OUT.zarr) rather than a NetCDF file."""
    return (path if is_remote(path) else Path(path)).suffix == SUFFIX


def _zarr():
    try:
        import zarr
    except ImportError:
        raise EnsembleError("a .zarr output needs zarr; install it with pip install 'ensemble[zarr]'") from None
    return zarr


def _open_group(path, mode: str):
    location, options = zarr_location(path)
    return _zarr().open_group(location, mode=mode, zarr_format=3, storage_options=options or None)


def _open_array(path, name: str, mode: str):
    location, options = zarr_location(path)
    return _zarr().open_array(location, path=name, mode=mode, storage_options=options or None)


def unfinished(out):
    """Where the store `out` is written until it is whole: OUT.zarr.tmp, or, at a URL, OUT.zarr itself."""
    return out if is_remote(out) else temporary_path(out)


def exists(out) -> bool:
    """Whether `out` exists, but for a URL's store that a run of ours is still writing (no result's root
    metadata yet, and our receipts folder beside it): that is OUT.zarr.tmp's part there."""
    if is_remote(out) and not whole(out) and (folder_of(out) / MANIFEST).is_file():
        return False
    return out.exists()


def whole(store) -> bool:
    """Whether the store's root metadata holds a result's attributes (a URL's store is given them last)."""
    try:
        return "members_written" in json.loads((store / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return False


def zarr_problem() -> str | None:
    """Why this machine cannot write a Zarr store (None if it can): zarr is missing."""
    try:
        _zarr()
    except EnsembleError as e:
        return str(e)
    return None


def _largest_divisor(n: int, at_most: int) -> int:
    """The largest divisor of n that is at most `at_most` (at least 1)."""
    best = 1
    for d in range(1, math.isqrt(n) + 1):
        if n % d == 0:
            best = max(best, *(k for k in (d, n // d) if k <= at_most))
    return best


def saved_layout(shape: tuple[int, ...], task: tuple[int, int]) -> tuple[tuple[int, ...], tuple[int, ...] | None]:
    """(chunk, shard or None) of a saved variable (member, t, ...) written by tasks of `task` = (members, samples
    per segment) (runner.segment_samples: the whole record, or the segments it runs in, written as they come).
    A task's range of whole records is one chunk if it fits CHUNK_BYTES, else one shard whose chunks hold whole
    records of as many members as fit, or part of one long record (zarr-python writes a shard several times
    slower than a chunk, measured: none is made where one chunk does). A record in segments has a chunk per
    task and segment, which its writes fill whole."""
    members, samples, *rest = shape
    task_shape = (min(task[0], members), samples, *rest)
    row = 8 * math.prod(rest)
    if task[1] < samples:
        return (task_shape[0], task[1], *rest), None
    if task_shape[0] * samples * row <= CHUNK_BYTES:
        return task_shape, None
    if samples * row <= CHUNK_BYTES:
        return (_largest_divisor(task_shape[0], CHUNK_BYTES // (samples * row)), samples, *rest), task_shape
    return (1, _largest_divisor(samples, max(1, CHUNK_BYTES // row)), *rest), task_shape


def _attribute(value):
    """A NetCDF attribute's value as JSON."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value.item() if isinstance(value, np.generic) else value


def create(path: Path, spec: Spec, command: str | None, task: tuple[int, int], attributes: bool = True) -> dict:
    """Write the template of the result of `spec` at `path` (a new folder): every variable of
    ensemble.store.Description, the coordinates that are not over member with their values; what is over member
    (member variables, samples, records) is written later by tasks, `task` = (members, samples per segment) at a
    time. Its size does not grow with the members. Returns the result's attributes, which the root group gets
    only with `attributes` (a URL's store gets them last: without them, it is no result)."""
    from xarray.backends.zarr import FillValueCoder
    from zarr.codecs import Crc32cCodec

    group = _open_group(path, "w-")
    nc = described(spec, command)
    try:
        found = {name: _attribute(nc.getncattr(name)) for name in nc.ncattrs()}
        if attributes:
            group.attrs.update(found)
        filled_later = set(written_by_ranges(spec))
        for name, variable in nc.variables.items():
            shape, dims = variable.shape, variable.dimensions
            shards = None
            if name in spec.save:
                chunks, shards = saved_layout(shape, task)
            elif dims[:1] == ("member",):
                chunks = (min(task[0], shape[0]), *shape[1:])
            elif dims == ("t",):
                chunks = (max(1, min(shape[0], TIMES_AT_ONCE)),)
            else:
                chunks = tuple(max(1, size) for size in shape)
            attributes = {k: _attribute(variable.getncattr(k)) for k in variable.ncattrs() if k != "_FillValue"}
            fill = variable.getncattr("_FillValue") if "_FillValue" in variable.ncattrs() else None
            if fill is not None:
                attributes["_FillValue"] = FillValueCoder.encode(fill, variable.dtype)  # as xarray writes it
            array = group.create_array(name, shape=shape, dtype=variable.dtype, chunks=chunks, shards=shards,
                                       fill_value=fill if fill is not None else 0, dimension_names=dims,
                                       attributes=attributes, compressors=(Crc32cCodec(),))
            if name not in filled_later and all(shape):
                array[...] = variable[...]
    finally:
        nc.close()
    return found


def task_members(path: Path, spec: Spec) -> int:
    """Members per task of the store at `path` (its chunks or shards of members): a resume continues them."""
    array = _open_array(path, spec.save[0] if spec.save else "status", "r")
    return int((array.shards or array.chunks)[0])


class Region:
    """Members start .. stop - 1 written into the store at `path` by the process that computed them (a task's
    range: whole chunks, or a shard, in which no one else writes). Same write_samples, write and log as
    ensemble.parts.PartWriter, with the run's member indices; receipt() says what was written. A record run in
    segments keeps each finished segment's file in `folder` (segments_folder; ensemble.segments), which whoever
    computes the range again continues from, once the store gives its samples' checksums."""

    def __init__(self, path: Path, spec: Spec, start: int, stop: int, folder: Path, arrays: dict | None = None):
        """`arrays`: the store's arrays by name, opened already (Region adds those it opens)."""
        self.spec, self.start, self.stop, self.path, self.segment_folder = spec, start, stop, path, folder
        self.arrays = {} if arrays is None else arrays  # each opened once: its metadata read from the store
        self.sums: dict[str, int] = dict.fromkeys(spec.save, 0)
        self.records: dict[str, np.ndarray] | None = None
        self.run_file_sha256 = run_file_sha256(spec)
        self._scrub()

    def _scrub(self) -> None:
        """Delete the range's chunk (or shard) files of its saved variables that cannot be read (their CRC32C
        fails: a flipped bit, or a crash before they reached the disk), left by an attempt that did not finish:
        the range writes them again, and zarr reads a chunk it writes only part of (a range of two launches, or
        a segment). Files are found by the store's chunk keys (c/ROW/COLUMN/..., its default encoding)."""
        for name in self.spec.save:
            array = self.array(name)
            grid = array.shards or array.chunks
            for row in range(self.start // grid[0], (self.stop - 1) // grid[0] + 1):
                folder = self.path / name / "c" / str(row)
                for path in [p for p in folder.rglob("*") if p.is_file()] if folder.is_dir() else []:
                    coordinates = (row, *map(int, path.relative_to(folder).parts))
                    try:
                        array[tuple(slice(c * g, (c + 1) * g) for c, g in zip(coordinates, grid))]
                    except ValueError:
                        path.unlink()

    def array(self, name: str):
        if name not in self.arrays:
            self.arrays[name] = _open_array(self.path, name, "r+")
        return self.arrays[name]

    def write_samples(self, start: int, first: int, data: dict[str, np.ndarray]) -> None:
        for name, values in data.items():
            self.array(name)[start:start + values.shape[0], first:first + values.shape[1]] = values
            self.sums[name] = (self.sums.get(name, 0) + sample_sum(values, start, first)) % 2**64

    def log(self, start: int, stop: int) -> SegmentLog:
        """The segment log of members start .. stop - 1 (a range of the region's members that runs together),
        with the range's segment files that run on unbroken from sample 0 and whose samples the store still gives;
        the others deleted."""
        if not self.segment_folder.is_dir():
            return SegmentLog(self, start, stop, [])
        pattern = f"segment-{start:012d}-{stop:012d}-*"
        found, _ = segment_files(self.segment_folder, lambda first: False, pattern)
        kept, _ = chains(found, self._segment_problem)
        return SegmentLog(self, start, stop, [segment.path for segment in kept.get((start, stop), [])])

    def _segment_problem(self, segment, inside: dict) -> str | None:
        arrays = {name: self.array(name) for name in self.spec.save}
        try:
            return inside_problem(inside, self.run_file_sha256, self.spec.save, segment.start, segment.stop,
                                  segment.first, segment.end, arrays)
        except (OSError, ValueError, KeyError):
            return "its samples in the store cannot be read"

    def make_durable(self) -> None:
        """Nothing to do: each chunk is a file written whole (a resume checks a segment's samples in the store)."""

    def write(self, start: int, data: dict[str, np.ndarray]) -> None:
        """The records and member variables (ensemble.store.member_variables) of every member of the range (start
        is the range's)."""
        for name, values in data.items():
            self.array(name)[start:start + len(values)] = values
            self.sums[name] = record_sum(values, start)
        self.records = data

    def receipt(self) -> dict:
        """The range, its run file, each variable's checksum, and the counts of what it ran (which
        summary.Tally.merge and Receipts.assemble add up)."""
        return {"start": self.start, "stop": self.stop, "run_file_sha256": self.run_file_sha256,
                "sums": {name: f"{value:016x}" for name, value in sorted(self.sums.items())},
                "counts": counts(self.records)}


def checked_sums(path: Path, spec: Spec, start: int, stop: int) -> dict[str, str] | None:
    """The checksums of members start .. stop - 1 as the store at `path` holds them now (as Region.receipt's);
    None when a chunk of theirs cannot be read (its CRC32C fails, or it is not a chunk)."""
    sums = {}
    try:
        for name in written_by_ranges(spec):
            values = _open_array(path, name, "r")[start:stop]
            sums[name] = sample_sum(values, start, 0) if name in spec.save else record_sum(values, start)
    except (OSError, ValueError, KeyError):
        return None
    return {name: f"{value:016x}" for name, value in sorted(sums.items())}


@dataclass(frozen=True)
class Receipt:
    start: int
    stop: int
    path: Path
    status: tuple[int, ...]  # members that ended in each Status, as its receipt counted them


class Receipts:
    """The receipts folder of a run writing OUT.zarr: the same questions as ensemble.parts.Parts asks of its
    parts (missing, members_done, begin, settle, assemble), answered from receipts.

    Receipts(out, spec, resume) opens it as Parts opens a parts folder (a manifest of another run refused); with
    `resume`, a receipt whose range the store no longer gives its checksums is dropped, with its members."""

    def __init__(self, out: Path, spec: Spec, resume: bool = False, client=None):
        """`client`: a dask.distributed Client whose workers will write the store: each must see it where this
        process does (cluster.check_sees), and they check the receipts kept, reading the store where they are."""
        self.store, self.folder, self.spec = unfinished(out), folder_of(out), spec
        self.segments = segments_folder(out)
        self.dropped: list[str] = []
        made = not self.folder.exists()
        open_folder(self.folder, spec, resume)
        if client is not None:
            from .cluster import check_sees

            try:
                check_sees(client, self.folder, str(out))
            except BaseException:
                if made:  # refused before anything ran: nothing is left
                    remove_folder(self.folder, lambda name: False)
                raise
        self.parts = self._verified(client) if self.store.exists() else self._lost()
        self.arrays: dict = {}  # the store's arrays, opened once for every range written here

    def _verified(self, client) -> list[Receipt]:
        """The receipts whose ranges the store still holds as they were written (checked on the cluster's workers
        when there is a `client`); the rest deleted."""
        found = {}
        for path in sorted(self.folder.glob("receipt-*.json")):
            try:
                inside = json.loads(path.read_text())
                if (path.name == RECEIPT.format(inside["start"], inside["stop"])
                        and inside["run_file_sha256"] == run_file_sha256(self.spec)):
                    found[path] = inside
                    continue
            except (OSError, ValueError, KeyError, TypeError):
                pass
            self._drop(path)
        ranges = [(inside["start"], inside["stop"]) for inside in found.values()]
        if client is None:
            stored = [checked_sums(self.store, self.spec, *r) for r in ranges]
        else:
            stored = client.gather(client.map(checked_sums, [self.store.resolve()] * len(ranges), [self.spec] * len(
                ranges), *zip(*ranges), pure=False)) if ranges else []
        kept = []
        for (path, inside), sums in zip(found.items(), stored):
            if sums == inside["sums"]:
                kept.append(Receipt(inside["start"], inside["stop"], path, tuple(inside["counts"]["status"])))
            else:
                self._drop(path)
        return kept

    def _lost(self) -> list[Receipt]:
        """No store to hold the receipts' members: every receipt and segment deleted, none kept."""
        for path in sorted([*self.folder.glob("receipt-*.json"), *self.segments.glob("segment-*")]):
            self._drop(path, "the store it vouches for is missing")
        return []

    def _drop(self, path: Path, why: str = "the store no longer holds what it says") -> None:
        path.unlink()
        self.dropped.append(f"{path.name} ({why})")

    def missing(self) -> list[tuple[int, int]]:
        return gaps(sorted(self.parts, key=lambda r: r.start), self.spec.n_members)

    def continuing(self) -> list[tuple[int, int, int]]:
        """(first member, stop member, samples done) of each member range with segments kept, from their names
        (whoever computes the range checks them against the store first)."""
        return segments_left(self.segments)

    def members_done(self) -> int:
        return sum(r.stop - r.start for r in self.parts)

    def begin(self, start: int, stop: int) -> RegionWriter:
        return RegionWriter(self, start, stop)

    def keep(self, receipt: dict) -> None:
        """Save a finished range's receipt (the store holds its members)."""
        path = self.folder / RECEIPT.format(receipt["start"], receipt["stop"])
        write_atomically(path, json.dumps(receipt).encode(), durable=False)  # a resume checks it against the store
        self.parts.append(Receipt(receipt["start"], receipt["stop"], path, tuple(receipt["counts"]["status"])))
        for path in self.segments.glob("segment-*.npz"):  # those of the range: the receipt holds their members
            segment = Segment.of(path)
            if segment and receipt["start"] <= segment.start < receipt["stop"]:
                path.unlink(missing_ok=True)

    def settle(self) -> list[Receipt]:
        return self.parts

    def close(self) -> list[Receipt]:
        return self.parts

    def assemble(self) -> np.ndarray:
        """How many members ended in each Status (as Parts.assemble), summed over the receipts: every member's
        records are in the store already, and the client reads none of them."""
        return np.sum([r.status for r in self.parts], axis=0, dtype=np.int64)

    @staticmethod
    def left_complete(out: Path, spec: Spec) -> bool:
        """Whether OUT.zarr is this run's whole result with its receipts still beside it."""
        manifest = folder_of(out) / MANIFEST
        if not (out / "zarr.json").is_file() or not manifest.is_file() or (
                not is_remote(out) and temporary_path(out).exists()):
            return False
        try:
            attributes = json.loads((out / "zarr.json").read_text()).get("attributes", {})
            return (attributes.get("spec") == spec.text and attributes.get("members_written") == spec.n_members
                    and json.loads(manifest.read_text()) == fingerprint(spec))
        except (OSError, ValueError):
            return False

    @staticmethod
    def discard(out: Path) -> None:
        """Delete the receipts of `out` and its unfinished store (OUT.zarr.tmp, or at a URL OUT.zarr while it is
        not whole: only beside our receipts)."""
        ours = (folder_of(out) / MANIFEST).is_file()
        if ours:
            for path in segments_folder(out).glob("segment-*"):
                if SEGMENT_NAME.fullmatch(path.name) or path.suffix == ".tmp":
                    path.unlink()
            if segments_folder(out).is_dir():
                segments_folder(out).rmdir()
        remove_folder(folder_of(out), lambda name: name.startswith("receipt-") or name == ROOT)
        if not is_remote(out) or (ours and not whole(out)):
            remove_store(unfinished(out))

    @staticmethod
    def segments_left(out: Path) -> list[tuple[int, int, int]]:
        return segments_left(segments_folder(out))


class RegionWriter(Region):
    """A range computed in this process: a Region whose finish() saves its receipt (Parts.begin's writer)."""

    def __init__(self, receipts: Receipts, start: int, stop: int):
        super().__init__(receipts.store, receipts.spec, start, stop, receipts.segments, receipts.arrays)
        self.receipts, self.done = receipts, False

    def finish(self) -> None:
        self.receipts.keep(self.receipt())
        self.done = True

    def abandon(self) -> None:
        """Nothing to delete: without a receipt the range is computed again."""


def segments_folder(out: Path) -> Path:
    """Where the segment files of a run writing the store `out` are kept."""
    return folder_of(out) / "segments"


def remove_store(path: Path) -> None:
    """Delete the Zarr store at `path`, if there is one (a folder with its zarr.json, or at a URL one whose root
    metadata is not written yet: its arrays' are)."""
    if (path / "zarr.json").is_file() or (is_remote(path) and any(path.glob("*/zarr.json"))):
        remove_tree(path)


class ZarrWriter:
    """The store OUT.zarr.tmp (at a URL, OUT.zarr without its root metadata): its template made (or, on a
    resume, found); on success the metadata consolidated and the store renamed to OUT.zarr (at a URL, its root
    metadata written). Members are written by Region, not through it. A record in segments is written segment
    by segment as its range runs, and a stopped run continues an unfinished range from its last segment
    (Region.log)."""

    def __init__(self, path: Path, spec: Spec, command: str | None, task: tuple[int, int], reopen: bool = False):
        """`task`: (members, samples per segment) a task writes at a time (create)."""
        self.path, self.temporary = path, unfinished(path)
        self.root = folder_of(path) / ROOT
        if not reopen:
            remove_store(self.temporary)  # at a URL, --force's store: there is no other place to write
            attributes = create(self.temporary, spec, command, task, attributes=not is_remote(path))
            if is_remote(path):  # the root's metadata as Zarr v3 writes it (NaN a bare token), put there last
                root = {"attributes": attributes, "zarr_format": 3, "node_type": "group"}
                write_atomically(self.root, json.dumps(root, indent=2).encode())
                (path / "zarr.json").unlink()

    def sync(self) -> None:
        """Each chunk is a file of its own, written whole: nothing is held back."""

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        if kind is None:
            if is_remote(self.path):
                (self.path / "zarr.json").write_bytes(self.root.read_bytes())
            with warnings.catch_warnings():  # consolidated metadata is not in the v3 spec yet; xarray reads it
                warnings.simplefilter("ignore")
                _zarr().consolidate_metadata(_open_group(self.temporary, "r+").store)
            if not is_remote(self.path):
                remove_store(self.path)  # --force: the store this run replaces
                os.replace(self.temporary, self.path)
                fsync_path(self.path.parent)
        return False


def xarray_source(path) -> tuple[str | Path, dict]:
    """(what xarray opens, the keyword arguments it opens it with) for the result at `path`: a Zarr store (a path
    or a URL, which may be a str) or a NetCDF file."""
    if not is_zarr(path):
        return path, {"engine": "netcdf4"}
    _zarr()
    location, options = zarr_location(place(path))
    return location, {"engine": "zarr", **({"storage_options": options} if is_remote(place(path)) else {})}


def convert(source: Path, target: Path, members_at_once: int | None = None) -> None:
    """Write the Zarr store `source` as the NetCDF file `target`: the same variables, dimensions, attributes and
    bits, in the layout `ensemble run` writes (saved variables and records contiguous); copied by ranges of the
    store's shards (`members_at_once`), so memory stays within a few of them. `target` appears when whole."""
    import netCDF4
    from xarray.backends.zarr import FillValueCoder

    group = _open_group(source, "r")
    arrays = dict(group.arrays())
    if "member" not in arrays or "spec" not in group.attrs:
        raise EnsembleError(f"{source}: is not a result of `ensemble run` (no member variable or spec attribute)")
    temporary = temporary_path(target)
    with netCDF4.Dataset(temporary, "w", format="NETCDF4") as nc:
        nc.set_fill_off()
        nc.setncatts(dict(group.attrs))
        for name, array in arrays.items():
            for dim, size in zip(array.metadata.dimension_names, array.shape):
                if dim not in nc.dimensions:
                    nc.createDimension(dim, size)
        for name, array in arrays.items():
            attributes = dict(array.attrs)
            fill = attributes.pop("_FillValue", None)
            if fill is not None:
                fill = FillValueCoder.decode(fill, array.dtype)
            dims = array.metadata.dimension_names
            variable = nc.createVariable(name, np.dtype(array.dtype).newbyteorder("="), dims, fill_value=fill,
                                         contiguous=dims[:1] == ("member",) and len(dims) > 0)
            variable.setncatts({k: np.asarray(v, dtype=array.dtype) if k == "flag_values" else v
                                for k, v in attributes.items()})
        for name, array in arrays.items():
            if array.ndim == 0:
                nc.variables[name].assignValue(array[...])
                continue
            step = max(1, members_at_once or (array.shards or array.chunks)[0])
            for first in range(0, array.shape[0], step):
                nc.variables[name][first:first + step] = array[first:first + step]
    fsync_path(temporary)
    os.replace(temporary, target)
    fsync_path(target.parent)
