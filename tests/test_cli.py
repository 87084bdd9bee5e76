"""The command line end to end, the NetCDF file it writes, and interrupted runs."""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import netCDF4
import numpy as np
import pytest
import xarray as xr

from ensemble import cli, runner
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SCENES, scenes_of, top
from ensemble.spec import load, members_table, parse
from tests.conftest import top_runfile

SWEEP_RUN = top_runfile(members=5, t_end=1.0, save_dt=0.1, parameters={"c": None}, sweep={"c": [1e-4, 2e-4]})


def ensemble(*args, cwd):
    return subprocess.run([sys.executable, "-m", "ensemble", *args], cwd=cwd, capture_output=True, text=True)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    """One real run through the command line, into its default output path."""
    folder = tmp_path_factory.mktemp("cli")
    (folder / "runs").mkdir()
    (folder / "runs" / "sweep.toml").write_text(SWEEP_RUN)
    done = ensemble("run", "runs/sweep.toml", cwd=folder)
    return folder, done


def test_run_writes_the_default_output_and_a_summary(cli_run):
    folder, done = cli_run
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (folder / "results").iterdir()) == ["sweep.nc"]  # no parts, lock or .tmp left
    summary = done.stdout.strip().splitlines()[-1]
    assert "10 members x 1000 steps" in summary and "member-steps/s" in summary


def test_progress_to_a_pipe_is_a_plain_line_now_and_then(tmp_path):
    """Issue 53: stderr to a file got a carriage-return update every tenth of a second (67 bar lines for a 5.7 s
    run). Off a terminal the bar writes a line each tenth of the run or half minute, and the summary ends it."""
    path = tmp_path / "run.toml"
    path.write_text(top_runfile(members=1000, t_end=1.0, save_dt=0.1))
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "-o", str(tmp_path / "out.nc"),
                           "--chunk", "128"], capture_output=True, text=True)  # stderr a pipe
    assert done.returncode == 0 and "\r" not in done.stderr, repr(done.stderr)
    progress = [line for line in done.stderr.splitlines() if " of 1000 members after " in line]
    assert 1 <= len(progress) <= 10, done.stderr
    fractions = [int(line.split("%")[0]) for line in progress]
    assert fractions == sorted(fractions) and all(b - a >= 10 for a, b in zip(fractions, fractions[1:])), progress
    assert done.stdout.startswith(f"wrote {tmp_path / 'out.nc'}: 1000 members x 1000 steps")


def test_dataset_follows_the_contract(cli_run):
    folder, _ = cli_run
    ds = xr.open_dataset(folder / "results" / "sweep.nc")
    assert ds.omega.dims == ("member", "t", "axis") and ds.tilt.dims == ("member", "t")
    assert ds.sizes == {"member": 10, "t": 11, "axis": 3}
    assert ds.t.attrs["units"] == "s" and ds.omega.attrs["units"] == "rad s-1" and ds.tilt.attrs["units"] == "rad"
    for name in ("lambda1", "lambda3", "c", "spin0", "tilt0", "azimuth0", "sweep_point"):
        assert ds[name].dims == ("member",) and "units" in ds[name].attrs and "long_name" in ds[name].attrs
    np.testing.assert_allclose(ds.t, np.arange(11) * 0.1, rtol=1e-12)
    attrs = ds.attrs
    assert attrs["Conventions"] == "CF-1.9" and attrs["scene"] == "top" and attrs["method"] == "rk4"
    assert attrs["spec"] == SWEEP_RUN and attrs["seed"] == 7 and attrs["dt"] == 1e-3
    assert attrs["source"].startswith("ensemble ") and attrs["members_written"] == 10
    assert sorted(set(ds.c.values)) == [1e-4, 2e-4]
    # long_names are labels (xarray's plots use them): short, with any explanation in `comment`
    assert max(len(ds[name].attrs.get("long_name", "")) for name in ds.variables) <= 80
    assert "growth_per_step" not in ds  # only where [measure] asks for it (tests/test_stability.py)


