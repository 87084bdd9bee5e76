"""The analysis commands users run on results (`ensemble fit`, `stability`, `work-precision`): tables, fits files,
charts, --check and bad input; and the benchmark tools' options."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from ensemble import runner, spec
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import top
from ensemble.spec import members_table

from .conftest import top_runfile

ROOT = Path(__file__).resolve().parent.parent


def run_small(name: str, folder: Path, members: int, **replace) -> Path:
    text = re.sub(r"^members = \d+", f"members = {members}", (ROOT / "runs" / name).read_text(), flags=re.M)
    for old, new in replace.items():
        assert old in text, old  # a replacement that matches nothing would test the unchanged file
        text = text.replace(old, new)
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / name.replace(".toml", ".nc")
    runner.run(spec.parse(text, name), out, progress=False)
    return out


def command(*args) -> subprocess.CompletedProcess:
    """`ensemble ARGS...` (fit, stability, work-precision) in this process, as a process's exit status and output:
    a process of its own spends 3 s importing. An exception the command does not turn into one line fails the
    test that called it."""
    import contextlib
    import io

    from ensemble import cli

    out, err, kept = io.StringIO(), io.StringIO(), np.geterr()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = cli.main([str(arg) for arg in args])
        except SystemExit as exit_:  # argparse's usage errors
            status = exit_.code
        finally:
            np.seterr(**kept)
    return subprocess.CompletedProcess(args, status, out.getvalue(), err.getvalue())


def script(name: str, *args) -> subprocess.CompletedProcess:
    """A benchmark tool, `python analysis/bench/NAME ARGS...`."""
    return subprocess.run([sys.executable, str(ROOT / "analysis" / "bench" / name), *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT)


RK4_SHIFT = {"dt = 2.5e-4 ": "dt = 1e-3 "}  # rk4 at 1e-3 s shifts the aerobie's slowest rate by 1.8e-6


def test_the_aerobie_passes_its_check_against_the_physics(tmp_path):
    result = run_small("aerobie.toml", tmp_path, 4)
    done = command("fit", result, "--check")
    assert done.returncode == 0 and len(re.findall(r"^c = .* pass$", done.stdout, flags=re.M)) == 3, done.stdout


def test_tilt_decay_script_shows_rk4s_own_shift(tmp_path):
    result = run_small("aerobie.toml", tmp_path, 4, **RK4_SHIFT)
    done = command("fit", result, "--check", "--against", "method", "--charts", tmp_path / "charts")
    assert done.returncode == 0, done.stderr
    assert len(re.findall(r"^c = .* pass$", done.stdout, flags=re.M)) == 3 and "FAIL" not in done.stdout
    # rk4 at W h = 0.06 shifts the slowest rate by 1.8e-6 relative: beyond 1e-6 of the physics.
    against_theory = command("fit", result, "--check")
    assert against_theory.returncode == 1
    assert re.search(r"^c = 5e-05 .* FAIL$", against_theory.stdout, flags=re.M)
    fits = xr.load_dataset(tmp_path / "aerobie_tilt_decay.nc")
    assert set(fits.data_vars) >= {"rate", "rate_stderr", "rate_theory", "rate_method", "z"}
    for chart in ("tilt", "rates", "z"):
        assert (tmp_path / "charts" / f"aerobie_tilt_decay_{chart}.png").stat().st_size > 10_000


def test_normal_modes_script_on_the_two_mass_chain(tmp_path):
    """The course's chain rings in both modes (w^2 = k/m and 3k/m), and both pass against the physics."""
    result = run_small("two_mass.toml", tmp_path, 2)
    done = command("fit", result, "--check")
    assert done.returncode == 0, done.stderr
    assert re.search(r"^mode 1 +1 .* 2  pass$", done.stdout, flags=re.M), done.stdout
    assert re.search(r"^mode 2 +1.73205.* 2  pass$", done.stdout, flags=re.M), done.stdout


def test_a_mode_nobody_fits_fails_the_check_unless_it_was_not_excited(tmp_path):
    """Started in mode 2 alone, mode 1 is 'not excited' and the check passes; started in both but recorded for
    only 3 periods of mode 1 (a fit needs 4), mode 1 is excited and unfitted, and the check fails."""
    started = run_small("two_mass.toml", tmp_path, 2,
                        **{"x0 = { normal = [0.0, 0.1] }": "x0 = { mode = 2, amplitude = 0.1 }"})
    done = command("fit", started, "--check")
    assert done.returncode == 0 and re.search(r"^mode 1 .* not excited", done.stdout, flags=re.M), done.stdout
    short = run_small("two_mass.toml", tmp_path / "short", 2, **{"t_end = 100.0": "t_end = 20.0"})
    done = command("fit", short, "--check", "--charts", tmp_path / "charts")
    assert done.returncode == 1 and re.search(r"^mode 1 .* none fitted: FAIL", done.stdout, flags=re.M), done.stdout
    for chart in ("spectrum", "frequencies", "z"):
        assert (tmp_path / "charts" / f"two_mass_mode_frequencies_{chart}.png").stat().st_size > 10_000


