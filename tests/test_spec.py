"""Run files: validation of every bad input, sweep expansion, seeded draws."""
import numpy as np
import pytest

from ensemble import cli, runner
from ensemble import spec as spec_module
from ensemble.spec import SpecError, members_table, parse
from tests.conftest import refused, top_runfile

BAD_INPUTS = {
    "toml syntax": ("scene = 'top'\ndt = = 1\n", "TOML syntax"),
    "moments beyond a float": (top_runfile(parameters={"lambda1": None, "lambda3": None, "body": {
        "shape": "box", "mass": 1e300, "width": 1e300, "height": 2e300, "depth": 3e300}}), "parameters.body"),
    "mode start past memory": ('scene = "chain"\nmethod = "verlet"\ndt = 0.01\nt_end = 1.0\nsave_dt = 0.1\n'
                               'members = 1\nseed = 1\n[parameters]\nn = 100000\nm = 1.0\nk = 1.0\n'
                               'x0 = { mode = 1, amplitude = 0.1 }\n', "parameters.x0"),
    "uniform wider than a float": (top_runfile(parameters={"tilt0": {"uniform": [-1e308, 1e308]}}),
                                   "parameters.tilt0.uniform"),
    "unknown parameter": (top_runfile(parameters={"lamda1": 1e-3}), "parameters.lamda1"),
    "unknown top-level key": (top_runfile(tend=3.0), "tend"),
    "wrong type": (top_runfile(dt="fast"), "dt"),
    "wrong type of integer": (top_runfile(members=2.5), "members"),
    "wrong parameter type": (top_runfile(parameters={"spin0": "fast"}), "parameters.spin0"),
    "unknown scene": (top_runfile(scene="pendulum"), "scene"),
    "unknown method": (top_runfile(method="rk45"), "method"),
    "dt zero": (top_runfile(dt=0.0), "dt"),
    "dt negative": (top_runfile(dt=-1e-3), "dt"),
    "t_end zero": (top_runfile(t_end=0.0), "t_end"),
    "save_dt not a multiple of dt": (top_runfile(save_dt=0.0015), "save_dt"),
    "t_end not a multiple of save_dt": (top_runfile(t_end=0.55), "t_end"),
    "members zero": (top_runfile(members=0), "members"),
    "lambda zero": (top_runfile(parameters={"lambda1": 0.0}), "parameters.lambda1"),
    "lambda negative in a sweep": (top_runfile(parameters={"lambda3": None}, sweep={"lambda3": [1e-3, -1e-3]}),
                                   "sweep.lambda3"),
    "c negative": (top_runfile(parameters={"c": -1e-5}), "parameters.c"),
    "no such rigid body": (top_runfile(parameters={"lambda3": 2.5e-3}), "parameters.lambda3"),
    "uniform lo > hi": (top_runfile(parameters={"tilt0": {"uniform": [0.2, 0.1]}}), "parameters.tilt0.uniform"),
    "normal sd < 0": (top_runfile(parameters={"spin0": {"normal": [60.0, -1.0]}}), "parameters.spin0.normal"),
    "unknown distribution": (top_runfile(parameters={"spin0": {"gauss": [60.0, 1.0]}}), "parameters.spin0"),
    "parameter and sweep axis": (top_runfile(sweep={"c": [1e-4, 2e-4]}), "sweep.c"),
    "missing parameter": (top_runfile(parameters={"spin0": None}), "parameters.spin0"),
    "missing top-level key": (top_runfile(seed=None), "seed"),
    "unknown saved variable": (top_runfile(save=["omega", "angle"]), "save[1]"),
    "method of another scene": (top_runfile(method="verlet"), "method"),
}


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_bad_input_is_one_line_naming_the_key_and_exit_2(case, write_runfile, tmp_path, capsys):
    text, key = BAD_INPUTS[case]
    with pytest.raises(SpecError) as error:
        parse(text)
    assert error.value.key == key
    out = tmp_path / "out.nc"
    status = cli.main(["run", str(write_runfile(text)), "-o", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert status == 2
    assert len(err.strip().splitlines()) == 1 and f" {key}: " in err
    assert not out.exists() and not list(tmp_path.glob("out.nc*"))


def test_unknown_key_suggests_the_close_one():
    with pytest.raises(SpecError, match="did you mean 'lambda1'"):
        parse(top_runfile(parameters={"lamda1": 1e-3}))


def test_method_mismatch_names_the_methods_that_apply():
    with pytest.raises(SpecError, match="euler, rk4, split2, split4, dopri5, exact"):
        parse(top_runfile(method="verlet"))


def test_flat_body_on_the_bound_is_accepted():
    """A thin annulus has lambda3 = 2 lambda1 up to rounding."""
    lambda1 = 0.1 * (0.1**2 + 0.13**2) / 4
    parse(top_runfile(parameters={"lambda1": lambda1, "lambda3": 2 * lambda1 * (1 + 1e-15)}))


def test_sweep_expands_every_combination_with_replicas():
    spec = parse(top_runfile(members=3, parameters={"c": None, "spin0": None},
                             sweep={"c": [1e-4, 2e-4], "spin0": [10.0, 20.0, 30.0]}))
    table = members_table(spec)
    assert spec.sweep_points == 6 and spec.n_members == 18
    pairs = list(zip(table["c"], table["spin0"]))
    assert sorted(set(pairs)) == [(c, s) for c in (1e-4, 2e-4) for s in (10.0, 20.0, 30.0)]
    assert all(pairs.count(p) == 3 for p in set(pairs))
    np.testing.assert_array_equal(table["sweep_point"], np.repeat(np.arange(6), 3))
    for point in range(6):  # a point's replicas share its sweep values
        same = table["sweep_point"] == point
        assert len(set(table["c"][same])) == 1 and len(set(table["spin0"][same])) == 1


def test_draws_are_seeded_per_member_and_follow_their_distribution():
    text = top_runfile(members=4000, parameters={"spin0": {"normal": [60.0, 2.0]},
                                                 "lambda1": {"loguniform": [1e-3, 1e-2]},
                                                 "lambda3": 1e-3})
    a, b = members_table(parse(text)), members_table(parse(text))
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
    other = members_table(parse(text.replace("seed = 7", "seed = 8")))
    assert not np.any(other["tilt0"] == a["tilt0"])
    assert 0.02 <= a["tilt0"].min() and a["tilt0"].max() <= 0.2
    assert abs(a["spin0"].mean() - 60.0) < 4 * 2.0 / np.sqrt(4000)
    assert abs(a["spin0"].std() - 2.0) < 0.1
    log = np.log10(a["lambda1"])  # loguniform: uniform in log
    assert -3 <= log.min() and log.max() <= -2 and abs(log.mean() + 2.5) < 0.02


def test_a_member_keeps_its_draws_when_the_ensemble_grows():
    small = members_table(parse(top_runfile(members=5)))
    large = members_table(parse(top_runfile(members=50)))
    np.testing.assert_array_equal(small["tilt0"], large["tilt0"][:5])


def test_any_range_of_members_draws_what_the_whole_run_draws():
    """A task builds members start .. stop - 1 alone, per-mass normal draws included: the same values as the
    whole table, for ranges of every size and place."""
    text = CHAIN_TEXT.replace("members = 2", "members = 257").replace(
        "x0 = 0.1", "x0 = { normal = [0.0, 0.1] }\nv0 = { uniform = [-1.0, 1.0] }").replace(
        "m = 1.0", "m = { loguniform = [0.5, 2.0] }")
    spec = parse(text)
    whole = members_table(spec)
    for start, stop in [(0, 257), (0, 1), (5, 12), (128, 256), (256, 257)]:
        part = members_table(spec, start, stop)
        assert part.keys() == whole.keys()
        for name in whole:
            np.testing.assert_array_equal(part[name], whole[name][start:stop], err_msg=name)


def test_uniform_draws_are_numpys_stream_and_normal_draws_are_normal():
    """Member i's uniform is the i-th value of numpy's default_rng([seed, crc32(name)]).uniform (an independent
    computation: no jumping ahead); normal draws pass a Kolmogorov-Smirnov test against N(mu, sigma)."""
    import zlib

    from scipy import stats

    spec = parse(top_runfile(members=20000, parameters={"spin0": {"normal": [60.0, 2.0]}}))
    table = members_table(spec)
    stream = np.random.default_rng([7, zlib.crc32(b"tilt0")])
    np.testing.assert_array_equal(table["tilt0"], stream.uniform(0.02, 0.2, 20000))
    assert stats.kstest(table["spin0"], stats.norm(60.0, 2.0).cdf).pvalue > 1e-3


def test_loguniform_draws_are_the_c_librarys_exp_of_numpys_uniform_stream():
    """Member i's loguniform is math.exp (the C library's, as the kernels call it) of the i-th uniform of
    log(lo) .. log(hi): not NumPy's exp, whose SIMD code rounds otherwise on a host with AVX-512."""
    import math
    import zlib

    spec = parse(top_runfile(members=20000, parameters={"tilt0": {"loguniform": [1e-4, 1e-2]}}))
    table = members_table(spec)
    uniform = np.random.default_rng([7, zlib.crc32(b"tilt0")]).uniform(math.log(1e-4), math.log(1e-2), 20000)
    np.testing.assert_array_equal(table["tilt0"], [math.exp(u) for u in uniform])


SENTINEL = 12345.678  # stands for a raw TOML value (nan, inf, a table) that top_runfile would quote


def raw(text: str, value: str) -> str:
    return text.replace(repr(SENTINEL), value)


CHAIN_TEXT = ("scene = 'chain'\nmethod = 'verlet'\ndt = 0.01\nt_end = 1.0\nsave_dt = 0.1\nmembers = 2\nseed = 1\n"
              "[parameters]\nn = 2\nm = 1.0\nk = 1.0\nx0 = 0.1\n")


@pytest.mark.parametrize("text, key", [
    (raw(top_runfile({"c": SENTINEL}), "nan"), "parameters.c"),
    (raw(top_runfile({"c": SENTINEL}), "inf"), "parameters.c"),
    (raw(top_runfile({"lambda1": SENTINEL}), "nan"), "parameters.lambda1"),
    (raw(top_runfile({"tilt0": SENTINEL}), "nan"), "parameters.tilt0"),
    (raw(top_runfile({"spin0": SENTINEL}), "inf"), "parameters.spin0"),
    (raw(top_runfile({"azimuth0": SENTINEL}), "-inf"), "parameters.azimuth0"),
    (raw(top_runfile({"tilt0": SENTINEL}), "{ uniform = [nan, 1] }"), "parameters.tilt0.uniform"),
    (raw(top_runfile({"c": SENTINEL}), "{ loguniform = [1e-3, inf] }"), "parameters.c.loguniform"),
    (raw(top_runfile(dt=SENTINEL), "nan"), "dt"),
    (raw(top_runfile(sweep={"c": [1e-4, SENTINEL]}, parameters={"c": None}), "nan"), "sweep.c"),
    (CHAIN_TEXT.replace("m = 1.0", "m = [1.0, nan]"), "parameters.m[1]"),
    (CHAIN_TEXT.replace("k = 1.0", "k = [1.0, inf, 1.0]"), "parameters.k[1]"),
    (CHAIN_TEXT.replace("x0 = 0.1", "x0 = [0.1, nan]"), "parameters.x0[1]"),
    (CHAIN_TEXT.replace("x0 = 0.1", "x0 = { mode = 1, amplitude = nan }"), "parameters.x0.amplitude"),
    (CHAIN_TEXT + "omega_max = nan\n", "parameters.omega_max"),
    (raw(top_runfile(blowup_factor=SENTINEL), "nan"), "blowup_factor"),
])
def test_nan_and_infinity_are_refused_in_one_line(text, key, tmp_path, capsys):
    """NaN and infinity passed every `<= 0` check; now every number must be finite (blowup_factor may be inf)."""
    refused(text, tmp_path, capsys, f" {key}: must be a finite number")


def test_blowup_factor_may_be_infinite():
    assert parse(raw(top_runfile(blowup_factor=SENTINEL), "inf")).blowup_factor == float("inf")


@pytest.mark.parametrize("text, key", [
    (top_runfile(sweep={"c": [1e-4, 1e-4]}, parameters={"c": None}), "sweep.c"),  # a sweep point twice
    (CHAIN_TEXT.replace("n = 2", 'n = 1\nboundary = "periodic"'), "parameters.n"),  # a spring from a mass to itself
    (top_runfile({"spin0": 0.0}), "parameters.spin0"),  # a top at rest has no tilt
])
def test_nonsense_that_used_to_pass_is_one_line(text, key, tmp_path, capsys):
    refused(text, tmp_path, capsys, f" {key}: ")


def test_summary_says_closed_form_only_for_the_closed_form():
    """A stepping run whose members all failed before their first step took 0 member-steps, like a closed-form
    run; the summary used to call it closed form."""
    failed_at_once = str(runner.Summary(4, 0, 0.1, blew_up=4))
    assert "closed form" not in failed_at_once and "4 of 4 members failed" in failed_at_once
    assert "(closed form)" in str(runner.Summary(4, 0, 0.1, closed_form=True))


@pytest.mark.parametrize("change, expected", [
    ({"dt": 5e-324}, "save_dt: save_dt / dt = 0.1 / 5e-324 = inf: more than the 1e+12"),
    ({"t_end": 1e308, "save_dt": 1e308}, "save_dt: save_dt / dt = 1e+308 / 0.001 = inf"),
    ({"t_end": 1e13, "save_dt": 1e12, "dt": 1.0}, "dt: t_end / dt = 1e+13 steps per member: more than the 1e+12"),
    ({"seed": 2**70}, "seed: must be in 0 .. 2**63 - 1, got 1180591620717411303424"),
    ({"members": 10**12}, "the result needs about 3.52e+08 MB"),
])
def test_what_a_run_file_may_ask_for_is_bounded(change, expected, tmp_path, capsys):
    """Steps, seeds and members beyond the limits are one line before anything is allocated (a 10**12-member
    run's result would need more disk than there is; its parameters are drawn by ranges, never all at once)."""
    refused(top_runfile(**change), tmp_path, capsys, expected)


def test_timing_repeats_are_bounded(tmp_path, capsys):
    """Issue 40, item 15: [measure] repeats = 1000000000 was accepted and ran without end."""
    text = top_runfile() + "[measure]\ntiming = true\nrepeats = 1000000000\n"
    refused(text, tmp_path, capsys, "measure.repeats: must be in 1..100 (timed kernel calls per chunk), got 1000000000")


def test_a_variable_saved_twice_is_refused(tmp_path, capsys):
    refused('save = ["tilt", "tilt"]\n' + top_runfile(), tmp_path, capsys, "save[1]: names 'tilt' a second time")


def test_a_record_longer_than_memory_is_refused_before_the_run(tmp_path, capsys):
    """One kernel block of 128 members fitting growth to 1e9 saved times each cannot be held: refused with the
    number. Without `[measure] growth` the record runs in segments within the memory budget."""
    line = refused(top_runfile(t_end=1e7, save_dt=0.01, dt=0.01) + "[measure]\ngrowth = true\n", tmp_path, capsys,
                   "holding 1000000001 saved times each")
    assert line.endswith("or measure no growth")
    plain = parse(top_runfile(t_end=1e7, save_dt=0.01, dt=0.01))
    assert runner.smallest_chunk(plain) * runner.member_bytes(plain) <= 2 * runner.CHUNK_BYTES


@pytest.mark.parametrize("content, expected", [
    (b"\xff\xfe scene", "run file: is not UTF-8 text (byte 0)"),
    (b"#" * 1_000_001, "run file: is larger than 1 MB"),
    (b"x = " + b"[" * 100_000 + b"]" * 100_000, "TOML syntax: arrays and tables nest 100000 deep; at most 32"),
    (b".".join([b"a"] * 50_000) + b" = 1", "TOML syntax: a key of 50000 dotted parts; at most 32"),
    (b"[" + b".".join([b"a"] * 40) + b"]", "TOML syntax: a key of 40 dotted parts; at most 32")])
def test_a_run_file_that_is_not_short_text_is_refused(content, expected, tmp_path, capsys):
    """Not text, too long, or nested so deep that parsing would overflow Python's stack or take minutes (a
    50,000-part dotted key took over 90 s): one line, exit 2, in well under a second."""
    from ensemble import cli
    path = tmp_path / "bad.toml"
    path.write_bytes(content)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "bad.nc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0] and not list(tmp_path.glob("bad.nc*")), err


def test_a_setting_under_parameters_says_where_it_belongs(tmp_path, capsys):
    text = top_runfile(dt=None).replace("[parameters]\n", "[parameters]\ndt = 1e-3\n")
    refused(text, tmp_path, capsys, "parameters.dt: is a run setting: give it at the top of the run file")
    line = refused(top_runfile().replace("[parameters]\n", "[parameters]\nfoo = 1\n"), tmp_path, capsys,
                   "parameters.foo: unknown key")
    assert "known keys: azimuth0, body, c, lambda1, lambda3, spin0, tilt0" in line and "dt" not in line


def test_deep_but_allowed_nesting_and_long_arrays_parse():
    """32 levels of arrays, a key of 32 dotted parts, a 40-value array on one continuation line, and dots and
    brackets inside strings and comments all pass the depth check."""
    assert spec_module._nesting_problem("x = " + "[" * 32 + "]" * 32) is None
    assert spec_module._nesting_problem(".".join(["a"] * 32) + " = 1") is None
    assert spec_module._nesting_problem("k = [\n" + ", ".join(["1.5"] * 40) + ",\n]\n") is None
    assert spec_module._nesting_problem('note = "' + "." * 100 + '"  # ' + "[" * 100) is None


def test_a_first_trial_step_longer_than_the_run_still_runs(write_runfile, tmp_path):
    """dopri5 with dt (its first trial step) = 1e300 s: the chunking's guess of its steps is at least one, and the
    control shrinks the step; the members end near the rk4 result."""
    out = tmp_path / "out.nc"
    assert cli.main(["run", str(write_runfile(top_runfile(method="dopri5", dt=1e300, rtol=1e-10, atol=1e-12))), "-o",
                     str(out), "--quiet"]) == 0
    reference = runner.simulate(parse(top_runfile(method="rk4", dt=1e-4)))
    import xarray as xr

    with xr.open_dataset(out) as ds:
        assert np.allclose(ds.omega, reference.omega, rtol=1e-6, atol=1e-6)


def test_the_same_draws_at_every_sweep_point_when_asked():
    """`draws = "same at every point"` (issue 53): replica r of every sweep point draws what replica r of the
    first does, so that a sweep over methods compares the same members; one sweep point draws as by default, and
    any range of members is drawn as in the whole table."""
    text = top_runfile(method=None, members=5, sweep={"method": ["rk4", "split2", "euler"]})
    default, shared = parse(text), parse(text.replace("seed = 7", 'seed = 7\ndraws = "same at every point"'))
    tilt = members_table(shared)["tilt0"].reshape(3, 5)
    assert np.array_equal(tilt, np.tile(members_table(default)["tilt0"][:5], (3, 1)))
    assert not np.array_equal(members_table(default)["tilt0"][5:10], tilt[0])  # by default each member its own
    assert np.array_equal(members_table(shared, 3, 12)["tilt0"], tilt.ravel()[3:12])
    single = top_runfile(members=5)
    assert np.array_equal(members_table(parse(single.replace("seed = 7", 'seed = 7\ndraws = "same at every point"')))
                          ["tilt0"], members_table(parse(single))["tilt0"])
    with pytest.raises(SpecError, match="draws: must be one of 'each member', 'same at every point'"):
        parse(text.replace("seed = 7", 'seed = 7\ndraws = "shared"'))


def test_parameters_given_member_by_member_from_a_file_or_the_api(tmp_path):
    """A run file's `x0 = { file = "x0.npy" }` and ensemble.run(values=...) (issue 53): one row a member, of the
    whole run or of a sweep point; the result records where they came from; a wrong shape or a file that is not
    an array of numbers is one line naming the key."""
    import hashlib

    import ensemble

    tilts = np.linspace(0.02, 0.2, 4)
    np.save(tmp_path / "tilt.npy", tilts)
    text = top_runfile(members=4, parameters={"tilt0": None, "c": None}, sweep={"c": [1e-4, 2e-4]})
    (tmp_path / "run.toml").write_text(text.replace("[parameters]", '[parameters]\ntilt0 = { file = "tilt.npy" }'))
    ds = ensemble.run(tmp_path / "run.toml", progress=False)
    assert np.array_equal(ds.tilt0.values, np.tile(tilts, 2))  # one row per replica: each point takes them
    digest = hashlib.sha256((tmp_path / "tilt.npy").read_bytes()).hexdigest()[:16]
    assert ds.attrs["parameters_given"] == f"tilt0: {tmp_path / 'tilt.npy'} (sha256 {digest})"
    every = np.linspace(0.05, 0.15, 8)
    ds = ensemble.run(tmp_path / "run.toml", progress=False, values={"tilt0": every})
    assert np.array_equal(ds.tilt0.values, every) and ds.attrs["parameters_given"] == "tilt0: ensemble.run(values=...)"
    with pytest.raises(ensemble.EnsembleError, match=r"has shape \(3,\); it takes one value for each of the run's 8 "
                                                     r"members, or of the 4 of a sweep point"):
        ensemble.run(tmp_path / "run.toml", progress=False, values={"tilt0": every[:3]})
    np.save(tmp_path / "tilt.npy", np.array(["a", "b"]))
    with pytest.raises(SpecError, match=r"parameters.tilt0.file: .*tilt.npy: must hold finite numbers"):
        spec_module.load(tmp_path / "run.toml")


def test_a_bad_member_past_the_checked_ones_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    """A run of more members than its reading checks (CHECKED_BEFORE_START) checks every other range where it is
    integrated: a bad member there is one line naming its range, exit status 2, and nothing is left."""
    from ensemble import members

    monkeypatch.setattr(members, "CHECKED_BEFORE_START", 16)
    tilt0 = np.full(300, 0.1)
    tilt0[250] = 4.0
    np.save(tmp_path / "tilt0.npy", tilt0)
    refused(top_runfile(members=300, parameters={"tilt0": {"file": "tilt0.npy"}}), tmp_path, capsys,
            "parameters.tilt0: must lie in [0, pi] (among members ")


@pytest.mark.parametrize("members, points", [(10, 4), (100_000, 1), (20, 5000), (40_000, 6)])
def test_the_members_checked_before_the_start_cover_every_sweep_point(members, points):
    """Every member of a small run; of a large one the first members of each sweep point (of at most
    SAMPLED_POINTS, spread, the last included), about CHECKED_BEFORE_START in all."""
    from ensemble.members import CHECKED_BEFORE_START, SAMPLED_POINTS, before_start

    spec = parse(top_runfile(members=members, sweep={"c": [1e-6 * k for k in range(points)]},
                             parameters={"c": None}))
    ranges = before_start(spec)
    if spec.n_members <= CHECKED_BEFORE_START:
        assert ranges == [(0, spec.n_members)]
        return
    starts = sorted({start // members for start, _ in ranges})
    assert len(starts) <= SAMPLED_POINTS + 1 and max(np.diff(starts, prepend=0)) <= -(-points // SAMPLED_POINTS)
    assert starts[0] == 0 and starts[-1] == points - 1 and all(stop - start >= 1 for start, stop in ranges)
    assert sum(stop - start for start, stop in ranges) <= CHECKED_BEFORE_START + len(ranges)


def test_launch_ranges_come_from_the_grid_as_from_the_table():
    """runner.one_launch_ranges cuts ranges where the sweep points' method or dt change, without a members table:
    the cuts the table's settings give, for ranges that start and end inside points."""
    spec = parse(top_runfile(members=5, method=None, dt=None, parameters={"c": None},
                             sweep={"method": ["rk4", "split2"], "dt": [1e-3, 2e-3], "c": [1e-4, 2e-4]}))
    for todo in ([(0, spec.n_members)], [(3, 17), (17, 20), (20, 31)], [(0, 1), (4, 6), (8, 12)]):
        expected = []
        for start, stop in todo:
            table = members_table(spec, start, stop)
            expected += [(start + k0, start + k1) for k0, k1 in runner._same_settings(table, 0, stop - start)]
        assert runner.one_launch_ranges(spec, todo) == expected
