"""Checksums of what a run keeps, and files written whole or not at all."""
from __future__ import annotations

import os
import zlib
from pathlib import Path

import numba
import numpy as np

from .places import is_remote
from .store import fsync_path


def sample_sum(values: np.ndarray, member: int, first: int) -> int:
    """A checksum of saved samples that does not depend on how they were cut into writes: the sum (mod 2^64) over
    every value of a 64-bit mix (splitmix64's) of its bits and its place (its member, then its index among that
    member's values). values: (members, samples, ...) of members member, member + 1, ... from sample `first`.
    A changed value, or a value moved to another place, changes the sum (but for a 2^-64 chance)."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    members = values.shape[0]
    per_sample = values[0, 0].size if values.size else 1
    return int(_mixed_sum(values.reshape(members, -1).view(np.uint64), member, first * per_sample))


def record_sum(values: np.ndarray, member: int) -> int:
    """sample_sum of a per-member variable (member, ...) of members member, member + 1, ..."""
    return sample_sum(np.asarray(values, dtype=np.float64).reshape(len(values), 1, -1), member, 0)


@numba.njit(cache=True, nogil=True)
def _mixed_sum(bits, member, offset):  # (members, values) uint64; the inner loop vectorizes: no temporaries
    total = np.uint64(0)
    for i in range(bits.shape[0]):
        base = np.uint64(member + i) * np.uint64(0xD6E8FEB86659FD93) + np.uint64(offset)  # odd: members apart
        for n in range(bits.shape[1]):
            x = bits[i, n] ^ ((base + np.uint64(n)) * np.uint64(0x9E3779B97F4A7C15))
            x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            total += x ^ (x >> np.uint64(31))
    return total


def file_crc32(path: Path) -> str:
    """The CRC-32 of a file's bytes, 8 hex digits."""
    crc = 0
    with path.open("rb") as file:
        for block in iter(lambda: file.read(2**20), b""):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def write_atomically(path: Path, data: bytes | memoryview, durable: bool = True) -> None:
    """Write `path` whole or not at all (a .tmp renamed); `durable`: on the disk before it is renamed, and the
    rename too (fsync). At a URL (ensemble.places) an object is put whole."""
    if is_remote(path):
        path.write_bytes(data)
        return
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "wb") as file:
        file.write(data)
        if durable:
            file.flush()
            os.fsync(file.fileno())
    os.replace(temporary, path)
    if durable:
        fsync_path(path.parent)
