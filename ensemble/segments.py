"""Finished segments of records run in segments (runner.segment_samples): the files that let a member range
stopped midway continue from its last finished segment instead of from sample 0, beside a NetCDF result
(ensemble.parts) or a Zarr store (ensemble.zarr_store) alike.

    segment-J0-J1-S0-S1-CRC.npz    members J0 .. J1 - 1 have samples S0 .. S1 - 1 in the result; inside, what
                                   their kernel and observation noise continue from, and the range, run file
                                   and a checksum of each saved variable's samples of the segment (`inside`);
                                   CRC is the CRC-32 of the file's bytes

A segment is trusted only when its bytes give its CRC, its inside names its range and this run's file, and the
result still gives its samples' checksums; a range continues from the end of its unbroken run of such segments
from sample 0 (chains).
"""
from __future__ import annotations

import io
import itertools
import json
import re
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .checksums import file_crc32, sample_sum, write_atomically

SEGMENT_NAME = re.compile(r"segment-(\d{12})-(\d{12})-(\d{12})-(\d{12})-([0-9a-f]{8})\.npz")


@dataclass(frozen=True)
class Segment:
    """A finished segment: samples first .. end - 1 of members start .. stop - 1, described by the file `path`."""
    start: int
    stop: int
    first: int
    end: int
    path: Path

    @staticmethod
    def of(path: Path) -> Segment | None:
        match = SEGMENT_NAME.fullmatch(path.name)
        return match and Segment(*(int(match[k]) for k in range(1, 5)), path)


def segment_files(folder: Path, whole, pattern: str = "segment-*") -> tuple[list[Segment], list[str]]:
    """(the segment files in `folder` (those `pattern` matches) whose bytes match their checksum, what was
    dropped): a segment whose members `whole(start)` says are held whole already (by a part) is deleted
    silently, one whose name or bytes are broken with a phrase saying so."""
    kept, dropped = [], []
    for path in sorted(folder.glob(pattern)):
        segment = Segment.of(path)
        if segment and whole(segment.start):
            path.unlink()
        elif not segment or file_crc32(path) != SEGMENT_NAME.fullmatch(path.name)[5]:
            path.unlink()
            dropped.append(f"{path.name} ({'checksum differs' if segment else 'not a segment'})")
        else:
            kept.append(segment)
    return kept, dropped


def chains(segments: list[Segment], problem_of) -> tuple[dict[tuple[int, int], list[Segment]], list[str]]:
    """(per member range, its segments that run on unbroken from sample 0 and of which problem_of(segment, inside)
    finds nothing wrong; what was dropped): every other segment deleted."""
    found, dropped = {}, []
    ordered = sorted(segments, key=lambda g: (g.start, g.stop, g.first))
    for members, group in itertools.groupby(ordered, key=lambda g: (g.start, g.stop)):
        chain, problem = [], None
        for segment in group:
            if problem:
                problem = "follows a segment that was dropped"
            elif segment.first != (chain[-1].end if chain else 0):
                problem = "does not continue the segments before it"
            else:
                problem = problem_of(segment, segment_inside(segment.path))
            if problem:
                segment.path.unlink()
                dropped.append(f"{segment.path.name} ({problem})")
            else:
                chain.append(segment)
        if chain:
            found[members] = chain
    return found, dropped


def inside_problem(inside: dict, run_file_sha256: str, save, start: int, stop: int, first: int, end: int | None,
                   arrays) -> str | None:
    """What is wrong with a part's or segment's own account of members start .. stop - 1, samples first .. end - 1
    (every sample: end None), checked against its name, this run's file and the saved variables `save` in
    `arrays` (the result's variables by name)."""
    if (inside.get("first_member"), inside.get("stop_member")) != (start, stop) or (
            end is not None and (inside.get("first_sample"), inside.get("stop_sample")) != (first, end)):
        return "holds other members than its name says"
    if inside.get("run_file_sha256") != run_file_sha256:
        return "is another run's"
    for name in save:
        found = sample_sum(arrays[name][start:stop, first:end], start, first)
        if inside.get(f"samples_sum_{name}") != f"{found:016x}":
            return f"its members' {name} in the result changed since it was written"
    return None


def segments_left(folder: Path) -> list[tuple[int, int, int]]:
    """(first member, stop member, samples done) of each member range with segment files in `folder`, from their
    names."""
    done: dict[tuple[int, int], int] = {}
    for path in folder.glob("segment-*.npz"):
        segment = Segment.of(path)
        if segment:
            done[segment.start, segment.stop] = max(done.get((segment.start, segment.stop), 0), segment.end)
    return [(start, stop, end) for (start, stop), end in sorted(done.items())]