def test_check_fails_when_the_method_moves_the_frequency(tmp_path):
    # Verlet at w h = 0.5: the fitted frequency (2/h) asin(w h / 2) is 1% above the physics.
    result = run_small("two_mass.toml", tmp_path, 2,
                       **{"dt = 1e-3": "dt = 0.1", "k = 1.0 ": "k = 0.08333333333333333 "})
    done = command("fit", result, "--check")
    assert done.returncode == 1 and "FAIL" in done.stdout


@pytest.mark.parametrize("name", ["fit", "stability", "work-precision"])
def test_a_missing_result_is_one_line_and_exit_2(tmp_path, name):
    missing = command(name, tmp_path / "nothing.nc")
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1, missing.stderr


def test_bad_options_are_one_line_and_exit_2(tmp_path):
    result = run_small("two_mass.toml", tmp_path, 1)
    member = command("fit", result, "--members", "5")
    assert member.returncode == 2 and member.stderr.strip().splitlines() == [
        "ensemble: error: --members: 5 is not in 0..0"]
    assert not (tmp_path / "two_mass_mode_frequencies.nc").exists()
    not_a_folder = tmp_path / "charts"
    not_a_folder.write_text("")
    refused = command("fit", result, "--charts", not_a_folder)
    assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [
        f"ensemble: error: --charts {not_a_folder}: {not_a_folder} is not a folder"]
    assert not (tmp_path / "two_mass_mode_frequencies.nc").exists()
    negative = command("fit", result, "--members", "1,-1")
    assert negative.returncode == 2 and "--members: member numbers are >= 0, got -1" in negative.stderr
    assert len(negative.stderr.strip().splitlines()) == 1
    not_netcdf = tmp_path / "notes.nc"
    not_netcdf.write_text("not a result\n")
    refused = command("fit", not_netcdf)
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("name", ["bench_chain.py", "bench_top.py", "bench_dopri5.py", "fresh_pages.py"])
def test_benchmark_options_are_checked_in_one_line(name):
    done = script(name, "--repeats", 0)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"{name}: error: argument --repeats: must be >= 1, got 0 "
                                                f"(see {name} --help)"]


@pytest.mark.skipif(shutil.which("gcc") is None, reason="the C yardstick needs gcc")
def test_the_c_dopri5_yardstick_steps_as_ensembles_dopri5(tmp_path, monkeypatch):
    """bench_dopri5.py's hand-written C dopri5 is a fair yardstick only if it does ensemble's job: on 128
    aerobie tops it takes ensemble's steps (accepted and rejected) to 1% (its first step is dt, not Hairer's
    guess); and loading it must not change how this process computes."""
    monkeypatch.syspath_prepend(str(ROOT / "analysis" / "bench"))
    import bench_dopri5
    table = members_table(spec.parse((ROOT / "runs" / "aerobie.toml").read_text()))
    tops = {name: values[:128] for name, values in table.items()}
    c = bench_dopri5.c_tops(tops, 11, 0.1, 1e-3, tmp_path)
    outcome = launch.integrate(top, METHODS["dopri5"], tops, {}, n_save=11, save_dt=0.1, rtol=1e-8, atol=1e-12)
    steps = outcome.counts[:2].sum()
    assert steps > 128 * 100  # the tops need more than 100 steps each at this tolerance
    assert c["C dopri5"]() == pytest.approx(steps, rel=0.01)
    assert 0.0 <= c["C dopri5"].waited < 0.5  # a block runs at least its members' trial steps
    assert np.array([5e-324]) > 0.0  # loading the C left subnormal numbers alone (no flush-to-zero modes)


