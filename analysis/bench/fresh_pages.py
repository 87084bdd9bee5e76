"""What writing a new file costs this host, by how recently its memory was last used.

    python analysis/bench/fresh_pages.py [--mb 680] [--pause 5] [--repeats 3]

A run writes its samples into new pages of the system's page cache. On a
virtual machine whose host takes back the memory its guest frees (virtio-balloon
free page reporting), a page freed a few seconds ago must be backed again by
the host at its first touch, which costs several times the copy. This writes
--mb MB (a 262,144-top run's samples are 680 MB) to a new file in the system's
temporary folder, deletes it, and times writing it again: right after
("recycled": the pages the deletion freed) and after --pause seconds idle
("after a pause"). Medians of --repeats; each write is flushed to the page
cache, not to the disk.

Then the price of what a run does after each chunk (store.fsync_path with
release: fsync, then let the system drop the file's cached pages, so that the
next chunk writes into pages just freed): reading the file back right after
it is written and fsynced, from the page cache, and after its pages were
released (from the disk, or the host's cache of it); and deleting it once it
is on the disk, as `--force` replaces an earlier result (a filesystem mounted
with `discard` trims the file's blocks then).
"""
from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int
from ensemble.store import fsync_path

CHUNK = 16 << 20  # bytes per write call


def write_file(path: Path, data: np.ndarray, total: int) -> None:
    """Write `total` bytes of `data` (CHUNK bytes a call) into the new file `path`."""
    with open(path, "xb", buffering=0) as file:
        for _ in range(total // CHUNK):
            file.write(data)


def write_seconds(path: Path, data: np.ndarray, total: int) -> float:
    """Seconds to write the new file `path` (write_file), which is deleted afterwards."""
    start = time.perf_counter()
    write_file(path, data, total)
    seconds = time.perf_counter() - start
    path.unlink()
    return seconds


def read_seconds(path: Path, data: np.ndarray, total: int, release: bool) -> tuple[float, float]:
    """Seconds to read back the new file `path` of `total` bytes right after writing and fsyncing it (with
    `release`, fsync_path's release of its cached pages), and then to delete it."""
    write_file(path, data, total)
    fsync_path(path, release=release)
    start = time.perf_counter()
    with open(path, "rb", buffering=0) as file:
        buffer = bytearray(CHUNK)
        while file.readinto(buffer):
            pass
    middle = time.perf_counter()
    path.unlink()
    return middle - start, time.perf_counter() - middle


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mb", type=positive_int, default=680, help="megabytes per write (default 680)")
    parser.add_argument("--pause", type=positive_int, default=5, help="seconds idle before a write (default 5)")
    parser.add_argument("--repeats", type=positive_int, default=3)
    args = parser.parse_args(argv)
    print(host())
    data = np.random.default_rng(0).random(CHUNK // 8)
    total = args.mb * (1 << 20) // CHUNK * CHUNK
    recycled, paused, cached, released, deleted = [], [], [], [], []
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fresh_pages.bin"
        write_seconds(path, data, total)  # untimed: whatever the memory's state at the start
        for _ in range(args.repeats):
            recycled.append(write_seconds(path, data, total))
            time.sleep(args.pause)
            paused.append(write_seconds(path, data, total))
            for release, reads in ((False, cached), (True, released)):
                read, delete = read_seconds(path, data, total, release)
                reads.append(read)
                deleted.append(delete)
    mb = total / (1 << 20)
    print(f"writing {mb:.0f} MB to a new file: {statistics.median(recycled):.3f} s with recycled pages, "
          f"{statistics.median(paused):.3f} s after {args.pause} s idle (medians of {args.repeats}; "
          f"ratio {statistics.median(paused) / statistics.median(recycled):.1f})")
    print(f"reading it back right after writing and fsyncing it: {statistics.median(cached):.3f} s from the page "
          f"cache, {statistics.median(released):.3f} s once its pages were released (medians of {args.repeats})")
    print(f"deleting it once on the disk: {statistics.median(deleted):.3f} s (median of {len(deleted)})")


if __name__ == "__main__":
    main()