class SegmentLog:
    """The finished segments of members start .. stop - 1 of a range being written by `owner` (a parts.PartWriter
    or a zarr_store.Region): each segment's end is saved as a segment file, and a resumed run continues from the
    last one of `paths` (the range's kept segments, checked) instead of from sample 0.

    The owner has `sums` (name: sample_sum of its saved variables so far), `segment_folder`, `run_file_sha256`,
    and `make_durable()`, which puts the samples written so far on the disk before a segment file says so."""

    STATE = ("works", "status", "failure_time", "counts", "event_times", "event_counts", "stopped",
             "event_states")  # Launch.state()

    def __init__(self, owner, start: int, stop: int, paths: list[Path]):
        self.owner, self.start, self.stop, self.paths = owner, start, stop, list(paths)

    def resumed(self, call, record) -> tuple[int, dict] | None:
        """Where the kept segments end, (sample, kernel state), with `record` (records.Record) and the owner's
        checksums restored to that point; None (and the segments deleted) when there are none, or when they are
        of another kernel layout than `call`'s."""
        kept = self.kept()
        if kept is None:
            return None
        if not call.takes(kept["state"]):
            self.restart()
            return None
        record.restore(kept["noise"], kept["amplitudes"], kept["errors"])
        return kept["sample"], kept["state"]

    def kept(self) -> dict | None:
        """What the kept segments leave to continue from, the owner's checksums restored to that point: "sample"
        (the first not done), "state" (launch.Launch.state()), "noise" (the noise streams' states), "amplitudes"
        and "errors" (a list of pieces, one per segment); None when there are none."""
        if not self.paths:
            return None
        loaded = [_load(path) for path in self.paths]
        for inside in (json.loads(str(d["inside"])) for d in loaded):
            for name in self.owner.sums:
                self.owner.sums[name] = (self.owner.sums[name] + int(inside[f"samples_sum_{name}"], 16)) % 2**64
        return {"sample": Segment.of(self.paths[-1]).end,
                "state": {name: loaded[-1][name] for name in self.STATE if name in loaded[-1]},
                "noise": json.loads(str(loaded[-1]["noise"])),
                "amplitudes": [d["amplitudes"] for d in loaded if "amplitudes" in d],
                "errors": [d["errors"] for d in loaded if "errors" in d]}

    def restart(self) -> None:
        """The range starts again from sample 0: its segments deleted, the owner's checksums zeroed."""
        self.discard()
        self.owner.sums = dict.fromkeys(self.owner.sums, 0)

    def save(self, first: int, data: dict[str, np.ndarray], state: dict[str, np.ndarray], record: dict) -> None:
        """Samples first, first + 1, ... of the members, just written as `data` (name: (members, samples, ...)),
        are finished: with the kernel's `state` and the record's (records.Record.state), a segment file says so,
        once the samples are on the disk."""
        end = first + len(next(iter(data.values()))[0])
        inside = {"first_member": self.start, "stop_member": self.stop, "first_sample": first, "stop_sample": end,
                  "run_file_sha256": self.owner.run_file_sha256,
                  **{f"samples_sum_{name}": f"{sample_sum(values, self.start, first):016x}"
                     for name, values in data.items()}}
        self.owner.make_durable()
        folder = self.owner.segment_folder
        folder.mkdir(exist_ok=True)
        name = f"segment-{self.start:012d}-{self.stop:012d}-{first:012d}-{end:012d}"
        file = io.BytesIO()
        np.savez(file, **state, **{k: v for k, v in record.items() if k != "noise"},
                 noise=np.array(json.dumps(record["noise"])), inside=np.array(json.dumps(inside)))
        data = file.getbuffer()  # no copy: a chunk's state may be tens of MB
        path = folder / f"{name}-{zlib.crc32(data):08x}.npz"
        write_atomically(path, data, durable=False)
        self.paths.append(path)

    def discard(self) -> None:
        for path in self.paths:
            path.unlink(missing_ok=True)
        self.paths = []


def _load(path: Path) -> dict[str, np.ndarray]:
    with path.open("rb") as file, np.load(file, allow_pickle=False) as data:
        return dict(data)


def segment_inside(path: Path) -> dict:
    """A segment file's own account of itself (see SegmentLog.save); empty when it cannot be read."""
    try:
        return json.loads(str(_load(path)["inside"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return {}
