"""A Zarr store as a run's output (issue 54): the NetCDF result's contract and bits; members written by the
process that computed them, a Dask worker included, each range leaving a receipt; a resume trusts the store only
where a receipt's checksums still hold; `ensemble convert` gives back the NetCDF file."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import netCDF4
import numpy as np
import pytest
import xarray as xr

import ensemble
from ensemble import cli, runner, zarr_store
from ensemble.errors import Incomplete
from ensemble.parts import folder_of
from ensemble.spec import load

from .conftest import run_without, top_runfile
from .test_resume import _interrupted, _killed, same_bits

zarr = pytest.importorskip("zarr")
SWEPT_TOPS = (top_runfile(members=60, t_end=2.0, save_dt=0.01, method=None) + "[observe]\nnoise = { tilt = 0.01 }\n"
              + '[sweep]\nmethod = ["rk4", "split2"]\n')  # NOISY_TOPS's, in two launches (a range may hold both)


def same_attributes(a: Path, b: Path) -> None:
    """Every variable's attributes equal, values and types, and the global ones but the history."""
    with xr.open_dataset(a) as x, xr.open_dataset(b) as y:
        for name in x.variables:
            assert x[name].attrs.keys() == y[name].attrs.keys(), name
            for key, value in x[name].attrs.items():
                np.testing.assert_array_equal(value, y[name].attrs[key], err_msg=f"{name}.{key}")
            assert x[name].encoding.get("_FillValue") is None or np.array_equal(
                x[name].encoding["_FillValue"], y[name].encoding.get("_FillValue"), equal_nan=True), name


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(run file of swept noisy tops, its NetCDF result, its Zarr store in sharded ranges of 8 members)."""
    folder = tmp_path_factory.mktemp("zarr")
    path = folder / "run.toml"
    path.write_text(SWEPT_TOPS)
    nc, store = folder / "ref.nc", folder / "ref.zarr"
    assert cli.main(["run", str(path), "-o", str(nc), "--quiet"]) == 0
    with pytest.MonkeyPatch.context() as patch:  # chunks of 4 members at most: a task's 8 are a shard of 2
        patch.setattr(zarr_store, "CHUNK_BYTES", 4 * 201 * 24)
        runner.run(load(path), store, chunk=8, progress=False)  # the command line would round 8 up to a block
    return path, nc, store


def test_a_store_holds_the_netcdf_results_bits_and_contract(reference):
    _, nc, store = reference
    same_bits(store, nc)
    same_attributes(store, nc)
    assert not Path(f"{store}.tmp").exists() and not folder_of(store).exists()
    group = zarr.open_consolidated(store, zarr_format=3)  # consolidated once, at the end
    for name, array in group.arrays():
        codecs = array.metadata.codecs
        inner = codecs[0].codecs if type(codecs[0]).__name__ == "ShardingCodec" else codecs
        assert any(type(c).__name__ == "Crc32cCodec" for c in inner), name
    assert group["omega"].shards[0] == 8 and group["omega"].chunks[0] == 4  # a task's range: a shard
    assert group["tilt"].shards is None and group["tilt"].chunks[0] == 8 == group["status"].chunks[0]  # fits a chunk
    with ensemble.open(store) as ds:
        assert ds.sizes["member"] == 120 and ds.attrs["members_written"] == 120


def test_a_chains_store_holds_its_per_site_variables(tmp_path, write_runfile):
    """Per-site parameters and samples (member, t, site), events' records (member, occurrence): the file's bits."""
    from .test_cluster import CHAIN

    path = write_runfile(CHAIN + '[events.turn]\nof = "v"\nindex = 1\ndirection = "down"\ncount = 2\n')
    assert cli.main(["run", str(path), "-o", str(tmp_path / "chain.nc"), "--quiet"]) == 0
    runner.run(load(path), tmp_path / "chain.zarr", chunk=8, progress=False)
    same_bits(tmp_path / "chain.zarr", tmp_path / "chain.nc")
    with xr.open_zarr(tmp_path / "chain.zarr") as ds:
        assert ds.x.dims == ("member", "t", "site") and ds.turn_time.dims == ("member", "turn")


def test_fit_reads_a_store_as_it_reads_the_file(reference, capsys):
    _, nc, store = reference
    said = []
    for result in (nc, store):
        assert cli.main(["fit", str(result)]) == 0
        said.append([line.replace(str(result), "RESULT") for line in capsys.readouterr().out.splitlines()
                     if not line.startswith("fits:")])
    assert said[0] == said[1] and len(said[0]) > 3


def test_convert_gives_the_file_a_netcdf_run_writes(reference, tmp_path, capsys):
    _, nc, store = reference
    out = tmp_path / "converted.nc"
    assert cli.main(["convert", str(store), str(out)]) == 0
    same_bits(out, nc)
    same_attributes(out, nc)
    with netCDF4.Dataset(nc) as x, netCDF4.Dataset(out) as y:
        for name in x.variables:
            assert x[name].chunking() == y[name].chunking() and x[name].dtype == y[name].dtype, name
        assert {k: type(x.getncattr(k)) for k in x.ncattrs()} == {k: type(y.getncattr(k)) for k in y.ncattrs()}
    capsys.readouterr()
    for argv in (["convert", str(store), str(out)], ["convert", str(nc), str(tmp_path / "x.nc")],
                 ["convert", str(store), str(tmp_path / "x.zarr")]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and err.startswith("ensemble: error: "), err


@pytest.mark.parametrize("sharded", [False, True])
def test_an_interrupted_run_resumes_where_the_receipts_hold(reference, tmp_path, monkeypatch, capsys, sharded):
    """Three ranges of 7 finished; one's tilt chunk (or shard) then tampered with (its CRC32C fails), another's
    omega chunk deleted (a torn write): both are computed again, the first kept, and the bits are a whole run's."""
    path, nc, _ = reference
    out = tmp_path / "out.zarr"
    if sharded:
        monkeypatch.setattr(zarr_store, "CHUNK_BYTES", 2 * 201 * 24)
    _interrupted(load(path), out, after=3, monkeypatch=monkeypatch)
    receipts = sorted(folder_of(out).glob("receipt-*.json"))
    assert [r.name for r in receipts] == [zarr_store.RECEIPT.format(j, j + 7) for j in (0, 7, 14)]
    inside = json.loads(receipts[0].read_text())
    assert inside["counts"]["members"] == 7 and set(inside["sums"]) >= {"tilt", "omega", "status"}
    store = Path(f"{out}.tmp")
    assert (zarr.open_group(store, mode="r")["omega"].shards is not None) == sharded
    chunk = store / "tilt" / "c" / "1" / "0"
    data = bytearray(chunk.read_bytes())
    data[8] ^= 1
    chunk.write_bytes(bytes(data))
    (store / "omega" / "c" / "2" / "0" / "0").unlink()
    calls = []
    real = runner.integrate_chunk
    monkeypatch.setattr(runner, "integrate_chunk", lambda *a, **k: calls.append(a[1:3]) or real(*a, **k))
    runner.run(load(path), out, chunk=3, progress=True, resume=True)  # the store's shards of 7 win
    assert calls[:2] == [(7, 14), (14, 21)] and (0, 7) not in calls
    said = capsys.readouterr().err.splitlines()[0]
    assert said.startswith("resuming: 7 of 120 members in 1 part(s) kept; dropped receipt-000000000007-"), said
    same_bits(out, nc)


