"""A run in segments of its samples (several kernel calls, each continuing from the work arrays the last left)
gives the bits of one call, for every kernel family, members that fail midway included."""
import numpy as np
import pytest

from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SCENES
from ensemble.spec import members_table, parse
from tests.conftest import top_runfile
from tests.test_chain import LONG

SWEEPS = '[[sweep]]\nmethod = ["{0}", "{1}"]\n\n[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-8]\n'
# Every kernel family of the body and the chain: a Runge-Kutta tableau, a splitting and the adaptive pair (the
# chain's of runs/work_precision_chain.toml's 4 masses: kernels the suite compiles once)
RUNS = {
    "body": ('scene = "body"\ndt = 1e-3\nt_end = 0.3\nsave_dt = 0.1\nmembers = 130\nseed = 3\n[parameters]\n'
             'lambda1 = 1.0\nlambda2 = 2.0\nlambda3 = 2.5\nc = 0.1\nspin0 = 10.0\ntilt0 = { uniform = [0.1, 1.0] }\n'
             'azimuth0 = 0.5\nspin_axis = 2\n' + SWEEPS.format("euler", "rotations2")),
    "chain": ('scene = "chain"\ndt = 0.01\nt_end = 1.0\nsave_dt = 0.5\nmembers = 70\nseed = 3\n[parameters]\nn = 4\n'
              'm = { uniform = [0.5, 2.0] }\nk = 1.0\nx0 = { normal = [0.0, 0.1] }\nv0 = 0.0\n'
              + SWEEPS.format("euler", "symplectic_euler")),
}

TEXTS = {
    "top": top_runfile(members=130, t_end=1.0, save_dt=0.1, method=None) + SWEEPS.format("rk4", "split2"),
    "body": RUNS["body"],
    "chain": RUNS["chain"],
    "long chain": RUNS["chain"].split("[[sweep]]")[0].replace("n = 4\n", f"n = {LONG}\n")
    + '[[sweep]]\nmethod = ["verlet"]\n',  # the tiled splitting kernel
    "long ring": RUNS["chain"].split("[[sweep]]")[0].replace("n = 4\n", f"n = {LONG}\nboundary = \"periodic\"\n")
    + '[[sweep]]\nmethod = ["verlet"]\n',  # its halos live in the work arrays a later call continues from
}


@pytest.mark.parametrize("scene", TEXTS)
def test_segments_give_the_bits_of_one_call(scene):
    text = TEXTS[scene]
    spec = parse(text)
    table = members_table(spec)
    failed_midway = 0
    for name, step in dict.fromkeys(zip(table["method"], table["dt"])):
        chosen = (table["method"] == name) & ((table["dt"] == step) | METHODS[name].adaptive)
        values = {key: v[chosen] for key, v in table.items()}
        dt = values["dt"] if METHODS[name].adaptive else step
        settings = dict(n_save=spec.n_save, save_dt=spec.save_dt, dt=dt, rtol=values["rtol"], atol=values["atol"],
                        blowup_factor=1.02)  # members whose largest component grows by 2% fail
        whole = launch.integrate(SCENES[spec.scene], METHODS[name], values, spec.constants, **settings)
        for segment in (1, 2):
            call = launch.Launch(SCENES[spec.scene], METHODS[name], values, spec.constants, **settings,
                                 segment=segment)
            call.run(threads=2)
            parts = call.outcome()
            np.testing.assert_array_equal(parts.samples, whole.samples)
            for got, expected in zip(parts[1:], whole[1:]):
                np.testing.assert_array_equal(got, expected)
        failed_midway += np.sum(whole.failure_time > 0)
    if scene != "top":  # no top member grows by 2%; the body shares the top's failure helpers
        assert failed_midway > 0  # the continuation of failed blocks is exercised


def test_each_member_gets_its_own_samples_whatever_block_it_runs_in():
    """A kernel writes each member's samples straight into its own rows (members, count, rows): 70 chain members
    (a full block of 64 and a padded one), the last 6 of them alone (one padded block) and each of three alone
    give the same bits member by member, and they differ between members."""
    rng = np.random.default_rng(3)
    n, members = 2, 70
    values = {"m": rng.uniform(0.5, 2, (members, n)), "k": rng.uniform(0.5, 2, (members, n + 1)),
              "x0": rng.normal(0, 0.1, (members, n)), "v0": rng.normal(0, 0.1, (members, n))}
    constants = {"n": n, "boundary": "fixed"}

    def samples(chosen):
        return launch.integrate(SCENES["chain"], METHODS["verlet"], {k: v[chosen] for k, v in values.items()},
                                constants, n_save=5, save_dt=0.5, dt=0.05).samples

    every = samples(slice(None))
    assert every.shape == (5, 2 * n, members)
    np.testing.assert_array_equal(samples(slice(64, 70)), every[:, :, 64:])
    for member in (0, 63, 69):
        np.testing.assert_array_equal(samples(slice(member, member + 1))[:, :, 0], every[:, :, member])
    assert np.all(np.diff(every[-1, 0]) != 0)
