"""Spring chains: normal modes, the exact solution, and every stepping method against them."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.linalg import expm

from ensemble import cli, runner
from ensemble.engine import launch, sites
from ensemble.engine.sites import TILE_ROWS, block_size, tiles
from ensemble.methods import METHODS
from ensemble.scenes import applies, chain
from ensemble.spec import SpecError, load, parse
from ensemble.tuning import Tuning

CHAIN_METHODS = [name for name, m in METHODS.items() if applies(m, chain) and not (m.closed_form or m.adaptive)]
LONG = 16 * TILE_ROWS + 5  # masses of a chain whose splitting runs in tiles (test_long_chains_are_tiled)
RULES = Tuning()  # untuned: the engine's layout rules


def chain_runfile(parameters=None, **top_level) -> str:
    head = dict(scene='"chain"', method='"verlet"', dt=1e-3, t_end=1.0, save_dt=0.1, members=4, seed=3)
    head.update({k: v for k, v in top_level.items()})
    params = dict(n=2, m=1.0, k=1.0, x0="{ mode = 2, amplitude = 0.1 }")
    params.update(parameters or {})
    lines = [f"{k} = {v}" for k, v in head.items() if v is not None]
    return "\n".join(lines + ["[parameters]"] + [f"{k} = {v}" for k, v in params.items() if v is not None]) + "\n"


def disordered(n, boundary, members=3, seed=0):
    """Members with random masses, springs and initial state: a members table."""
    rng = np.random.default_rng(seed)
    springs = chain.spring_count(n, boundary)
    return {"m": rng.uniform(0.5, 2.0, (members, n)), "k": rng.uniform(0.5, 2.0, (members, springs)),
            "x0": rng.normal(0, 0.1, (members, n)), "v0": rng.normal(0, 0.1, (members, n))}


def relative_error(samples, reference):
    return np.abs(samples - reference).max(axis=(0, 1)) / np.abs(reference).max(axis=(0, 1))


# --- normal modes -------------------------------------------------------------------------------

def test_course_two_mass_modes():
    omega, shapes = chain.normal_modes([2.0, 2.0], [5.0, 5.0, 5.0])
    np.testing.assert_allclose(omega, [np.sqrt(5 / 2), np.sqrt(3 * 5 / 2)], rtol=1e-14)
    np.testing.assert_allclose(shapes / shapes[0], [[1, 1], [1, -1]], atol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 7, 32])
def test_uniform_fixed_chain_frequencies(n):
    m, k = 0.7, 3.0
    omega, _ = chain.normal_modes(np.full(n, m), np.full(n + 1, k))
    j = np.arange(1, n + 1)
    np.testing.assert_allclose(omega, 2 * np.sqrt(k / m) * np.sin(j * np.pi / (2 * (n + 1))), rtol=1e-12)


def test_uniform_ring_and_free_chain_frequencies():
    n, m, k = 8, 1.5, 2.0
    ring, _ = chain.normal_modes(np.full(n, m), np.full(n, k), "periodic")
    expected = np.sort(2 * np.sqrt(k / m) * np.abs(np.sin(np.pi * np.arange(n) / n)))
    np.testing.assert_allclose(ring, expected, rtol=1e-12, atol=1e-12)
    free, _ = chain.normal_modes(np.full(n, m), np.full(n - 1, k), "free")
    np.testing.assert_allclose(free, 2 * np.sqrt(k / m) * np.sin(np.pi * np.arange(n) / (2 * n)), atol=1e-12)


def test_large_mass_ratio_stays_accurate():
    """Two masses 1 and 1e8 between walls: w^2 = k((m1+m2) +- sqrt(m1^2 - m1 m2 + m2^2)) / (m1 m2)."""
    m1, m2, k = 1.0, 1e8, 1.0
    root = np.sqrt(m1 * m1 - m1 * m2 + m2 * m2)
    high = k * (m1 + m2 + root) / (m1 * m2)
    low = 3 * k * k / (m1 * m2 * high)  # the product of the roots, free of cancellation
    omega, shapes = chain.normal_modes([m1, m2], [k, k, k])
    np.testing.assert_allclose(omega ** 2, [low, high], rtol=1e-12)
    mass = np.diag([m1, m2])
    np.testing.assert_allclose(shapes.T @ mass @ shapes, np.eye(2), atol=1e-12)


@pytest.mark.parametrize("boundary", chain.BOUNDARIES)
def test_modes_solve_the_generalized_eigenproblem(boundary):
    values = disordered(6, boundary, members=4)
    omega, shapes = chain.normal_modes(values["m"], values["k"], boundary)
    stiff = chain.stiffness(values["k"], 6, boundary)
    mass = values["m"][:, :, None] * np.eye(6)
    np.testing.assert_allclose(stiff @ shapes, mass @ shapes * omega[:, None, :] ** 2, atol=1e-12)
    np.testing.assert_allclose(np.swapaxes(shapes, 1, 2) @ mass @ shapes, np.broadcast_to(np.eye(6), mass.shape),
                               atol=1e-12)


# --- the exact solution -------------------------------------------------------------------------

@pytest.mark.parametrize("boundary", chain.BOUNDARIES)
def test_exact_matches_the_matrix_exponential(boundary):
    """Including the free and periodic chains' zero mode, which drifts."""
    n = 5
    values = disordered(n, boundary, members=3, seed=1)
    t = np.linspace(0, 7, 15)
    samples = chain.exact(values, {"n": n, "boundary": boundary}, t)
    for j in range(3):
        stiff = chain.stiffness(values["k"][j], n, boundary)
        generator = np.block([[np.zeros((n, n)), np.eye(n)], [-stiff / values["m"][j][:, None], np.zeros((n, n))]])
        y0 = np.concatenate((values["x0"][j], values["v0"][j]))
        reference = np.array([expm(generator * ti) @ y0 for ti in t])
        np.testing.assert_allclose(samples[:, :, j], reference, atol=1e-12 * np.abs(reference).max())
    if boundary != "fixed":  # the centre of mass moves at its initial velocity
        m = values["m"]
        centre = np.einsum("mi,tim->tm", m, samples[:, :n]) / m.sum(axis=1)
        drift = (m * values["v0"]).sum(axis=1) / m.sum(axis=1)
        np.testing.assert_allclose(centre - centre[0], t[:, None] * drift, atol=1e-12)


