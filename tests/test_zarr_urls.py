"""A Zarr store at an fsspec URL (issue 54, item 4): written where it will stay (an object store has no rename),
its root metadata last, so that an unfinished store opens as none; resumed from receipts kept beside it at the
URL; written by a cluster's workers when each sees the URL, refused in one line when one does not. file:// URLs
go through fsspec as an object store's would; memory:// is a file system only its own process sees."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import xarray as xr

import ensemble
from ensemble import cli, runner, zarr_store
from ensemble.api import NotAResult
from ensemble.spec import load

from .conftest import top_runfile
from .test_resume import _interrupted, _killed, same_bits
from .test_zarr import SWEPT_TOPS

zarr = pytest.importorskip("zarr")
upath = pytest.importorskip("upath")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(run file of swept noisy tops, its NetCDF result)."""
    folder = tmp_path_factory.mktemp("urls")
    path = folder / "run.toml"
    path.write_text(SWEPT_TOPS)
    assert cli.main(["run", str(path), "-o", str(folder / "ref.nc"), "--quiet"]) == 0
    return path, folder / "ref.nc"


def test_a_store_at_a_url_holds_the_files_bits_and_is_read_as_a_path_is(reference, tmp_path, capsys):
    path, nc = reference
    url = f"file://{tmp_path}/store/out.zarr"  # a folder that does not exist yet: made as files are written
    assert cli.main(["run", str(path), "-o", url, "--quiet"]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {url}: 120 members")
    same_bits(url, nc)
    assert sorted(p.name for p in (tmp_path / "store").iterdir()) == ["out.zarr"]  # no .tmp, no receipts left
    with xr.open_zarr(url) as ds:  # consolidated, as a Pangeo user opens it
        assert ds.attrs["members_written"] == 120
    assert cli.main(["fit", url]) == 0 and (tmp_path / "store" / "out_tilt_decay.nc").is_file()  # beside it
    assert cli.main(["convert", url, str(tmp_path / "converted.nc")]) == 0
    with xr.open_dataset(tmp_path / "converted.nc") as x, xr.open_dataset(nc) as y:
        assert all(x[name].values.tobytes() == y[name].values.tobytes() for name in y.variables)
    capsys.readouterr()
    assert cli.main(["run", str(path), "-o", url, "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == (f"ensemble: error: {url}: exists; use --force to replace it (at a "
                                               f"URL, the old store is deleted when the run starts)")
    assert cli.main(["run", str(path), "-o", url, "--quiet", "--force"]) == 0
    same_bits(url, nc)


def test_an_unfinished_store_at_a_url_opens_as_none_and_resumes_from_its_receipts(reference, tmp_path, monkeypatch,
                                                                                capsys):
    """Three ranges of 7 finished, then interrupted: the store has no root metadata (xarray and ensemble.open find
    no store), a new run without --resume is sent to --resume or --force, a range's tampered chunk is computed
    again, and the resumed store holds the bits of a whole run."""
    path, nc = reference
    url = f"memory://{tmp_path.name}/out.zarr"
    _interrupted(load(path), url, after=3, monkeypatch=monkeypatch)
    root = upath.UPath(url)
    receipts = sorted(p.name for p in root.with_name("out.zarr.parts").glob("receipt-*.json"))
    assert len(receipts) == 3 and not (root / "zarr.json").exists()
    with pytest.raises((OSError, ValueError, KeyError)):
        xr.open_zarr(url)
    with pytest.raises(NotAResult):
        ensemble.open(url)
    capsys.readouterr()
    assert cli.main(["run", str(path), "-o", url, "--quiet"]) == 2
    said = capsys.readouterr().err.strip()
    assert "\n" not in said and "holds the parts of an unfinished run; add --resume" in said, said
    chunk = root / "tilt" / "c" / "1" / "0"  # the second range's (chunks of 7 members)
    data = bytearray(chunk.read_bytes())
    data[8] ^= 1
    chunk.write_bytes(bytes(data))
    runner.run(load(path), url, chunk=3, progress=True, resume=True)
    said = capsys.readouterr().err.splitlines()[0]
    assert said.startswith("resuming: 14 of 120 members in 2 part(s) kept; dropped receipt-000000000007-"), said
    same_bits(url, nc)
    assert not root.with_name("out.zarr.parts").exists()
    assert json.loads((root / "zarr.json").read_text())["consolidated_metadata"] is not None


def test_a_url_run_killed_while_its_template_is_made_leaves_no_result_and_resumes(reference, tmp_path):
    """Killed between the template's arrays and its root's removal: the root is there, but without the result's
    attributes (an object store's arrays take seconds to make), so it opens as no result; --resume starts it
    over and gives the file's bits."""
    from ensemble.places import place

    path, nc = reference
    url = f"memory://{tmp_path.name}/out.zarr"
    spec = load(path)
    zarr_store.Receipts(place(url), spec)  # the run's manifest, as the killed run left it
    zarr_store.create(place(url), spec, None, (7, spec.n_save), attributes=False)
    with pytest.raises(NotAResult, match="is not a result of `ensemble run`"), pytest.warns(RuntimeWarning,
                                                                                           match="consolidated"):
        ensemble.open(url)
    assert not zarr_store.exists(place(url))  # ours, unfinished: --resume, not --force, continues it
    runner.run(spec, url, chunk=7, progress=False, resume=True)
    same_bits(url, nc)


def test_a_store_in_s3_resumes_from_its_receipts_there(reference, tmp_path, monkeypatch):
    """An S3 bucket (moto's server, where moto and s3fs are installed; the test extras leave them out): a run
    stopped after three ranges leaves no root metadata, and its resume gives the bits of the file."""
    moto_server = pytest.importorskip("moto.server")
    s3fs = pytest.importorskip("s3fs")
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        for name, value in (("AWS_ACCESS_KEY_ID", "testing"), ("AWS_SECRET_ACCESS_KEY", "testing"),
                            ("AWS_DEFAULT_REGION", "us-east-1"), ("AWS_ENDPOINT_URL", f"http://{host}:{port}")):
            monkeypatch.setenv(name, value)
        s3fs.S3FileSystem.clear_instance_cache()
        s3fs.S3FileSystem().mkdir("runs")
        path, nc = reference
        url = "s3://runs/sweep/out.zarr"
        _interrupted(load(path), url, after=3, monkeypatch=monkeypatch)
        assert len(list(upath.UPath(f"{url}.parts").glob("receipt-*.json"))) == 3
        assert not upath.UPath(url, "zarr.json").exists()
        runner.run(load(path), url, chunk=7, progress=False, resume=True)
        same_bits(url, nc)
        assert not upath.UPath(f"{url}.parts").exists()
    finally:
        s3fs.S3FileSystem.clear_instance_cache()
        server.stop()


def test_sigkill_of_a_run_writing_a_url_then_resume(tmp_path, write_runfile):
    """A real run into a file:// URL killed after some ranges (the store half written, without its root), resumed
    from the command line: the bits of an uninterrupted run."""
    path = write_runfile(top_runfile(members=300, t_end=0.2, save_dt=0.01))
    expected, url = tmp_path / "expected.nc", f"file://{tmp_path}/out.zarr"
    one_by_one = [sys.executable, "-c", "import sys; from ensemble import runner; from ensemble.spec import load; "
                  "runner.run(load(sys.argv[1]), sys.argv[2], chunk=1, progress=False)", str(path), url]
    subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "--quiet", "-o", str(expected)], check=True)
    _killed(one_by_one, lambda: len(list((tmp_path / "out.zarr.parts").glob("receipt-*.json"))) >= 20)
    assert (tmp_path / "out.zarr" / "status").is_dir() and not (tmp_path / "out.zarr" / "zarr.json").exists()
    subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "--quiet", "-o", url, "--resume"],
                   check=True)
    same_bits(url, expected)