def test_file_round_trips_the_kernel_output(cli_run, tmp_path):
    """What the file holds equals an independent in-process integration of the same members."""
    folder, _ = cli_run
    ds = xr.open_dataset(folder / "results" / "sweep.nc")
    table = members_table(parse(SWEEP_RUN))
    for name in ("lambda1", "lambda3", "c", "spin0", "tilt0", "azimuth0"):
        np.testing.assert_array_equal(ds[name].values, table[name])
    samples = launch.integrate(top, METHODS["rk4"], table, {}, n_save=11, save_dt=0.1, dt=1e-3).samples
    np.testing.assert_array_equal(ds.omega.values, samples.transpose(2, 0, 1))
    np.testing.assert_allclose(ds.tilt.values, top.tilt(ds.omega.values, axis=2), rtol=1e-15)
    copy = tmp_path / "copy.nc"
    ds.to_netcdf(copy)
    xr.testing.assert_identical(xr.open_dataset(copy), ds)


def test_output_passes_the_cf_compliance_checker(cli_run):
    folder, _ = cli_run
    executable = shutil.which("compliance-checker", path=str(Path(sys.executable).parent)) or "compliance-checker"
    checker = subprocess.run([executable, "--test=cf:1.9", "-f", "json", "-o", "-",
                              str(folder / "results" / "sweep.nc")], capture_output=True, text=True)
    report = json.loads(checker.stdout)["cf:1.9"]
    assert report["high_count"] == 0, report["high_priorities"]


def test_existing_output_needs_force(cli_run):
    folder, _ = cli_run
    out = folder / "results" / "sweep.nc"
    before = out.stat().st_mtime_ns
    refused = ensemble("run", "runs/sweep.toml", cwd=folder)
    assert refused.returncode == 2 and "--force" in refused.stderr and out.stat().st_mtime_ns == before
    forced = ensemble("run", "runs/sweep.toml", "--force", "--quiet", "-o", "results/sweep.nc", cwd=folder)
    assert forced.returncode == 0 and out.stat().st_mtime_ns > before


def test_version_help_and_methods(tmp_path):
    version = ensemble("--version", cwd=tmp_path)
    assert version.returncode == 0 and version.stdout.startswith("ensemble ")
    helped = ensemble("--help", cwd=tmp_path)
    assert helped.returncode == 0 and "run" in helped.stdout and "methods" in helped.stdout
    listing = ensemble("methods", cwd=tmp_path).stdout.splitlines()
    rows = {line.split()[0]: line.split()[1:4] for line in listing[1:]}
    assert set(rows) == set(METHODS)
    for name, m in METHODS.items():
        order = "exact" if m.order is None else str(m.order)
        assert rows[name] == [order, "yes" if m.symplectic else "no", ",".join(scenes_of(m))]
    assert rows["verlet"] == ["2", "yes", "chain"] and rows["rk4"] == ["4", "no", "top,chain,body"]


def test_results_do_not_depend_on_chunk_size(write_runfile):
    spec = load(write_runfile(top_runfile(members=300, t_end=0.2)))
    small, large = runner.simulate(spec, chunk=128), runner.simulate(spec, chunk=1000)
    xr.testing.assert_equal(small.drop_attrs(), large.drop_attrs())


def test_save_limits_what_is_stored(write_runfile):
    ds = runner.simulate(load(write_runfile(top_runfile(save=["tilt"]))))
    assert "tilt" in ds and "omega" not in ds and "axis" not in ds.dims


def interrupt_after_one_chunk(monkeypatch) -> None:
    """Make the next run raise KeyboardInterrupt (Ctrl-C) when its second chunk's kernel starts."""
    segments, calls = launch.Launch.segments, []

    def interrupted_after_one_chunk(self, *args, **kwargs):
        if calls:
            raise KeyboardInterrupt
        calls.append(1)
        return segments(self, *args, **kwargs)

    monkeypatch.setattr(launch.Launch, "segments", interrupted_after_one_chunk)


