"""The methods as data: tableaus and compositions checked for consistency."""
import numpy as np
import pytest

from ensemble.methods import METHODS, YOSHIDA4, Splitting

TABLEAUS = {name: m.tableau for name, m in METHODS.items() if m.tableau}
SPLITTINGS = {name: m.splitting for name, m in METHODS.items() if m.splitting}


@pytest.mark.parametrize("name", TABLEAUS)
def test_tableau_is_consistent(name):
    tableau = TABLEAUS[name]
    a = np.array(tableau.square_a()).reshape(tableau.stages, tableau.stages)
    assert np.sum(tableau.b) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(a.sum(axis=1), tableau.c, atol=1e-15)
    assert np.all(np.triu(a) == 0)  # explicit


def test_rk4_order_conditions():
    """The eight order conditions up to order four."""
    t = METHODS["rk4"].tableau
    a, b, c = np.array(t.square_a()).reshape(4, 4), np.array(t.b), np.array(t.c)
    for value, expected in [(b @ c, 1 / 2), (b @ c**2, 1 / 3), (b @ a @ c, 1 / 6), (b @ c**3, 1 / 4),
                            (b @ (c * (a @ c)), 1 / 8), (b @ a @ c**2, 1 / 12), (b @ a @ a @ c, 1 / 24)]:
        assert value == pytest.approx(expected, abs=1e-15)


def test_yoshida_weights_sum_to_one_and_cancel_the_third_order_error():
    assert sum(YOSHIDA4) == pytest.approx(1.0, abs=1e-15)
    assert sum(w**3 for w in YOSHIDA4) == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize("name", SPLITTINGS)
def test_each_piece_advances_a_whole_step(name):
    """Every piece of a consistent splitting is applied for a total of one step."""
    totals = {}
    for piece, fraction in SPLITTINGS[name].sequence:
        totals[piece] = totals.get(piece, 0.0) + fraction
    assert set(totals) == set(range(len(SPLITTINGS[name].pieces)))
    assert all(total == pytest.approx(1.0, abs=1e-14) for total in totals.values())


@pytest.mark.parametrize("name", ["verlet", "split2", "yoshida4", "split4", "rotations2", "rotations4"])
def test_symmetric_methods_read_the_same_backwards(name):
    sequence = SPLITTINGS[name].sequence
    np.testing.assert_allclose([f for _, f in sequence], [f for _, f in reversed(sequence)], atol=1e-15)
    assert [p for p, _ in sequence] == [p for p, _ in reversed(sequence)]


def test_composition_merges_adjacent_pieces():
    base = Splitting(("kick", "drift"), ((0, 0.5), (1, 1.0), (0, 0.5)))
    assert base.composed((0.5, 0.5)).sequence == ((0, 0.25), (1, 0.5), (0, 0.5), (1, 0.5), (0, 0.25))
