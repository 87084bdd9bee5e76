"""Where a result goes: a path on this machine, or an fsspec URL (s3://, gs://, file://, memory://, ...) of a Zarr
store, reached through universal_pathlib's UPath, which answers the questions a pathlib.Path does (exists, glob,
read_bytes, unlink, ...) on any fsspec file system. A URL's place has no rename, no file lock and no free-space
figure: ensemble.zarr_store completes such a store by writing its root's metadata last."""
from __future__ import annotations

import re
from pathlib import Path

from .errors import EnsembleError

URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://")


def place(output: str | Path) -> Path:
    """The Path of `output`, or the UPath of a URL (the zarr extra: universal_pathlib and fsspec)."""
    if isinstance(output, Path) or not URL.match(str(output)):
        return Path(output)
    try:
        from upath import UPath
    except ImportError:
        raise EnsembleError(f"{output}: a URL output needs universal_pathlib; install it with pip install "
                            f"'ensemble[zarr]'") from None
    if UPath(output).protocol in ("file", "local"):  # folders made as files are written, as an object store's
        return UPath(output, auto_mkdir=True)          # prefixes are
    return UPath(output)


def is_remote(path) -> bool:
    """Whether `path` is a URL's UPath, reached through fsspec, rather than a path on this machine (or a str)."""
    if isinstance(path, (str, Path)):
        return False
    try:
        from upath import UPath
    except ImportError:
        return False
    return isinstance(path, UPath)


def remove_tree(path) -> None:
    """Delete the folder (or a URL's prefix) `path` and everything in it."""
    if is_remote(path):
        path.fs.rm(path.path, recursive=True)
    else:
        import shutil

        shutil.rmtree(path)


def zarr_location(path) -> tuple[str, dict]:
    """(what zarr opens, its storage options) for the store at `path`."""
    return (str(path), dict(path.storage_options)) if is_remote(path) else (str(path), {})