def test_interrupted_run_leaves_no_complete_looking_file(write_runfile, tmp_path, monkeypatch, capsys):
    interrupt_after_one_chunk(monkeypatch)
    out = tmp_path / "out.nc"
    status = cli.main(["run", str(write_runfile(top_runfile(members=300))), "-o", str(out), "--chunk", "128"])
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the bar
    assert status == 130 and err == (f"ensemble: interrupted; the 1 chunk(s) finished so far are kept in "
                                     f"{out}.tmp and {out}.parts; ensemble run {tmp_path / 'run.toml'} -o {out} "
                                     f"--resume finishes the run")
    assert not out.exists()
    (part,) = (out.with_name("out.nc.parts")).glob("members-*.nc")
    with netCDF4.Dataset(part) as nc:
        assert nc.dimensions["member"].size == 128 and np.all(nc["steps_accepted"][:] > 0)
    with netCDF4.Dataset(out.with_name("out.nc.tmp")) as nc:
        assert np.all(np.isfinite(nc["omega"][:128]))


def test_the_command_printed_after_an_interrupted_force_run_finishes_it(write_runfile, tmp_path, monkeypatch,
                                                                         capsys):
    """Issue 40, item 9: a --force run over an earlier result, interrupted, printed `... --resume`, which then
    refused ("exists; use --force"). The printed command now finishes the run."""
    runfile, out = write_runfile(top_runfile(members=300)), tmp_path / "out.nc"
    assert cli.main(["run", str(runfile), "-o", str(out), "--quiet"]) == 0
    interrupt_after_one_chunk(monkeypatch)
    assert cli.main(["run", str(runfile), "-o", str(out), "--chunk", "128", "--force", "--quiet"]) == 130
    printed = capsys.readouterr().err.strip().splitlines()[-1]
    command = printed.split("; ")[-1].removesuffix(" finishes the run").split()
    assert command[:2] == ["ensemble", "run"] and "--resume" in command and "--force" in command
    monkeypatch.undo()
    assert cli.main([*command[1:], "--quiet"]) == 0
    assert xr.load_dataset(out).sizes["member"] == 300 and not out.with_name("out.nc.parts").exists()