# --- stepping methods ---------------------------------------------------------------------------

def run(method, values, constants, dt, steps_per_save, n_save, blowup_factor=np.inf):
    """Samples (n_save, 2n, members); members never fail unless blowup_factor is given."""
    return launch.integrate(chain, METHODS[method], values, constants, n_save=n_save, save_dt=dt * steps_per_save,
                            dt=dt, blowup_factor=blowup_factor).samples


# Rings step with the same kernels but for the ghost masses, which every splitting and every tableau share: a
# splitting and a tableau on rings (each kernel compiled is ten seconds of the test suite's first run).
CONVERGENCE_CASES = [(method, "fixed") for method in CHAIN_METHODS] + [("verlet", "periodic"), ("rk4", "periodic")]


@pytest.mark.parametrize("method, boundary", CONVERGENCE_CASES)
def test_convergence_order(method, boundary):
    n, t_end = 4, 2.0
    constants = {"n": n, "boundary": boundary}
    values = disordered(n, boundary)
    exact = chain.exact(values, constants, [0.0, t_end])
    dts = {1: (2e-4, 1e-4, 5e-5), 2: (1e-2, 5e-3, 2.5e-3), 4: (4e-2, 2e-2, 1e-2)}[METHODS[method].order]
    errors = [relative_error(run(method, values, constants, dt, round(t_end / dt), 2), exact) for dt in dts]
    slopes = np.diff(np.log(errors), axis=0) / np.diff(np.log(dts))[:, None]
    np.testing.assert_allclose(slopes, METHODS[method].order, atol=0.15)