def test_a_resume_of_another_run_file_is_refused(reference, tmp_path, monkeypatch, capsys):
    path, _, _ = reference
    changed = tmp_path / "changed.toml"
    changed.write_text(SWEPT_TOPS.replace("seed = 7", "seed = 8"))
    out = tmp_path / "out.zarr"
    _interrupted(load(path), out, after=1, monkeypatch=monkeypatch)
    capsys.readouterr()
    assert cli.main(["run", str(changed), "-o", str(out), "--quiet", "--resume"]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "(run_file_sha256, members_sha256 differ)" in line, line
    assert len(list(folder_of(out).glob("receipt-*.json"))) == 1


def test_a_record_in_segments_is_written_as_its_segments_come(reference, client, tmp_path, monkeypatch):
    """A block's record too long for a chunk's memory runs in segments: each segment is written into its own
    chunks as it comes (here, and on the cluster: a task writes its range's segments itself)."""
    path, nc, _ = reference
    monkeypatch.setattr(runner, "CHUNK_BYTES", 2**19)
    spec = load(path)
    segment = runner.segment_samples(spec)
    assert 1 < segment < spec.n_save
    for where, on in (("here", None), ("cluster", client)):
        out = tmp_path / f"{where}.zarr"
        runner.run(spec, out, chunk=8, progress=False, client=on)
        same_bits(out, nc)
        assert zarr.open_group(out, mode="r")["tilt"].chunks == (8, segment)


def test_without_zarr_a_store_says_how_to_install_it(tmp_path, write_runfile):
    path = write_runfile(top_runfile())
    done = run_without("zarr", ["run", str(path), "-o", str(tmp_path / "out.zarr")])
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "pip install 'ensemble[zarr]'" in done.stderr and not list(tmp_path.glob("out.zarr*"))


def test_receipts_whose_store_is_lost_are_dropped(reference, tmp_path, monkeypatch, capsys):
    path, nc, _ = reference
    out = tmp_path / "lost.zarr"
    _interrupted(load(path), out, after=2, monkeypatch=monkeypatch)
    zarr_store.remove_store(Path(f"{out}.tmp"))
    runner.run(load(path), out, chunk=7, progress=True, resume=True)
    said = capsys.readouterr().err.splitlines()[0]
    assert said.startswith("resuming: 0 of 120 members in 0 part(s) kept; dropped receipt-000000000000-"), said
    assert "(the store it vouches for is missing)" in said
    same_bits(out, nc)


def test_sigkill_of_the_client_then_resume(tmp_path, write_runfile):
    """A real run killed after some ranges (the store half written), resumed: the bits of a whole run."""
    path = write_runfile(top_runfile(members=300, t_end=0.2, save_dt=0.01))
    expected, out = tmp_path / "expected.nc", tmp_path / "out.zarr"
    one_by_one = [sys.executable, "-c", "import sys; from ensemble import runner; from ensemble.spec import load; "
                  "runner.run(load(sys.argv[1]), sys.argv[2], chunk=1, progress=False)", str(path), str(out)]
    subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "--quiet", "-o", str(expected)], check=True)
    _killed(one_by_one, lambda: len(list(folder_of(out).glob("receipt-*.json"))) >= 20)
    assert not out.exists() and Path(f"{out}.tmp").exists()
    subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "--quiet", "-o", str(out), "--resume"],
                   check=True)
    same_bits(out, expected)


