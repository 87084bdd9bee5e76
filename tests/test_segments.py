"""A run in segments of its samples (several kernel calls, each continuing from the work arrays the last left)
gives the bits of one call, for every kernel family, members that fail midway included."""
import numpy as np
import pytest

from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SCENES
from ensemble.spec import members_table, parse
from tests.conftest import top_runfile
from tests.test_cache import RUNS, SWEEPS
from tests.test_chain import LONG

TEXTS = {
    "top": top_runfile(members=130, t_end=1.0, save_dt=0.1, method=None) + SWEEPS.format("rk4", "split2"),
    "body": RUNS["body"],
    "chain": RUNS["chain"],
    "long chain": RUNS["chain"].split("[[sweep]]")[0].replace("n = 1\n", f"n = {LONG}\n")
    + '[[sweep]]\nmethod = ["verlet"]\n',  # the tiled splitting kernel
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


def test_member_major_is_the_blocked_samples_member_by_member():
    """launch.member_major against numpy's transpose of the block layout, the padding members cut off."""
    rng = np.random.default_rng(3)
    for count, blocks, rows, block, members in ((7, 3, 5, 4, 10), (1, 1, 3, 128, 1), (4, 2, 32, 8, 16)):
        samples = rng.standard_normal((count, blocks, rows, block))
        by_numpy = samples.transpose(1, 3, 0, 2).reshape(blocks * block, count, rows)[:members]
        np.testing.assert_array_equal(launch.member_major(samples, members), by_numpy)