def test_symplectic_methods_keep_energy_bounded_and_euler_does_not():
    n, h, steps = 4, 0.02, 100_000
    constants = {"n": n, "boundary": "fixed"}
    values = disordered(n, "fixed", members=2)
    drift = {}
    for method in ("verlet", "yoshida4", "euler"):
        samples = run(method, values, constants, h, steps // 100, 101)
        x, v = samples[:, :n].transpose(2, 0, 1), samples[:, n:].transpose(2, 0, 1)
        e = chain.energy(x, v, values["m"][:, None], values["k"][:, None], "fixed")
        drift[method] = np.abs(e / e[:, :1] - 1)
    # verlet's energy error is O((w h)^2) and does not grow: the last half is no worse than the first
    for method, bound in (("verlet", 1e-3), ("yoshida4", 1e-6)):
        assert drift[method].max() < bound
        assert drift[method][:, 51:].max() < 2 * drift[method][:, 1:51].max()
    assert np.all(np.diff(drift["euler"][:, 1:], axis=1) > 0) and drift["euler"][:, -1].min() > 1.0


def test_verlet_is_reversible():
    n, h, steps = 4, 1e-2, 2000
    constants = {"n": n, "boundary": "fixed"}
    values = disordered(n, "fixed")
    forward = run("verlet", values, constants, h, steps, 2)[1]
    back = run("verlet", {**values, "x0": forward[:n].T, "v0": forward[n:].T}, constants, -h, steps, 2)[1]
    start = np.concatenate((values["x0"].T, values["v0"].T))
    np.testing.assert_allclose(back, start, atol=1e-12 * np.abs(start).max())


def numpy_splitting(method, values, constants, h, steps):
    """State (2n, members) after `steps` steps of a splitting method applied one piece at a time, with NumPy
    (fixed or free ends, or a ring)."""
    n = constants["n"]
    state, rate = chain.inputs(values, constants)
    x, v = state[:n].copy(), state[n:].copy()
    with_walls = np.zeros((n + 2, x.shape[1]))
    for _ in range(steps):
        for piece, fraction in METHODS[method].splitting.sequence:
            if METHODS[method].splitting.pieces[piece] == "kick":
                with_walls[1:-1] = x
                if constants["boundary"] == "periodic":
                    with_walls[0], with_walls[-1] = x[-1], x[0]
                v += h * fraction * (rate[:n] * (with_walls[:-2] - x) + rate[n:] * (with_walls[2:] - x))
            else:
                x += h * fraction * v
    return np.concatenate((x, v))


@pytest.mark.parametrize("method, boundary", [("verlet", "fixed"), ("verlet", "free"), ("yoshida4", "fixed"),
                                              ("yoshida4", "periodic")])
def test_long_chains_step_in_tiles_as_one_piece_at_a_time(method, boundary):
    """A long chain's splitting kernel runs many pieces at once over tiles of masses (a ring with copies of its
    other end beyond each end); 37 steps a save interval make chunks of pieces that do not divide it."""
    n, h = LONG, 0.05
    constants = {"n": n, "boundary": boundary}
    values = disordered(n, boundary, members=5)
    samples = run(method, values, constants, h, 37, 3)
    reference = numpy_splitting(method, values, constants, h, 74)
    np.testing.assert_allclose(samples[-1], reference, rtol=0, atol=1e-12 * np.abs(reference).max())


def test_a_long_rings_masses_take_the_same_bits_wherever_its_ends_are():
    """A tiled ring turned by 40 masses (its masses, springs and state rolled): the same bits, turned, so the
    masses beside its ends (in the halos' reach) step as those in the middle do."""
    n, turn = LONG, 40
    constants = {"n": n, "boundary": "periodic"}
    values = disordered(n, "periodic", members=5)
    turned = {name: np.roll(v, turn, axis=1) for name, v in values.items()}
    samples = run("verlet", values, constants, 0.05, 37, 3)
    samples_turned = run("verlet", turned, constants, 0.05, 37, 3)
    x, v = samples[:, :n], samples[:, n:]
    np.testing.assert_array_equal(samples_turned, np.concatenate((np.roll(x, turn, 1), np.roll(v, turn, 1)), 1))


def test_long_chains_are_tiled(monkeypatch):
    """The tiling tests' chains run in tiles on this host; short ones do not, even where the L1 cache is small."""
    assert tiles(LONG, block_size({"n": LONG}, METHODS["verlet"], RULES), RULES)
    assert not tiles(2 * TILE_ROWS, block_size({"n": 2 * TILE_ROWS}, METHODS["verlet"], RULES), RULES)
    monkeypatch.setattr(sites, "l1_data_bytes", lambda: 1024)
    assert tiles(2 * TILE_ROWS + 1, 8, RULES) and not tiles(2 * TILE_ROWS, 8, RULES)


def test_a_members_bits_do_not_depend_on_its_block(monkeypatch):
    """The same 20 members of a 4-mass chain in blocks of 16 and of 64 (the rule's, which test_convergence_order
    compiles): the same bits."""
    constants = {"n": 4, "boundary": "fixed"}
    values = disordered(4, "fixed", members=20)
    samples = []
    for block in (16, 64):
        monkeypatch.setattr(sites, "block_size", lambda constants, method, tuning, block=block: block)
        samples.append(run("verlet", values, constants, 0.05, 7, 3))
    np.testing.assert_array_equal(samples[0], samples[1])


def test_a_chain_dopri5_member_does_not_depend_on_its_block_and_an_underflow_stops_it_alone(monkeypatch):
    """20 members of a 4-mass chain in dopri5 blocks of 8 and of 16 (the rule's): the same steps and the same
    values to a few units in the last place (unlike a splitting's, a pair's rounding depends on its block: LLVM's
    fast-math code differs), within rtol of the exact solution; the member given rtol = atol = 1e-300 underflows
    (status 2, NaN from then on), the others run."""
    constants = {"n": 4, "boundary": "fixed"}
    values = disordered(4, "fixed", members=20)
    rtol = np.where(np.arange(20) == 5, 1e-300, 1e-9)
    atol = np.where(np.arange(20) == 5, 1e-300, 1e-12)
    outcomes = []
    for block in (8, 16):
        monkeypatch.setattr(sites, "block_size", lambda constants, method, tuning, block=block: block)
        outcomes.append(launch.integrate(chain, METHODS["dopri5"], values, constants, n_save=4, save_dt=0.5,
                                         rtol=rtol, atol=atol))
    np.testing.assert_allclose(outcomes[0].samples, outcomes[1].samples, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(outcomes[0].counts, outcomes[1].counts)
    out, running = outcomes[0], np.arange(20) != 5
    np.testing.assert_array_equal(out.status, np.where(running, 0, 2))
    assert np.all(np.isnan(out.samples[1:, :, 5]))
    exact = chain.exact(values, constants, np.arange(4) * 0.5)
    assert relative_error(out.samples[:, :, running], exact[:, :, running]).max() < 1e-7


def test_splitting_blocks_are_two_vectors_of_the_host_unless_they_outgrow_its_l1(monkeypatch, tmp_path):
    for index, (level, kind, size) in enumerate([("1", "Instruction", "32K"), ("1", "Data", "48K"),
                                                 ("2", "Unified", "1024K")]):
        folder = tmp_path / f"index{index}"
        folder.mkdir()
        for name, text in (("level", level), ("type", kind), ("size", size)):
            (folder / name).write_text(text + "\n")
    assert sites.l1_data_bytes.__wrapped__(tmp_path) == 48 * 1024
    assert sites.l1_data_bytes.__wrapped__(tmp_path / "absent") == 32 * 1024
    (tmp_path / "index1" / "size").write_text("48 KB\n")  # not sysfs's form: the default, not a crash
    assert sites.l1_data_bytes.__wrapped__(tmp_path) == 32 * 1024
    verlet = METHODS["verlet"]
    for doubles, l1, expected in ((8, 48 * 1024, {16: 16, 64: 16, 100: 8, 1024: 8}),
                                  (4, 32 * 1024, {16: 8, 127: 8, 128: 4})):
        monkeypatch.setattr(sites, "vector_doubles", lambda doubles=doubles: doubles)
        monkeypatch.setattr(sites, "l1_data_bytes", lambda l1=l1: l1)
        assert {n: sites.block_size({"n": n}, verlet, RULES) for n in expected} == expected
    assert sites.block_size({"n": 2}, verlet, RULES) == 64
    # an adaptive pair's 20n + 15 rows: 64 members fit 48 KiB up to n = 4 and 32 KiB up to n = 2, then 16
    # members below 16 masses; 16 members fit 48 KiB at n = 16, not at n = 24; never fewer than 8
    dopri5 = METHODS["dopri5"]
    for doubles, l1, expected in ((8, 48 * 1024, {2: 64, 4: 64, 5: 16, 15: 16, 16: 16, 24: 8, 128: 8}),
                                  (4, 32 * 1024, {2: 64, 3: 16, 15: 16, 16: 8, 128: 8})):
        monkeypatch.setattr(sites, "vector_doubles", lambda doubles=doubles: doubles)
        monkeypatch.setattr(sites, "l1_data_bytes", lambda l1=l1: l1)
        assert {n: sites.block_size({"n": n}, dopri5, RULES) for n in expected} == expected


def test_course_chain_in_mode_two_oscillates_at_sqrt_3k_over_m(write_runfile):
    """Two masses m = 2 kg, springs k = 5 N/m: x1 = -x2 = A cos(w t), w = sqrt(3k/m).

    Verlet shows the frequency (2/h) asin(w h / 2) instead of w; both are checked.
    """
    text = chain_runfile({"m": 2.0, "k": 5.0}, t_end=10.0, save_dt=0.01, dt=1e-2)
    w = np.sqrt(3 * 5.0 / 2.0)
    for method, frequency in (("exact", w), ("verlet", 2 / 1e-2 * np.arcsin(w * 1e-2 / 2))):
        ds = runner.simulate(load(write_runfile(text.replace('"verlet"', f'"{method}"'), f"{method}.toml")))
        x = ds.x.values
        np.testing.assert_array_equal(x[:, :, 0], -x[:, :, 1])
        expected = np.broadcast_to(0.1 * np.cos(frequency * ds.t.values), x[:, :, 0].shape)
        np.testing.assert_allclose(x[:, :, 0], expected, rtol=0, atol=1e-13)


def test_dataset_energy_and_parameters(write_runfile):
    """Energy in the file equals the hand-written spring sum; parameters have their per-site dims."""
    text = chain_runfile({"n": 4, "m": "{ uniform = [0.5, 2.0] }", "k": "[1.0, 2.0, 3.0, 4.0, 5.0]",
                          "x0": "{ normal = [0.0, 0.1] }"}, method='"rk4"')
    ds = runner.simulate(load(write_runfile(text)))
    assert ds.x.dims == ("member", "t", "site") and ds.sizes["site"] == 4 and ds.sizes["spring"] == 5
    assert ds.m.dims == ("member", "site") and ds.k.dims == ("member", "spring")
    assert ds.attrs["n"] == 4 and ds.attrs["boundary"] == "fixed"
    np.testing.assert_array_equal(ds.k.values, np.tile([1.0, 2.0, 3.0, 4.0, 5.0], (4, 1)))
    x, v, m, k = ds.x.values, ds.v.values, ds.m.values[:, None], ds.k.values[:, None]
    walls = np.pad(x, ((0, 0), (0, 0), (1, 1)))
    by_hand = 0.5 * (m * v ** 2).sum(-1) + 0.5 * (k * np.diff(walls, axis=-1) ** 2).sum(-1)
    np.testing.assert_allclose(ds.energy.values, by_hand, rtol=1e-14)
    np.testing.assert_allclose(ds.energy.values / ds.energy.values[:, :1], 1, atol=1e-9)  # rk4, small steps


@pytest.mark.parametrize("boundary", ["fixed", "free", "periodic"])
def test_observed_energy_is_the_models_spring_sum(boundary):
    """The run's compiled energy (physics.sample_energy, from member-major samples) against model.energy (numpy,
    its own extensions) on random states, masses and springs: the same sums in another order."""
    rng = np.random.default_rng(7)
    for n in (2, 3, 16, 129):
        samples = rng.standard_normal((9, 5, 2 * n))  # (members, t, (x; v))
        m, k = rng.uniform(0.5, 2.0, (9, n)), rng.uniform(0.5, 2.0, (9, chain.spring_count(n, boundary)))
        observed = chain.observe(samples.transpose(1, 2, 0), ("energy",), {"m": m, "k": k},
                                 {"n": n, "boundary": boundary})["energy"]
        expected = chain.energy(samples[..., :n], samples[..., n:], m[:, None], k[:, None], boundary)
        np.testing.assert_allclose(observed, expected, rtol=1e-14)


@pytest.mark.parametrize("n", [4, LONG])  # blocks of 64 members, and the tiled kernel of the tiling tests
def test_chain_results_do_not_depend_on_chunk_size(n, write_runfile):
    text = chain_runfile({"n": n, "m": "{ uniform = [0.5, 2.0] }", "x0": "{ normal = [0.0, 0.1] }"},
                         members=70, t_end=0.2)
    spec = load(write_runfile(text))
    xr.testing.assert_equal(runner.simulate(spec, chunk=16).drop_attrs(), runner.simulate(spec).drop_attrs())


BAD_CHAINS = {
    "n below 1": ({"n": 0}, "parameters.n"),
    "n not an integer": ({"n": 2.5}, "parameters.n"),
    "masses list too long": ({"m": "[1.0, 2.0, 3.0]"}, "parameters.m"),
    "springs list too short": ({"k": "[1.0, 2.0]"}, "parameters.k"),
    "free chain springs": ({"boundary": '"free"', "k": "[1.0, 2.0]"}, "parameters.k"),
    "mass zero": ({"m": 0.0}, "parameters.m"),
    "negative spring in a list": ({"k": "[1.0, -2.0, 1.0]"}, "parameters.k"),
    "drawn negative mass": ({"m": "{ normal = [0.1, 1.0] }"}, "parameters.m"),
    "mode above n": ({"x0": "{ mode = 3, amplitude = 0.1 }"}, "parameters.x0.mode"),
    "mode zero": ({"v0": "{ mode = 0, amplitude = 0.1 }"}, "parameters.v0.mode"),
    "unknown boundary": ({"boundary": '"open"'}, "parameters.boundary"),
}


@pytest.mark.parametrize("case", list(BAD_CHAINS))
def test_bad_chain_input(case, write_runfile, tmp_path, capsys):
    change, key = BAD_CHAINS[case]
    text = chain_runfile(change)
    with pytest.raises(SpecError) as error:
        parse(text)
    assert error.value.key == key
    out = tmp_path / "out.nc"
    assert cli.main(["run", str(write_runfile(text)), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and f" {key}: " in err and not out.exists()


def test_run_constants_cannot_be_swept():
    with pytest.raises(SpecError) as error:
        parse(chain_runfile({"n": None}) + "[sweep]\nn = [2, 3]\n")
    assert error.value.key == "sweep.n"


def test_chain_output_passes_the_cf_compliance_checker(write_runfile, tmp_path):
    out = tmp_path / "chain.nc"
    text = chain_runfile({"n": 4, "boundary": '"periodic"', "k": "{ uniform = [1.0, 2.0] }"})
    runner.run(load(write_runfile(text)), out, progress=False)
    executable = shutil.which("compliance-checker", path=str(Path(sys.executable).parent)) or "compliance-checker"
    checker = subprocess.run([executable, "--test=cf:1.9", "-f", "json", "-o", "-", str(out)],
                             capture_output=True, text=True)
    report = json.loads(checker.stdout)["cf:1.9"]
    assert report["high_count"] == 0, report["high_priorities"]


@pytest.mark.parametrize("boundary", ["fixed", "free", "periodic"])
def test_stiffness_is_d_transpose_diag_k_d(boundary):
    """The spring-by-spring sum equals the dense product D^T diag(k) D exactly, for one member and for a batch."""
    rng = np.random.default_rng(3)
    for n in (2, 3, 9):
        d = chain.incidence(n, boundary)
        k = rng.uniform(0.5, 2.0, (2, 3, d.shape[0]))
        dense = np.einsum("si,abs,sj->abij", d, k, d)
        np.testing.assert_array_equal(chain.stiffness(k, n, boundary), dense)
        np.testing.assert_array_equal(chain.stiffness(k[0, 0], n, boundary), dense[0, 0])


@pytest.mark.parametrize("boundary", ["fixed", "free", "periodic"])
def test_extensions_in_linear_time_are_the_incidence_product(boundary):
    """The O(n) spring extensions the energy uses equal the dense D @ x, bit for bit (products by 1, -1 and 0
    are exact), for a batch of members and samples."""
    rng = np.random.default_rng(4)
    for n in (2, 3, 17):
        x = rng.normal(size=(3, 5, n))
        np.testing.assert_array_equal(chain.extensions(x, boundary), x @ chain.incidence(n, boundary).T)


def test_kernel_work_arrays_start_on_a_cache_line():
    """cache_line_array: `size` values starting on a 64-byte boundary, for sizes that leave every remainder."""
    from numba import njit

    from ensemble.engine.blocks import CACHE_LINE, cache_line_array

    @njit
    def address_and_size(size):
        work = cache_line_array(size)
        work[:] = 1.0  # every value is inside the array's buffer
        return work.ctypes.data, work.size

    for size in range(1, 20):
        address, got = address_and_size(size)
        assert address % CACHE_LINE == 0 and got == size


def _example_chain_error(step: float) -> float:
    """ensemble.engine.sites_kernels's Runge-Kutta kernel, called as a module: its example (4 unit masses between
    walls, unit springs, blocks of 4, Bogacki and Shampine's third-order weights) through 1 s in steps of `step`
    (s), from sample 0 in one call and the save interval in a second (a resume), against the matrix exponential
    of x'' = -K x: the largest error."""
    from ensemble.engine import sites_kernels as example
    n, B, t_end = example.N, example.B, 1.0
    K = 2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    state0 = np.random.default_rng(3).normal(size=(1, 2 * n, B))
    rate = np.ones((1, 2 * n, B))  # every coupling 1, the walls' included
    flow = expm(t_end * np.block([[np.zeros((n, n)), np.eye(n)], [-K, np.zeros((n, n))]]))
    status, failure_time, progress, limit = np.zeros(B), np.zeros(B), np.zeros(1, np.int64), np.full(B, 1e6)
    works = np.zeros((1, example.stage_rows(n, example.S)[-1] * B))
    for start in (0, 1):
        samples = np.full((B, 1, 2 * n), np.nan)
        example.runge_kutta_kernel(state0, rate, step, round(t_end / step), limit, samples, status, failure_time,
                                   progress, works, start, 0, 1)
    assert np.all(status == 0)
    return np.max(np.abs(samples[:, 0] - np.einsum("rc,cj->jr", flow, state0[0])))


def test_the_sites_kernels_module_runs_its_example_chain_at_its_order():
    """The module's Runge-Kutta kernel, called as it stands (its splitting and adaptive kernels run in every chain
    kernel's file: the tests of this file)."""
    coarse, fine = _example_chain_error(4e-3), _example_chain_error(2e-3)
    assert fine < 2e-8
    assert 2.9 < np.log2(coarse / fine) < 3.1
