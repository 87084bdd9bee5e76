"""Sweeps on a Dask cluster (issue 16): a LocalCluster of two worker processes gives the bits of a local run; a
worker killed mid-task has its chunk computed elsewhere; chunks that keep failing leave the rest done, are
named, and --resume completes them; mismatched versions and a missing dask are refused in one line."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from ensemble import cli, cluster, runner
from ensemble.errors import Incomplete
from ensemble.parts import folder_of
from ensemble.spec import load

from .conftest import run_without, top_runfile
from .test_resume import NOISY_TOPS, same_bits

distributed = pytest.importorskip("distributed")
CHAIN = """scene = "chain"
method = "verlet"
dt = 0.01
t_end = 1.0
save_dt = 0.1
members = 30
seed = 3
[parameters]
n = 4
boundary = "fixed"
m = { loguniform = [0.5, 2.0] }
k = 1.0
x0 = { normal = [0.0, 0.1] }
v0 = 0.0
"""


@pytest.mark.parametrize("text", [NOISY_TOPS, CHAIN], ids=["noisy tops", "chain"])
def test_two_workers_give_the_bits_of_a_local_run(client, tmp_path, write_runfile, text):
    path = write_runfile(text)
    local, remote = tmp_path / "local.nc", tmp_path / "remote.nc"
    assert cli.main(["run", str(path), "-o", str(local), "--quiet"]) == 0
    runner.run(load(path), remote, chunk=7, progress=False, client=client)
    same_bits(remote, local)


def _dies_on(marker, start: int, always: bool = False):
    """A chunk task whose worker process dies when it gets member `start` (once, or every time)."""
    def task(spec, j0, j1, repeats):
        if j0 == start and (always or not marker.exists()):
            marker.touch()
            os._exit(1)
        return runner.chunk_task(spec, j0, j1, repeats)
    return task


def test_a_worker_killed_mid_task_has_its_chunk_computed_again(client, tmp_path, write_runfile):
    path = write_runfile(NOISY_TOPS)
    local, remote = tmp_path / "local.nc", tmp_path / "remote.nc"
    assert cli.main(["run", str(path), "-o", str(local), "--quiet"]) == 0
    runner.run(load(path), remote, chunk=7, progress=False, client=client, task=_dies_on(tmp_path / "died", 14))
    assert (tmp_path / "died").exists()
    same_bits(remote, local)


def test_a_chunk_that_keeps_failing_is_named_and_resume_completes_it(client, tmp_path, write_runfile):
    path = write_runfile(NOISY_TOPS)
    local, remote = tmp_path / "local.nc", tmp_path / "remote.nc"
    assert cli.main(["run", str(path), "-o", str(local), "--quiet"]) == 0
    with pytest.raises(Incomplete, match=r"members (.*, )?21..27(, .*)? were not computed") as failure:
        runner.run(load(path), remote, chunk=7, progress=False, client=client,
                   task=_dies_on(tmp_path / "died", 21, always=True))
    # a chunk queued on a worker that died with it may be blamed too (Dask's suspicious tasks)
    failed = failure.value.ranges
    assert (21, 28) in failed and len(failed) <= 3 and "KilledWorker" in failure.value.cause
    assert not remote.exists() and len(list(folder_of(remote).glob("members-*.nc"))) == 9 - len(failed)
    runner.run(load(path), remote, chunk=7, progress=False, client=client, resume=True)
    same_bits(remote, local)


def test_a_long_member_resumes_from_its_last_segment_on_the_cluster(client, tmp_path, write_runfile, monkeypatch):
    """Issue 50, item 9: on a cluster, records run in segments are computed a segment per task, and the client
    saves each finished one (parts.SegmentLog) before the next task continues it. Stopped after 20 segments
    (here, the client), the run resumes on the cluster from its last segment, with noise and growth along, to
    the bits of a local run; the resume computes only the segments still missing."""
    from ensemble import parts

    from .test_long_members import NOISY_GROWING

    monkeypatch.setattr(runner, "CHUNK_BYTES", 20_000)  # segments of 2 samples: 51 per group of members
    path = write_runfile(NOISY_GROWING)
    spec = load(path)
    assert runner.segment_samples(spec) == 2 and spec.n_save == 101
    local, remote = tmp_path / "local.nc", tmp_path / "remote.nc"
    runner.run(spec, local, progress=False)
    real, saved, stop_after = parts.SegmentLog.save, [], [20]

    def save(self, *args):
        real(self, *args)
        saved.append(args[0])
        if len(saved) == stop_after[0]:
            raise KeyboardInterrupt

    monkeypatch.setattr(parts.SegmentLog, "save", save)
    with pytest.raises(KeyboardInterrupt):
        runner.run(spec, remote, progress=False, client=client)
    kept = len(list(folder_of(remote).glob("segment-*.npz")))
    assert kept == 20 and not remote.exists()
    saved.clear()
    stop_after[0] = None
    runner.run(spec, remote, progress=False, client=client, resume=True)
    assert len(saved) == 2 * 51 - kept
    same_bits(remote, local)
    assert not folder_of(remote).exists()


def test_workers_with_other_versions_are_refused(client, monkeypatch):
    monkeypatch.setattr(cluster, "__version__", "0.0.1")  # this process claims another ensemble than the workers
    with pytest.raises(cluster.ClusterError, match=r"has ensemble .* \(here 0.0.1\); install the same versions"):
        cluster._check_versions(client, "test")


def test_an_unreachable_scheduler_is_one_line(monkeypatch):
    monkeypatch.setattr(cluster, "CONNECT_SECONDS", 1)
    with pytest.raises(cluster.ClusterError, match="--scheduler tcp://127.0.0.1:9: cannot connect"):
        cluster.connect("tcp://127.0.0.1:9")


def test_without_dask_the_cluster_options_say_how_to_install_it(tmp_path, write_runfile):
    path = write_runfile(top_runfile())
    done = run_without("distributed", ["run", str(path), "-o", str(tmp_path / "out.nc"), "--workers", "2"])
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "pip install 'ensemble[dask]'" in done.stderr and not list(tmp_path.glob("out.nc*"))


def test_the_command_line_runs_on_two_local_workers(tmp_path, write_runfile):
    """`ensemble run --workers 2` (a real process: it starts the LocalCluster, checks the workers' versions and
    closes them) writes the bits of a local run, and says so in its one summary line."""
    path = write_runfile(NOISY_TOPS)
    local, remote = tmp_path / "local.nc", tmp_path / "remote.nc"
    assert cli.main(["run", str(path), "-o", str(local), "--quiet"]) == 0
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "-o", str(remote), "--quiet",
                           "--workers", "2"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.startswith(f"wrote {remote}: 60 members"), done.stderr
    assert done.stderr == "", done.stderr  # the cluster's own logging stays quiet
    same_bits(remote, local)


def test_ctrl_c_on_local_workers_is_one_line(tmp_path, write_runfile):
    """Issue 39: Ctrl-C (SIGINT to the terminal's whole process group) on `--workers 2` printed the right line
    and then a KeyboardInterrupt traceback from each worker (67 lines). The workers now ignore SIGINT and stop
    with the run: one line, exit 130, the finished chunks kept."""
    import signal
    import time

    path = write_runfile(top_runfile(members=4000, t_end=300.0, save_dt=1.0))
    out = tmp_path / "out.nc"
    run = subprocess.Popen([sys.executable, "-m", "ensemble", "run", str(path), "-o", str(out), "--quiet",
                            "--workers", "2", "--chunk", "128"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, start_new_session=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # whatever pytest's is
    deadline = time.monotonic() + 120
    # a sealed part (members-*.nc), not one being written (members-*.tmp): then a chunk has finished
    while not list(folder_of(out).glob("members-*.nc")) and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    os.killpg(run.pid, signal.SIGINT)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 130, err
    assert err.splitlines() == [err.splitlines()[0]] and err.startswith("ensemble: interrupted; the "), err