distributed = pytest.importorskip("distributed")  # the tests below use conftest's `client`


def _dies_on(marker: Path, start: int, spec, j0, j1, repeats, *, out, always=False):
    """zarr_task into `out`, but its worker process dies the first time (or every time) it gets member `start`."""
    if j0 == start and (always or not marker.exists()):
        marker.touch()
        os._exit(1)
    return runner.zarr_task(spec, j0, j1, repeats, store=Path(f"{out}.tmp").resolve(),
                            folder=zarr_store.segments_folder(out).resolve(), segment=spec.n_save)


def test_workers_write_the_store_and_the_client_only_receipts(reference, client, tmp_path, monkeypatch):
    """The client process never writes a region (the workers do), a worker killed mid-task has its range written
    again by another, and the store holds the bits of a local run."""
    path, nc, _ = reference
    out = tmp_path / "remote.zarr"

    def refused(*args, **kwargs):
        raise AssertionError("the client wrote members")

    monkeypatch.setattr(zarr_store.Region, "__init__", refused)
    task = partial(_dies_on, tmp_path / "died", 14, out=out)
    runner.run(load(path), out, chunk=7, progress=False, client=client, task=task)
    assert (tmp_path / "died").exists()
    same_bits(out, nc)
    monkeypatch.undo()
    again = tmp_path / "plain.zarr"
    runner.run(load(path), again, chunk=7, progress=False, client=client)
    same_bits(again, nc)