def test_ctrl_c_inside_a_long_kernel_call_stops_the_run_at_once(tmp_path):
    """One save interval of 5e9 steps (hours): Ctrl-C while the kernel runs ends the process within seconds, exit
    130, keeping only the segment that finished (the first sample: a member resumes at its saved samples) and
    writing no output. The kernel runs on daemon threads; the main thread only waits, so the interrupt reaches
    it."""
    import signal
    import time

    runfile = tmp_path / "long.toml"
    runfile.write_text(top_runfile(members=1, dt=1e-7, t_end=1000.0, save_dt=500.0))
    out = tmp_path / "long.nc"
    # SIGINT as in a terminal: a shell starts background jobs (a test run with `&`) with SIGINT ignored
    run = subprocess.Popen([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out)],
                           stderr=subprocess.PIPE, text=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    result = tmp_path / "long.nc.tmp"  # made once the kernels are ready, before the first chunk
    deadline = time.monotonic() + 300
    while not result.exists() and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.0)  # the kernel is running now
    sent = time.monotonic()
    run.send_signal(signal.SIGINT)
    try:
        _, err = run.communicate(timeout=30)
    finally:
        run.kill()
    assert run.returncode == 130 and time.monotonic() - sent < 5, err
    assert err.splitlines()[-1] == (f"ensemble: interrupted; samples 0 to 0 of members 0 to 0 are kept in {result} "
                                    f"and {out}.parts; ensemble run {runfile} -o {out} --resume finishes the run"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.nc.parts", "long.nc.tmp", "long.toml"]


def test_the_watch_sees_the_fraction_done_grow_to_one():
    """launch.integrate calls watch with the fraction of samples stored so far: never decreasing, 1 at the end."""
    fractions = []
    spec = parse(top_runfile(members=300, t_end=2.0, save_dt=0.1))
    runner.integrate(spec, METHODS["rk4"], members_table(spec), watch=fractions.append)
    assert fractions and fractions[-1] == 1.0 and np.all(np.diff(fractions) >= 0)


def test_second_process_loads_kernels_from_the_disk_cache(cli_run):
    folder, _ = cli_run  # that run compiled (or loaded) the rk4 kernel
    env = {**os.environ, "NUMBA_DEBUG_CACHE": "1"}
    again = subprocess.run([sys.executable, "-m", "ensemble", "run", "runs/sweep.toml", "-o", "again.nc", "--quiet"],
                           cwd=folder, capture_output=True, text=True, env=env)
    log = again.stdout + again.stderr
    assert again.returncode == 0, log
    assert "data loaded" in log and "data saved" not in log


@pytest.mark.parametrize("args, key", [(["--chunk", "0"], "--chunk"), ([], "run file")])
def test_bad_command_line_input_is_one_line_and_exit_2(args, key, write_runfile, tmp_path, capsys):
    runfile = write_runfile(top_runfile()) if args else tmp_path / "missing.toml"
    out = tmp_path / "out.nc"
    assert cli.main(["run", str(runfile), "-o", str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f" {key}: " in err and err.count(str(runfile)) <= 1
    assert not list(tmp_path.glob("out.nc*"))


@pytest.mark.parametrize("text", [
    top_runfile(members=100_000, t_end=100.0, save_dt=0.1) + "[measure]\ngrowth = true\n",
    "scene = 'chain'\nmethod = 'verlet'\ndt = 0.01\nt_end = 10.0\nsave_dt = 0.01\nmembers = 5000\nseed = 1\n"
    "save = ['energy']\n[parameters]\nn = 256\nm = 1.0\nk = 1.0\n",
    "scene = 'chain'\nmethod = 'verlet'\ndt = 0.01\nt_end = 10.0\nsave_dt = 0.1\nmembers = 5000\nseed = 1\n"
    "save = ['energy']\n[parameters]\nn = 256\nm = 1.0\nk = 1.0\n",
])
def test_default_chunk_keeps_kernel_samples_and_saved_data_near_the_budget(text):
    """A chunk holds a segment of the kernel's samples (state rows) and of the saved variables, its work arrays,
    and (`[measure] growth`) two amplitudes per saved sample, 8 bytes a value; it is whole kernel blocks, and a
    single block when one block alone exceeds the budget. A segment is every sample unless one block's would
    exceed the budget."""
    spec = parse(text)
    chunk = runner.default_chunk(spec)
    block = runner.run_block(spec)
    state_rows = 3 if spec.scene == "top" else 2 * spec.constants["n"]
    saved = 4 if spec.scene == "top" else 1  # omega (3) + tilt, or energy
    segment = min(spec.n_save, runner.CHUNK_BYTES // (8 * (state_rows + saved) * block))
    assert runner.segment_samples(spec) == segment
    work = launch.layout(SCENES[spec.scene], METHODS[spec.methods[0]], spec.constants).rows
    per_member = (segment * (state_rows + saved) + work + (2 * spec.n_save if spec.measure["growth"] else 0)) * 8
    assert chunk % block == 0
    if block * per_member > runner.CHUNK_BYTES:
        assert chunk == block
    else:
        assert runner.CHUNK_BYTES / 2 < chunk * per_member <= runner.CHUNK_BYTES


def test_a_long_record_runs_in_segments_within_the_memory_budget(tmp_path, monkeypatch):
    """One member with 50,001 samples: its kernel block (128 members) would hold 154 MB of samples in one call.
    With a 1 MiB budget the record runs in segments of 146 samples, and traced memory peaks at what fitting
    growth_per_step to the whole record's two amplitudes takes (0.8 MB, and ten or so temporaries that size)."""
    import tracemalloc

    monkeypatch.setattr(runner, "CHUNK_BYTES", 2**20)
    spec = parse(top_runfile(members=1, t_end=50.0, save_dt=1e-3) + "[measure]\ngrowth = true\n")
    assert spec.n_save == 50_001 and runner.segment_samples(spec) == 2**20 // (8 * 7 * 128)
    tracemalloc.start()
    try:
        runner.run(spec, tmp_path / "long.nc", progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64e6, peak
    with xr.open_dataset(tmp_path / "long.nc") as ds:
        assert ds.members_written == 1 and np.isfinite(ds.omega.values).all()


def test_a_run_in_segments_writes_the_bits_of_a_run_in_one(tmp_path, monkeypatch):
    """Records of 2001 samples, run whole and in segments of 14 samples (a 100 kB budget), with observation
    noise and measured errors: every variable the same, bit for bit."""
    text = (top_runfile(members=200, t_end=2.0, save_dt=1e-3)
            + "[observe]\nnoise = { tilt = 0.01 }\n[measure]\nerror = true\n")
    spec = parse(text)
    whole = runner.simulate(spec)
    monkeypatch.setattr(runner, "CHUNK_BYTES", 100_000)
    assert runner.segment_samples(spec) == 100_000 // (8 * 7 * 128)
    xr.testing.assert_identical(runner.simulate(spec).drop_attrs(), whole.drop_attrs())


def test_a_run_imports_no_analysis_and_parsing_no_numba(write_runfile, tmp_path):
    """Start-up: `ensemble run` loads neither the fits nor scipy.signal, scipy.stats or scipy.linalg (Numba's BLAS
    probe skipped, cli._skip_numba_blas_probe); reading a run file loads neither Numba nor scipy (run files are
    checked before any kernel is loaded). Afterwards scipy.linalg imports, and a kernel calling BLAS compiles."""
    runfile = write_runfile(top_runfile(members=10))
    probe = ("import sys\nfrom ensemble import spec\nspec.load(sys.argv[1])\n"
             "assert 'numba' not in sys.modules and 'scipy' not in sys.modules\n"
             "from ensemble import cli\nassert cli.main(['run', sys.argv[1], '-o', sys.argv[2], '--quiet']) == 0\n"
             "loaded = [m for m in ('ensemble.fitting', 'ensemble.stability', 'ensemble.report', 'scipy.signal', "
             "'scipy.stats', 'scipy.linalg', 'xarray') if m in sys.modules]\nassert not loaded, loaded\n"
             "assert 'numba' in sys.modules\n"
             "import numpy as np, scipy.linalg\nfrom numba import njit\n"
             "a = np.array([[2.0, 1.0], [0.0, 3.0]])\nassert (njit(lambda x, y: np.dot(x, y))(a, a) == a @ a).all()\n")
    done = subprocess.run([sys.executable, "-c", probe, str(runfile), str(tmp_path / "out.nc")], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("where, expected", [
    ("kernels", "ensemble: interrupted; no chunk had finished; nothing was kept"),
    ("members", "ensemble: interrupted while reading the run file; nothing was written")])
def test_interrupt_before_the_file_opens_is_one_line_naming_no_file(where, expected, write_runfile, tmp_path,
                                                                    monkeypatch, capsys):
    """Ctrl-C while kernels load, or while members are drawn (a long chain's mode starts solve eigenproblems):
    one line, status 130, and nothing is left, so the message must not point to anything."""
    from ensemble import members

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(*((launch, "prepare") if where == "kernels" else (members, "build_table")), interrupted)
    out = tmp_path / "out.nc"
    assert cli.main(["run", str(write_runfile(top_runfile())), "-o", str(out)]) == 130
    assert capsys.readouterr().err.strip().splitlines() == [expected]
    assert not list(tmp_path.glob("out.nc*"))


def test_a_slow_kernel_start_says_it_is_compiling(write_runfile, tmp_path, monkeypatch, capsys):
    """When getting the kernels ready takes longer than a cache load (compiling, once per machine), a line on
    stderr says so while it happens, another how long it took, and the summary does not hide it."""
    import time
    prepare = launch.prepare

    def slow(*args, **kwargs):
        time.sleep(1.5)
        return prepare(*args, **kwargs)

    monkeypatch.setattr(launch, "prepare", slow)
    assert cli.main(["run", str(write_runfile(top_runfile())), "-o", str(tmp_path / "out.nc")]) == 0
    captured = capsys.readouterr()
    assert "compiling the rk4 kernels for top (once per machine; later runs load them) ..." in captured.err
    assert re.search(r"compiled in 1\.\d s", captured.err)
    assert re.search(r"member-steps/s \(after 1\.\d+ s compiling kernels\)$", captured.out.strip())


def test_history_title_and_overwrite_say_what_happened(write_runfile, tmp_path):
    """history keeps the whole command line; a run from a string is not titled '<string>'; runner.run, like the
    command line, replaces an existing file only when told to."""
    out = tmp_path / "out.nc"
    path = write_runfile(top_runfile())
    assert cli.main(["run", str(path), "-o", str(out), "--quiet"]) == 0
    assert cli.main(["run", str(path), "-o", str(out), "--force", "--quiet"]) == 0
    with netCDF4.Dataset(out) as nc:
        assert nc.history.endswith(f": ensemble run {path} -o {out} --force --quiet")
        assert nc.title == "ensemble top run run (rk4)"
    from_string = tmp_path / "string.nc"
    runner.run(parse(top_runfile()), from_string, progress=False)
    with netCDF4.Dataset(from_string) as nc:
        assert nc.title == "ensemble top run (rk4)"
    with pytest.raises(FileExistsError, match="exists; pass force=True"):
        runner.run(parse(top_runfile()), from_string, progress=False)
    runner.run(parse(top_runfile()), from_string, progress=False, force=True)


@pytest.mark.parametrize("members, chunks", [(1_000, 1), (10_000, 4), (300_000, None)])
def test_a_run_of_few_chunks_is_cut_into_pipeline_chunks(members, chunks):
    """10^4 tops with 101 samples (49 MB) make PIPELINE_CHUNKS chunks of whole blocks, not two of the memory
    budget's size; 10^3 (4.9 MB: each of four would hold less than PIPELINE_CHUNK_BYTES) stay one; 3 x 10^5 keep
    the budget's chunks."""
    spec = parse(top_runfile(members=members, t_end=2.0, save_dt=0.02))
    chunk, block = runner.default_chunk(spec), runner.run_block(spec)
    by_budget = runner.CHUNK_BYTES // runner.member_bytes(spec) // block * block
    assert chunk % block == 0 or chunk == members
    expected = chunks or -(-members // by_budget)
    assert -(-members // chunk) == expected
    if chunks is None:
        assert chunk == by_budget


def test_default_chunk_bounds_the_work_between_progress_updates():
    """A long record with few saves: the records are small, but a chunk holds at most CHUNK_MEMBER_STEPS of
    work, so the bar moves (and Ctrl-C lands between chunks) every few seconds; never less than one block."""
    spec = parse(top_runfile(members=100_000, t_end=1000.0, save_dt=100.0))  # 1e6 steps a member
    block = launch.layout(SCENES["top"], METHODS["rk4"], {}).block
    assert runner.steps_per_member(spec) == pytest.approx(1e6)
    assert runner.default_chunk(spec) == runner.CHUNK_MEMBER_STEPS // 1e6 // block * block
    one_block = parse(top_runfile(members=1000, t_end=1e5, save_dt=1e4))  # 1e8 steps: one block is the least
    assert runner.default_chunk(one_block) == block


@pytest.mark.parametrize("name", ["job.nc.tmp", "job.nc.lock", "job.nc.parts/run.toml"])
def test_a_run_file_named_like_the_outputs_scratch_paths_is_refused_and_kept(tmp_path, name):
    """Issue 40: `ensemble run job.nc.tmp -o job.nc` deleted its run file, and so did a run file named job.nc.lock
    or kept in job.nc.parts/ with --force. Now: one line, exit 2, the run file as it was."""
    runfile = tmp_path / name
    runfile.parent.mkdir(exist_ok=True)
    runfile.write_text(top_runfile())
    done = ensemble("run", str(runfile), "-o", str(tmp_path / "job.nc"), "--force", "--quiet", cwd=tmp_path)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "run file" in done.stderr and runfile.read_text() == top_runfile()
    assert not (tmp_path / "job.nc").exists()


def test_force_deletes_only_what_a_run_wrote_in_a_parts_folder(tmp_path, write_runfile):
    """Issue 40: --force removed a parts folder with whatever was in it. Now it deletes only a run's own files
    there (its manifest and parts), and a folder that still holds someone else's file is refused in one line,
    that file kept; once it is moved away, the run goes through."""
    runfile = write_runfile(top_runfile())
    out, parts = tmp_path / "job.nc", tmp_path / "job.nc.parts"
    parts.mkdir()
    (parts / "notes.txt").write_text("mine")
    (parts / "manifest.json").write_text("{}")  # another run's parts folder, with a stranger in it
    (parts / "members-000000000000-000000000004-0123abcd.nc").write_bytes(b"a part")
    done = ensemble("run", str(runfile), "-o", str(out), "--force", "--quiet", cwd=tmp_path)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "not a run's parts" in done.stderr and sorted(p.name for p in parts.iterdir()) == ["notes.txt"]
    assert (parts / "notes.txt").read_text() == "mine" and not out.exists()
    (parts / "notes.txt").rename(tmp_path / "notes.txt")
    done = ensemble("run", str(runfile), "-o", str(out), "--force", "--quiet", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert not parts.exists() and xr.load_dataset(out).sizes["member"] == 4


@pytest.mark.parametrize("refusal", ["disk space", "scheduler"])
def test_a_refusal_makes_no_output_folder(tmp_path, write_runfile, refusal):
    """Issue 40, item 12: the disk-space refusal and an unreachable --scheduler each created the output's folder.
    Now the folder is made only when the run starts."""
    text = top_runfile(members=10**5, t_end=1000.0, save_dt=1e-3) if refusal == "disk space" else top_runfile()
    runfile = write_runfile(text)
    out = tmp_path / "new" / "deeper" / "job.nc"
    extra = ["--scheduler", "tcp://127.0.0.1:1"] if refusal == "scheduler" else []
    done = ensemble("run", str(runfile), "-o", str(out), "--quiet", *extra, cwd=tmp_path)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert ("needs about" if refusal == "disk space" else "cannot connect") in done.stderr
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("parameters, top_level, status", [
    ({"lambda1": 1e-320}, {}, 2), ({"spin0": 1e308}, {}, 0), ({}, {"blowup_factor": 1e308}, 0)])
def test_extreme_values_print_no_numpy_warnings(tmp_path, write_runfile, parameters, top_level, status):
    """Issue 40, item 17: these printed RuntimeWarnings before their one line (or beside a finished run)."""
    runfile = write_runfile(top_runfile(parameters=parameters, **top_level))
    done = ensemble("run", str(runfile), "-o", str(tmp_path / "out.nc"), "--quiet", cwd=tmp_path)
    assert done.returncode == status and "Warning" not in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == (1 if status else 0), done.stderr
