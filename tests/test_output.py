"""Where a run writes: the output path is checked before any work, two runs never share an output, and a write
that fails midway (a full disk) says so, exits 3, leaves no file that looks complete and keeps its finished
parts, which --resume completes."""
import fcntl
import os
import resource
import signal
import subprocess
import sys

import netCDF4
import numpy as np
import pytest

from ensemble import cli
from tests.conftest import top_runfile

RUN = top_runfile(members=300, t_end=0.5, save_dt=0.005)


def refused_output(folder, capsys, out, *options, expected):
    runfile = folder / "run.toml"
    if not runfile.exists():
        runfile.write_text(RUN)
    status = cli.main(["run", str(runfile), "-o", str(out), "--quiet", *options])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1 and expected in err, err
    assert not list(folder.glob("*.parts")) and not list(folder.glob("*.tmp")) and not list(folder.glob("*.lock"))
    return err


def test_the_run_file_is_never_the_output(tmp_path, capsys):
    runfile = tmp_path / "run.toml"
    runfile.write_text(RUN)
    refused_output(tmp_path, capsys, runfile, "--force", expected="is the run file itself")
    assert runfile.read_text() == RUN


def test_a_file_ensemble_did_not_write_is_not_replaced_even_with_force(tmp_path, capsys):
    other = tmp_path / "notes.nc"
    other.write_text("my notes\n")
    refused_output(tmp_path, capsys, other, "--force", expected="is not a result written by ensemble")
    assert other.read_text() == "my notes\n"