def test_a_worker_that_does_not_see_the_store_is_refused(reference, client, tmp_path, monkeypatch):
    """Each worker reads a probe file the client wrote beside the store: one that reads something else (another
    file system under the same path) stops the run before anything is computed, in one line."""
    path, _, _ = reference
    out = tmp_path / "blind.zarr"
    real = Path.write_text
    monkeypatch.setattr(Path, "write_text", lambda self, text, *a, **k: real(self, "elsewhere", *a, **k)
                        if self.name.startswith("probe-") else real(self, text, *a, **k))
    with pytest.raises(ensemble.cluster.ClusterError, match=r"cannot read .*blind\.zarr\.parts; give an output on a "
                                                             r"path or URL every worker shares"):
        runner.run(load(path), out, chunk=7, progress=False, client=client)
    assert not Path(f"{out}.tmp").exists() and not folder_of(out).exists()


def test_a_run_stopped_here_resumes_on_the_cluster_whose_workers_check_the_receipts(reference, client, tmp_path,
                                                                                   monkeypatch, capsys):
    path, nc, _ = reference
    out = tmp_path / "moved.zarr"
    _interrupted(load(path), out, after=3, monkeypatch=monkeypatch)
    chunk = Path(f"{out}.tmp") / "steps_accepted" / "c" / "2"  # the third range's: a record's chunk
    data = bytearray(chunk.read_bytes())
    data[0] ^= 1
    chunk.write_bytes(bytes(data))

    here, real = os.getpid(), zarr_store.checked_sums

    def on_workers_only(*args):  # sent to the workers by value
        assert os.getpid() != here, "the client read the store"
        return real(*args)

    monkeypatch.setattr(zarr_store, "checked_sums", on_workers_only)
    runner.run(load(path), out, chunk=5, progress=True, resume=True, client=client)
    said = capsys.readouterr().err.splitlines()[0]
    assert said.startswith("resuming: 14 of 120 members in 2 part(s) kept; dropped receipt-000000000014-"), said
    same_bits(out, nc)


def test_a_range_that_keeps_failing_is_named_and_resume_completes_it(reference, client, tmp_path):
    path, nc, _ = reference
    out = tmp_path / "failing.zarr"
    task = partial(_dies_on, tmp_path / "died", 21, out=out, always=True)
    with pytest.raises(Incomplete, match=r"members (.*, )?21..27(, .*)? were not computed") as failure:
        runner.run(load(path), out, chunk=7, progress=False, client=client, task=task)
    failed = failure.value.ranges  # a range queued on the worker that died with it may be blamed too
    assert (21, 28) in failed and len(failed) <= 3
    assert not out.exists() and len(list(folder_of(out).glob("receipt-*.json"))) == 18 - len(failed)
    runner.run(load(path), out, chunk=7, progress=False, client=client, resume=True)
    same_bits(out, nc)


def test_the_clients_memory_does_not_grow_with_the_members(tmp_path):
    """Issue 54, item 8: reading a run file of 10^9 members, its fingerprint and its store's template take the
    memory those of 10^6 take, and the template holds no member's values (each range draws, checks and writes
    its own where it runs)."""
    import tracemalloc

    from ensemble.parts import fingerprint
    from ensemble.spec import parse

    peaks = {}
    for members in (10**6, 10**9, 10**6):  # the first of 10^6 warms the imports and caches
        tracemalloc.start()
        spec = parse(top_runfile(members=members, save=["tilt"]), "run.toml")
        fingerprint(spec)
        store = tmp_path / f"{members}-{len(peaks)}.zarr"
        zarr_store.create(store, spec, None, (4096, spec.n_save))
        peaks[members] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks[10**9] < 1.1 * peaks[10**6] + 2**20, peaks
    group = zarr.open_group(store, mode="r")
    assert group["tilt0"].shape == (10**6,) and group["member"].nchunks_initialized == 0
    assert group["tilt"].nchunks_initialized == 0 and group["t"].nchunks_initialized == 1