@pytest.mark.skipif(shutil.which("gcc") is None, reason="the C yardstick needs gcc")
def test_the_benchmark_times_the_c_beside_its_own_calls_in_a_process_apart(monkeypatch):
    """benchmark.py's ratios to the C come round by round from hostinfo.CBeside: limit.py's kernels timed on
    request in a process of their own, whose -ffast-math library then sets no flush-to-zero mode here; a round's
    ratio is ensemble's work over its own seconds over the C's rate of that round."""
    monkeypatch.syspath_prepend(str(ROOT / "analysis" / "bench"))
    import benchmark
    import hostinfo
    if not hostinfo.LIMIT.exists():
        pytest.skip("no ../shared/limit/limit.py beside the checkout")
    beside = hostinfo.CBeside()
    try:
        rates = [beside.rate(name) for name in ("top rk4", "chain verlet N=2", "chain verlet N=16")]
    finally:
        beside.close()
    assert all(np.isfinite(rate) and rate > 1e6 for rate in rates)  # steps/s: even a slow host makes millions
    assert np.array([5e-324]) > 0.0  # subnormal numbers survive in this process
    assert [benchmark.c_kernel_beside(case) for case in ("top rk4", "top dopri5", "chain yoshida4 N=128",
                                                         "ring verlet N=2")] == [
        "top rk4", None, "chain verlet N=128", "chain verlet N=2"]
    seconds, c_rates = [1.0, 2.0, 4.0, 8.0, 0.5], [10.0, 5.0, 1.0, 1.0, 40.0]  # rounds, work 10 steps each
    got = benchmark.ensemble_rates(10.0, seconds, c_rates)
    ratios = sorted(10.0 / s / c for s, c in zip(seconds, c_rates))  # 1, 1, 2.5, 1.25, 0.5
    assert got == {"ensemble": 10.0 / 2.0, "C": 5.0, "to_C": ratios[2]}


def test_compare_revisions_runs_each_revisions_own_code_even_from_the_checkout(tmp_path, monkeypatch):
    """A process under compare_revisions' environment for a revision imports ensemble from that revision's
    folder, also when started in the checkout (whose own ensemble Python would otherwise find first)."""
    monkeypatch.syspath_prepend(str(ROOT / "analysis" / "bench"))
    import compare_revisions
    tree = tmp_path / "revision"
    (tree / "ensemble").mkdir(parents=True)
    (tree / "ensemble" / "__init__.py").write_text("")
    env = {**os.environ, **compare_revisions.revision_env(tree, tmp_path / "cache")}
    found = subprocess.run([sys.executable, "-c", "import ensemble; print(ensemble.__file__)"], cwd=ROOT, env=env,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert Path(found) == tree / "ensemble" / "__init__.py"


def test_an_unwritable_output_is_one_line_and_keeps_the_verdict(tmp_path):
    """When the fits cannot be written (here a folder stands where the fits file goes), the table is printed,
    one line names the folder, and --check still decides the exit status."""
    result = run_small("aerobie.toml", tmp_path, 2, **RK4_SHIFT)
    (tmp_path / "aerobie_tilt_decay.nc").mkdir()
    passed = command("fit", result, "--check", "--against", "method")
    failed = command("fit", result, "--check")  # rk4 misses the slowest rate by 1.8e-6: FAIL
    for done, status in ((passed, 0), (failed, 1)):
        assert done.returncode == status and "[rate], " in done.stdout
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].endswith("); the table above stands"), lines
        assert lines[0].startswith(f"ensemble: error: cannot write in {tmp_path} (")