def test_a_folder_is_not_an_output(tmp_path, capsys):
    (tmp_path / "out").mkdir()
    refused_output(tmp_path, capsys, tmp_path / "out", "--force", expected="is a folder")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_refused_before_the_run(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    refused_output(tmp_path, capsys, locked / "out.nc", expected="cannot write in the folder")


def test_a_second_run_on_the_same_output_is_refused_at_once(tmp_path, capsys):
    out = tmp_path / "out.nc"
    with open(tmp_path / "out.nc.lock", "w") as held:  # what a running `ensemble run -o out.nc` holds
        fcntl.flock(held, fcntl.LOCK_EX)
        runfile = tmp_path / "run.toml"
        runfile.write_text(RUN)
        status = cli.main(["run", str(runfile), "-o", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and "another run is writing it" in err and not out.exists()


def _small_disk():
    """The child's files may not grow past 600 kB: a disk that fills up (SIGXFSZ ignored, so a write past the
    limit fails with EFBIG, as a full disk fails with ENOSPC)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (600_000, 600_000))


def test_a_disk_full_before_the_first_chunk_is_one_line_exit_3_and_leaves_nothing(tmp_path):
    """A real process whose result cannot grow to its size (HDF5 sizes it at the first chunk's flush): one line,
    exit 3, and nothing left behind, neither parts nor OUT.nc.tmp."""
    runfile = tmp_path / "run.toml"
    runfile.write_text(RUN)
    out = tmp_path / "out.nc"
    command = [sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--quiet", "--chunk", "64"]
    done = subprocess.run(command, capture_output=True, text=True, preexec_fn=_small_disk)
    assert done.returncode == 3, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "writing failed" in lines[0] and "nothing was kept" in lines[0], lines
    assert "past the file size limit of 600000 bytes (ulimit -f)" in lines[0], lines  # issue 40, item 11
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


def test_a_disk_that_fills_up_midway_is_one_line_exit_3_and_resume_finishes_the_run(tmp_path, capsys, monkeypatch):
    """The fourth chunk's write fails as on a full disk: one line, exit 3, no file that looks complete, the three
    finished chunks kept (their samples in OUT.nc.tmp); with room again, --resume writes the bits of an
    unhindered run."""
    import errno

    from ensemble import preflight, store

    runfile = tmp_path / "run.toml"
    runfile.write_text(RUN)
    out = tmp_path / "out.nc"
    real, writes = store.put_samples, []

    def fills_up(*args):
        if len(writes) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        writes.append(args[1])
        real(*args)

    monkeypatch.setattr(store, "put_samples", fills_up)
    monkeypatch.setattr(preflight, "whole_blocks", lambda spec, chunk: chunk)  # chunks of 64, as asked
    command = ["run", str(runfile), "-o", str(out), "--quiet", "--chunk", "64"]
    assert cli.main(command) == 3
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "writing failed (No space left on device)" in lines[0], lines
    assert f"kept in {out}.tmp and {out}.parts" in lines[0], lines
    assert not out.exists() and not (tmp_path / "out.nc.lock").exists()
    assert len(list((tmp_path / "out.nc.parts").glob("members-*.nc"))) == 3
    with netCDF4.Dataset(tmp_path / "out.nc.tmp") as nc:
        assert np.all(np.isfinite(nc["tilt"][:3 * 64]))
    monkeypatch.setattr(store, "put_samples", real)
    # Issue 40, item 10: the disk as full as it was; what is still to write fits, the whole result would not
    import shutil

    from ensemble.spec import load
    spec = load(runfile)
    whole = store.output_bytes(spec) + 8 * len(store.record_names(spec)) * spec.n_members
    room = whole - (tmp_path / "out.nc.tmp").stat().st_size + 10_000
    free = shutil.disk_usage(tmp_path)._replace(free=room)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: free)
    assert room < whole and cli.main([*command[:3], str(tmp_path / "elsewhere.nc"), "--quiet"]) == 2
    assert "the result needs about" in capsys.readouterr().err
    assert cli.main([*command, "--resume"]) == 0
    monkeypatch.undo()
    assert cli.main([*command[:3], str(tmp_path / "unhindered.nc"), "--quiet"]) == 0
    from tests.test_resume import same_bits
    same_bits(out, tmp_path / "unhindered.nc")


def test_a_disk_without_room_for_the_result_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    import shutil
    free = shutil.disk_usage(tmp_path)._replace(free=100_000)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: free)
    err = refused_output(tmp_path, capsys, tmp_path / "out.nc", expected="the result needs about")
    assert "has 0.1 MB free" in err


def test_step_counters_hold_more_than_two_billion(tmp_path):
    """A run of 3e9 steps per member must not wrap to a negative count in the file (they are 64-bit)."""
    from ensemble.spec import parse
    from ensemble.store import Writer
    spec = parse(top_runfile(members=3), "run.toml")
    counts = np.array([3_000_000_000, 2**40, 7], dtype=np.int64)
    with Writer(tmp_path / "out.nc", spec) as writer:
        writer.write(0, {"steps_accepted": counts, "rhs_evals": 4 * counts})
    with netCDF4.Dataset(tmp_path / "out.nc") as nc:
        np.testing.assert_array_equal(nc["steps_accepted"][:], counts)
        np.testing.assert_array_equal(nc["rhs_evals"][:], 4 * counts)


def test_the_results_structure_is_fixed_when_it_is_created(tmp_path):
    """Every record, saved variable and member variable has its whole space once the file is made
    (Writer._allocate), so writing members, the records last of all, changes only their bytes: a run killed
    while writing leaves a file that opens. HDF5 grows the file when it allocates a variable; here the size must
    not change."""
    from ensemble.spec import members_table, parse
    from ensemble.store import Writer, member_variables, record_names, temporary_path
    spec = parse(top_runfile(members=1000, save=["omega", "tilt"], t_end=1.0), "run.toml")
    path = tmp_path / "out.nc"
    with Writer(path, spec) as writer:
        writer.sync()
        size = temporary_path(path).stat().st_size
        samples = {name: np.ones(writer.nc.variables[name].shape) for name in spec.save}
        assert size > sum(x.nbytes for x in samples.values())  # the space is there already
        writer.write_samples(0, 0, samples)
        for start in (0, 500):  # the member variables by ranges, as runs write them
            writer.write(start, member_variables(spec, members_table(spec, start, start + 500), start))
        writer.write(0, {name: np.ones(1000, writer.nc.variables[name].dtype) for name in record_names(spec)})
        writer.sync()
        assert temporary_path(path).stat().st_size == size
    with netCDF4.Dataset(path) as nc:
        assert nc["tilt"][-1, -1] == 1.0 and nc["status"][-1] == 1  # the allocating writes were overwritten
        np.testing.assert_array_equal(nc["member"][:], np.arange(1000))
        np.testing.assert_array_equal(nc["tilt0"][:], members_table(spec)["tilt0"])


@pytest.mark.skipif(not hasattr(os, "posix_fadvise"), reason="no posix_fadvise here")
def test_a_finished_chunk_is_on_the_disk_before_its_pages_are_released(tmp_path, monkeypatch):
    """store.fsync_path(release=True), which seals every chunk: fsync first, then the advice that the system may
    drop the file's cached pages (DONTNEED, the whole file); without release, no advice; advice refused loses
    nothing."""
    from ensemble import store

    path, calls = tmp_path / "result.nc.tmp", []
    path.write_bytes(b"samples")
    monkeypatch.setattr(os, "fsync", lambda fd: calls.append("fsync"))
    monkeypatch.setattr(os, "posix_fadvise", lambda fd, offset, length, advice: calls.append((offset, length, advice)))
    store.fsync_path(path, release=True)
    assert calls == ["fsync", (0, 0, os.POSIX_FADV_DONTNEED)]
    calls.clear()
    store.fsync_path(path)
    assert calls == ["fsync"]

    def refuses(*args):
        raise OSError(22, "Invalid argument")

    monkeypatch.setattr(os, "posix_fadvise", refuses)
    store.fsync_path(path, release=True)
    assert path.read_bytes() == b"samples"


def test_the_member_coordinate_counts_past_an_int32():
    """`member` is int32 up to 2^31 - 1 members and int64 beyond (a run's members are drawn by ranges, so nothing
    else bounds their number); the description of a run of 3e9 members declares it without writing it."""
    from ensemble.spec import members_table, parse
    from ensemble.store import described, member_variables

    for members, kind in ((2**31 - 1, np.int32), (3 * 10**9, np.int64)):
        spec = parse(top_runfile(members=members), "run.toml")
        nc = described(spec)
        try:
            assert nc["member"].dtype == kind and nc.dimensions["member"].size == members
        finally:
            nc.close()
        last = member_variables(spec, members_table(spec, members - 2, members), members - 2)["member"]
        assert last.dtype == kind and last.tolist() == [members - 2, members - 1]