def test_a_bad_member_found_by_a_worker_stops_the_run_in_one_line(client, tmp_path, monkeypatch):
    """A member that the checks before the start do not reach (here: past the first 16) and that breaks the
    scene's constraints stops a cluster run as soon as its task meets it: one line naming the parameter and the
    members' range, and nothing is left (no resume could use what was done: the run file must change)."""
    from ensemble import members
    from ensemble.spec import SpecError, parse

    tilt0 = np.full(64, 0.1)
    tilt0[40] = -0.1
    np.save(tmp_path / "tilt0.npy", tilt0)
    path = tmp_path / "run.toml"
    path.write_text(top_runfile(members=64, parameters={"tilt0": {"file": "tilt0.npy"}}))
    monkeypatch.setattr(members, "CHECKED_BEFORE_START", 16)
    spec = load(path)
    out = tmp_path / "bad.zarr"
    with pytest.raises(SpecError, match=r"^parameters\.tilt0: must lie in \[0, pi\] \(among members 32 to 47, met "
                                        r"as they were integrated"):
        runner.run(spec, out, chunk=16, progress=False, client=client)
    assert not list(tmp_path.glob("bad.zarr*"))
    monkeypatch.undo()
    with pytest.raises(SpecError, match=r"^parameters\.tilt0: must lie in \[0, pi\]$"):
        parse(path.read_text(), str(path))  # every member of a run this small is checked before the start


def test_a_long_record_stopped_here_continues_on_the_cluster_from_its_last_good_segment(client, tmp_path,
                                                                                       write_runfile, monkeypatch):
    """A range whose record runs in segments, stopped after its fifth segment here, continues on the cluster from
    its segment files: the worker that takes the range checks them against the store first, so the third
    segment, whose tilt chunk got a flipped byte, is dropped with those after it. The workers compute only the
    segments missing (2 x 51 - 2), and the store holds the bits of one uninterrupted run."""
    from .test_long_members import NOISY_GROWING, _interrupted_after

    monkeypatch.setattr(runner, "CHUNK_BYTES", 20_000)  # records in segments of 2 samples
    spec = load(write_runfile(NOISY_GROWING))
    assert runner.segment_samples(spec) == 2 and spec.n_save == 101
    whole, out = tmp_path / "whole.nc", tmp_path / "long.zarr"
    runner.run(spec, whole, progress=False)
    _interrupted_after(spec, out, 5, monkeypatch)
    assert len(list(zarr_store.segments_folder(out).glob("segment-*.npz"))) == 5
    chunk = Path(f"{out}.tmp") / "tilt" / "c" / "0" / "2"  # samples 4 and 5 of the range's members
    data = bytearray(chunk.read_bytes())
    data[0] ^= 1
    chunk.write_bytes(bytes(data))

    def count_adds():  # on each worker: count the segments its records add
        from ensemble import records

        records.real_add, records.added = records.Record.add, []
        records.Record.add = lambda self, start, samples: records.added.append(start) or records.real_add(
            self, start, samples)

    def counted():
        from ensemble import records

        records.Record.add = records.real_add
        return len(records.added)

    client.run(count_adds)
    try:
        runner.run(spec, out, progress=False, resume=True, client=client)
    finally:
        added = sum(client.run(counted).values())
    assert added == 2 * 51 - 2
    same_bits(out, whole)
    assert not folder_of(out).exists()


def test_a_stores_disk_check_counts_no_copy_of_the_records(tmp_path, monkeypatch):
    """A NetCDF run keeps a copy of its records in its parts until the end; a Zarr run keeps receipts of a few
    hundred bytes: a disk with room for the result alone takes the store and refuses the file."""
    import shutil

    from ensemble import preflight, store
    from ensemble.spec import parse

    spec = parse(top_runfile(members=10_000))
    free = shutil.disk_usage(tmp_path)._replace(free=store.output_bytes(spec) + 4096)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: free)
    assert preflight.space_problem(tmp_path / "out.zarr", spec) is None
    assert "the result needs about" in preflight.space_problem(tmp_path / "out.nc", spec)