def test_tables_and_check_need_no_matplotlib(tmp_path):
    """With the core install alone (matplotlib hidden), a script prints its table, writes its fits, says in one
    line that charts need the plot extra, and exits with the check's verdict."""
    result = run_small("aerobie.toml", tmp_path, 2)
    hide = "import sys; sys.modules['matplotlib'] = None; from ensemble.cli import main; sys.exit(main())"
    done = subprocess.run([sys.executable, "-c", hide, "fit", str(result), "--check", "--against", "method",
                           "--charts", str(tmp_path)], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0 and re.search(r"^c = .* pass$", done.stdout, flags=re.M), done.stderr
    assert done.stderr.strip().splitlines() == [
        'no charts: they need matplotlib (pip install "ensemble[plot]"); the table above stands']
    assert (tmp_path / "aerobie_tilt_decay.nc").exists() and not list(tmp_path.glob("*.png"))


def test_table_rows_compare_the_same_members():
    """A member that could not be fitted leaves every column of its row, theory and method too."""
    from ensemble import report
    fits = xr.Dataset({"rate": ("member", [1.0, np.nan, 3.0]), "rate_stderr": ("member", [0.1, np.nan, 0.1]),
                       "rate_theory": ("member", [1.5, 100.0, 2.5]), "rate_method": ("member", [1.4, 90.0, 2.4])},
                      coords={"member": [0, 1, 2]})
    (row,) = report.rows(fits, "rate", lambda *a: "all")
    assert (row.mean, row.theory, row.method, row.members, row.failed) == (2.0, 2.0, 1.9, 2, 1)
    assert row.miss == pytest.approx(0.0, abs=1e-15)


def test_z_histograms_say_what_they_clip():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ensemble import plotting
    fig, ax = plt.subplots()
    plotting.z_histogram(ax, np.array([0.1, -0.5, 1.2, 400.0, -90.0, np.nan]), "fits")
    labels = ax.get_legend_handles_labels()[1]
    plt.close(fig)
    assert set(labels) == {"N(0, 1)", "fits (5, 2 beyond +-50 drawn at the edges)"}


def test_run_phases_times_every_step_of_a_run():
    """analysis/bench/run_phases.py wraps the run's own steps: each wrapped step ran (a renamed one would show 0 calls),
    and the kernel calls and the finishing, each on one thread, took no longer than the run; --members,
    --save-dt and --growth replace the run file's."""
    done = script("run_phases.py", ROOT / "runs" / "aerobie.toml", "--members", 512, "--save-dt", 0.5, "--growth",
                  "--no-limit")  # the C limit is benchmark.py's, tested there
    assert done.returncode == 0, done.stderr
    # 512 members at each of the run file's three drag coefficients; t_end 30 s
    assert re.search(r"^1536 members, .* 61 samples:", done.stdout, re.M), done.stdout
    steps = re.findall(r"^  (\s*[a-z ]+?)\s+([0-9.]+) s in (\d+) calls$", done.stdout, re.M)
    seconds = {name.strip(): float(value) for name, value, _ in steps}
    assert set(seconds) == {"kernel", "finishing", "observing", "amplitudes", "growth fit", "writing",
                            "fsync"}, done.stdout
    assert all(int(count) > 0 for _, _, count in steps), done.stdout
    run = float(re.search(r"the run ([0-9.]+) s", done.stdout)[1])
    assert seconds["kernel"] <= run + 0.005 and seconds["finishing"] <= run + 0.005, done.stdout  # rounding


def test_members_that_blew_up_are_left_out_of_the_fit_and_a_check_with_none_left_fails(tmp_path):
    """Issue 40, item 4: `fit --check` said "pass" on a body result whose members had all blown up (it
    fitted their records up to the failure). Now failed members are NaN in the fits, counted, and --check fails
    when no member is left."""
    unstable = {'method = "rk4"': 'method = "euler"', "dt = 1e-4": "dt = 1e-2", "seed = ": "blowup_factor = 2\nseed = ",
                "spin0 = [10.0, 20.0, 40.0]": "spin0 = [40.0, 80.0, 160.0]"}
    result = run_small("tennis_racket.toml", tmp_path, 3, **unstable)
    ds = xr.load_dataset(result)
    assert np.all(ds["status"].values != 0)  # forward Euler's rates grow every step, past twice their start
    done = command("fit", result, "--check")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "did not run to the end" in done.stdout and "no member could be fitted" in done.stdout
    fits = xr.load_dataset(result.with_name("tennis_racket_body_rates.nc"))
    assert fits.attrs["members_not_ok"] == ds.sizes["member"] and np.all(np.isnan(fits["z"].values))


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory) -> tuple[Path, Path, Path]:
    """A foreign NetCDF file, a result of no members, and a top's result labelled a chain."""
    folder = tmp_path_factory.mktemp("bad")
    result = folder / "tops.nc"
    runner.run(spec.parse(top_runfile(members=2, t_end=0.2), "tops.toml"), result, progress=False)
    foreign, empty, mislabelled = folder / "foreign.nc", folder / "empty.nc", folder / "mislabelled.nc"
    xr.Dataset({"x": ("time", np.arange(3.0))}).to_netcdf(foreign)
    ds = xr.load_dataset(result)
    ds.isel(member=slice(0, 0)).drop_encoding().to_netcdf(empty)
    ds.assign_attrs(scene="chain").to_netcdf(mislabelled)
    return foreign, empty, mislabelled


@pytest.mark.parametrize("name", ["work-precision", "stability", "fit"])
def test_a_foreign_empty_or_mislabelled_file_is_one_line_and_exit_2(bad_files, name, capsys):
    """Issue 40, item 18: work-precision on a zero-member result raised IndexError, fit on a foreign NetCDF
    KeyError: 'member', stability on a top result labelled a chain KeyError: 'm'."""
    from ensemble import cli

    foreign, empty, mislabelled = bad_files
    for path, says in ((foreign, "is not a result of `ensemble run`"), (empty, "has no members"),
                       (mislabelled, "")):
        status = cli.main([name, str(path)])  # an exception would fail the test: no traceback reaches a user
        err = capsys.readouterr().err
        assert status == 2 and len(err.strip().splitlines()) == 1 and says in err, (path, err)