distributed = pytest.importorskip("distributed")  # the test below uses conftest's `client`


def test_workers_write_a_store_at_a_url_they_see_and_refuse_one_they_do_not(reference, client, tmp_path,
                                                                             monkeypatch):
    """A file:// URL every worker process sees: a run stopped here after three ranges is resumed on the cluster,
    whose workers check the receipts kept at the URL and write the rest, the bits of a local run. A memory:// URL
    lives in the client's process alone: the probe finds that before anything runs, and nothing is left."""
    path, nc = reference
    url = f"file://{tmp_path}/shared.zarr"
    _interrupted(load(path), url, after=3, monkeypatch=monkeypatch)
    runner.run(load(path), url, chunk=7, progress=False, resume=True, client=client)
    same_bits(url, nc)
    private = f"memory://{tmp_path.name}/private.zarr"
    with pytest.raises(ensemble.cluster.ClusterError, match=r"^memory://.*private\.zarr: worker tcp://\S+ cannot "
                                                           r"read .*private\.zarr\.parts; give an output on a path "
                                                           r"or URL every worker shares$"):
        runner.run(load(path), private, chunk=7, progress=False, client=client)
    assert not upath.UPath(private).exists() and not upath.UPath(f"{private}.parts").exists()


def test_a_url_that_cannot_take_a_result_is_refused_in_one_line(tmp_path, write_runfile, monkeypatch, capsys):
    """A NetCDF file at a URL, a scheme fsspec does not know, a store that cannot be reached: one line, exit status
    2, nothing made (a Path would have made a folder named after the scheme)."""
    from ensemble.preflight import RunRefused

    monkeypatch.chdir(tmp_path)
    path = write_runfile(top_runfile())
    for url, why in (("file:///tmp/run.nc", "a URL takes a Zarr store (OUT.zarr); a NetCDF result is written to a "
                                            "path"),
                     ("nosuch://bucket/run.zarr", "Unsupported filesystem: 'nosuch'")):
        assert cli.main(["run", str(path), "-o", url]) == 2
        assert capsys.readouterr().err.strip() == f"ensemble: error: {url}: {why}"
    with pytest.raises(RunRefused, match=r"^gs://b/run\.nc: a URL takes a Zarr store"):
        ensemble.run(path, "gs://b/run.nc", progress=False)

    def denied(out):
        raise PermissionError("Access Denied")

    monkeypatch.setattr(zarr_store, "exists", denied)  # as an object store without the credentials
    url = f"memory://{tmp_path.name}/run.zarr"
    assert cli.main(["run", str(path), "-o", url]) == 2
    assert capsys.readouterr().err.strip() == (f"ensemble: error: {url}: cannot be reached (PermissionError: "
                                               f"Access Denied)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"] and not upath.UPath(url).parent.exists()
