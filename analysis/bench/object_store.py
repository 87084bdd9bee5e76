"""Check: a Dask run into an S3 bucket (moto's S3 server on localhost), killed and resumed, gives the file's bits.

    pip install "moto[server]" s3fs   # besides ensemble[zarr,dask]
    python analysis/bench/object_store.py [--members 10000] [--workers 2]

Starts `moto_server` and a scheduler with N single-threaded worker processes (client_bytes.cluster), every one
with the bucket's address and test credentials in its environment, as a real cluster has them. Runs the top
sweep of client_bytes.py (tilt and omega every 2 ms for 3 s) into a NetCDF file here and into
s3://runs/sweep.zarr with `--scheduler`: the bytes the client received and the walls. Then runs it again into a
second store, SIGKILLs the client once a third of its ranges have receipts in the bucket, and finishes it with
`--resume`. Prints whether both stores hold the file's bits (every variable; attributes but the history).
"""
from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import xarray as xr
from client_bytes import cluster, measured, sweep
from hostinfo import host

import ensemble
from ensemble.places import place
from ensemble.spec import load
from ensemble.zarr_store import task_members

BUCKET = "runs"


def moto(port: int) -> subprocess.Popen:
    """moto's S3 server on localhost:`port`, with the bucket made."""
    server = subprocess.Popen(["moto_server", "-p", str(port)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    import s3fs

    for _ in range(100):
        try:
            s3fs.S3FileSystem(skip_instance_cache=True).mkdir(BUCKET)
            return server
        except OSError:
            time.sleep(0.1)
    raise SystemExit("moto_server did not start")


def same_bits(url: str, nc: Path) -> bool:
    with ensemble.open(url) as x, xr.open_dataset(nc) as y:
        return set(x.variables) == set(y.variables) and all(
            x[v].values.tobytes() == y[v].values.tobytes() for v in y.variables) and {
            k: v for k, v in x.attrs.items() if k != "history"} == {k: v for k, v in y.attrs.items() if k != "history"}


def killed_and_resumed(runfile: Path, url: str, scheduler: str, ranges: int) -> float:
    """Run into `url`, SIGKILL the client once a third of `ranges` have receipts, resume; the resume's wall."""
    import s3fs

    command = [sys.executable, "-m", "ensemble", "run", str(runfile), "-o", url, "--quiet", "--scheduler", scheduler]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL)
    receipts = f"{url.removeprefix('s3://')}.parts/receipt-*"
    bucket = s3fs.S3FileSystem(skip_instance_cache=True)
    while len(bucket.glob(receipts)) < max(1, ranges // 3) and process.poll() is None:
        time.sleep(0.05)
    if process.poll() is not None:
        raise SystemExit("the run ended before it could be killed")
    process.send_signal(signal.SIGKILL)
    process.wait()
    print(f"killed after {len(bucket.glob(receipts))} receipts")
    began = time.perf_counter()
    subprocess.run([*command, "--resume"], check=True)
    return time.perf_counter() - began


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--members", type=int, default=10000)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    print(host())
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    os.environ.update({"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                       "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"})
    server = moto(port)
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        runfile = sweep(folder, args.members)
        address, started = cluster(folder, args.workers)
        try:
            nc, url = folder / "out.nc", f"s3://{BUCKET}/sweep.zarr"
            for out in (nc, url):
                m = measured(runfile, out, address, folder)
                print(f"{out}: client received {m['received'] / 1e6:.3f} MB on sockets, wall {m['wall']:.2f} s")
            print(f"{url} holds the file's bits: {same_bits(url, nc)}")
            spec = load(runfile)
            ranges = -(-spec.n_members // task_members(place(url), spec))
            again = f"s3://{BUCKET}/killed.zarr"
            wall = killed_and_resumed(runfile, again, address, ranges)
            print(f"{again}: resumed in {wall:.2f} s; holds the file's bits: {same_bits(again, nc)}")
        finally:
            for process in [*started[::-1], server]:
                process.terminate()
                process.wait()


if __name__ == "__main__":
    main()
