"""Inertia tensors against closed forms, an independent integration, and the theorems they must obey."""
import json

import numpy as np
import pytest
from scipy import integrate
from scipy.spatial.transform import Rotation

from ensemble import cli, inertia
from ensemble.inertia import SHAPES

COURSE_PLATE = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)]
L_SHAPE = [(0, 0), (0, 2), (1, 2), (1, 1), (3, 1), (3, 0)]  # clockwise, not convex
ROOT_HALF = np.sqrt(0.5)


def star(points: int, seed: int) -> np.ndarray:
    """A star-shaped (simple, generally non-convex) polygon with random radii, away from the origin."""
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0, 2 * np.pi, points))
    radii = rng.uniform(0.3, 1.5, points)
    return np.column_stack((radii * np.cos(angles) + 0.7, radii * np.sin(angles) - 0.4))


def integrated_tensor(vertices, mass, origin) -> np.ndarray:
    """The defining integral of a uniform lamina's tensor, by nested scipy quad over vertical strips."""
    v = np.asarray(vertices, dtype=float)
    edges = list(zip(v, np.roll(v, -1, axis=0)))
    ox, oy, oz = origin

    def strips(x):  # the y intervals inside the polygon at this x (even-odd rule)
        ys = sorted(a[1] + (x - a[0]) * (b[1] - a[1]) / (b[0] - a[0])
                    for a, b in edges if min(a[0], b[0]) < x < max(a[0], b[0]))
        return list(zip(ys[::2], ys[1::2]))

    def over_area(f):
        def column(x):
            return sum(integrate.quad(lambda y: f(x, y), lo, hi, epsabs=1e-14, epsrel=1e-12)[0] for lo, hi in strips(x))
        return integrate.quad(column, v[:, 0].min(), v[:, 0].max(), points=np.unique(v[:, 0]),
                              epsabs=0, epsrel=1e-12, limit=200)[0]

    area = over_area(lambda x, y: 1.0)
    sigma = mass / area
    xx = sigma * over_area(lambda x, y: (x - ox) ** 2 + oz**2)
    yy = sigma * over_area(lambda x, y: (y - oy) ** 2 + oz**2)
    xy = sigma * over_area(lambda x, y: (x - ox) * (y - oy))
    xz = sigma * over_area(lambda x, y: (x - ox) * -oz)
    yz = sigma * over_area(lambda x, y: (y - oy) * -oz)
    zz = sigma * over_area(lambda x, y: (x - ox) ** 2 + (y - oy) ** 2)
    return np.array([[yy, -xy, -xz], [-xy, xx, -yz], [-xz, -yz, zz]])


def test_the_course_plate_exactly():
    mass, leg = 3.0, 2.0
    body = inertia.polygon(mass, np.array(COURSE_PLATE) * leg)
    expected = mass * leg**2 / 12 * np.array([[2, -1, 0], [-1, 2, 0], [0, 0, 4]])
    np.testing.assert_allclose(body.tensor(), expected, rtol=0, atol=1e-15 * mass * leg**2)
    moments, axes = inertia.principal(body.tensor())
    np.testing.assert_allclose(moments, mass * leg**2 / 12 * np.array([1, 3, 4]), rtol=1e-14)
    np.testing.assert_allclose(axes, [[ROOT_HALF, -ROOT_HALF, 0], [ROOT_HALF, ROOT_HALF, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(body.centre, [leg / 3, leg / 3, 0], rtol=1e-15)


def test_vertex_order_and_a_closing_vertex_change_nothing():
    reference = inertia.polygon(1.0, L_SHAPE).tensor()
    for vertices in (L_SHAPE[::-1], L_SHAPE + L_SHAPE[:1], np.roll(L_SHAPE, 2, axis=0)):
        np.testing.assert_allclose(inertia.polygon(1.0, vertices).tensor(), reference, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("vertices", [COURSE_PLATE, L_SHAPE, star(9, 1), star(14, 2)],
                         ids=["triangle", "L", "star9", "star14"])
def test_polygon_matches_integration_of_the_definition(vertices):
    origin = (0.3, -0.2, 0.5)  # off the plane too, so every entry is non-zero
    computed = inertia.polygon(2.5, vertices).tensor(origin)
    np.testing.assert_allclose(computed, integrated_tensor(vertices, 2.5, origin), rtol=1e-9,
                               atol=1e-11 * np.abs(computed).max())


def test_regular_polygon_polar_moment_closed_form():
    """A regular n-gon of circumradius R: J = M R^2 (1 + 2 cos^2(pi/n)) / 6, the same about every in-plane axis."""
    for n in (3, 4, 7, 1000):
        angles = 2 * np.pi * np.arange(n) / n + 0.3
        vertices = 0.8 * np.column_stack((np.cos(angles), np.sin(angles)))
        tensor = inertia.polygon(2.0, vertices).tensor()
        polar = 2.0 * 0.8**2 * (1 + 2 * np.cos(np.pi / n) ** 2) / 6
        np.testing.assert_allclose(np.diag(tensor), [polar / 2, polar / 2, polar], rtol=1e-12)
        assert abs(tensor[0, 1]) < 1e-14


def laminae():
    """Every lamina, placed off the origin and turned about z."""
    turn = Rotation.from_euler("z", 0.7)
    return {
        "polygon": inertia.polygon(1.3, star(11, 5)),
        "disk": inertia.disk(0.5, 0.2).placed(turn, (0.3, -0.1, 0)),
        "annulus": inertia.annulus(0.1, 0.1, 0.13).placed(turn, (0.05, 0.2, 0)),
        "rectangle": inertia.rectangle(2.0, 0.4, 0.1).placed(turn, (-0.3, 0.1, 0)),
    }


@pytest.mark.parametrize("name", ["polygon", "disk", "annulus", "rectangle"])
def test_perpendicular_axis_theorem_for_every_lamina(name):
    body = laminae()[name]
    for origin in ((0, 0, 0), (0.4, -0.7, 0), (-1.0, 2.0, 0)):
        tensor = body.tensor(origin)
        assert tensor[2, 2] == pytest.approx(tensor[0, 0] + tensor[1, 1], rel=1e-13)
        assert tensor[0, 2] == tensor[1, 2] == 0


def test_composite_equals_the_sum_of_its_parts():
    # The L shape as two placed rectangles: one body, one tensor, about any point.
    density = 1.7  # kg per m2
    lower = inertia.rectangle(density * 3, 3, 1).placed(position=(1.5, 0.5, 0))
    upper = inertia.rectangle(density * 1, 1, 1).placed(position=(0.5, 1.5, 0))
    whole = inertia.polygon(density * 4, L_SHAPE)
    both = lower + upper
    for origin in ((0, 0, 0), (2, -1, 0.5)):
        np.testing.assert_allclose(both.tensor(origin), whole.tensor(origin), rtol=1e-13)
        np.testing.assert_allclose(both.tensor(origin), lower.tensor(origin) + upper.tensor(origin), rtol=1e-13)
    np.testing.assert_allclose(both.centre, whole.centre, rtol=1e-14)


@pytest.mark.parametrize("inner, outer, whole, core_share", [
    (lambda m: inertia.disk(m, 0.6), lambda m: inertia.annulus(m, 0.6, 1.0), lambda m: inertia.disk(m, 1.0), 0.6**2),
    (lambda m: inertia.cylinder(m, 0.6, 0.3), lambda m: inertia.hollow_cylinder(m, 0.6, 1.0, 0.3),
     lambda m: inertia.cylinder(m, 1.0, 0.3), 0.6**2),
    (lambda m: inertia.sphere(m, 0.6), lambda m: inertia.hollow_sphere(m, 0.6, 1.0), lambda m: inertia.sphere(m, 1.0),
     0.6**3),
], ids=["disk+annulus", "cylinder+tube", "ball+shell"])
def test_a_solid_is_its_core_plus_its_shell(inner, outer, whole, core_share):
    """Same density: a core of radius 0.6 plus the shell from 0.6 to 1 is the whole body of radius 1."""
    total = 2.0
    parts = inner(total * core_share) + outer(total * (1 - core_share))
    np.testing.assert_allclose(parts.tensor(), whole(total).tensor(), rtol=1e-14)


def test_thin_and_flat_limits():
    m, r = 1.5, 0.4
    shell = inertia.hollow_sphere(m, r * (1 - 1e-12), r).tensor()
    np.testing.assert_allclose(np.diag(shell), 2 * m * r**2 / 3, rtol=1e-11)
    np.testing.assert_allclose(inertia.cylinder(m, r, 1e-9).tensor(), inertia.disk(m, r).tensor(), rtol=1e-12)
    np.testing.assert_allclose(inertia.box(m, 0.3, 0.2, 1e-9).tensor(), inertia.rectangle(m, 0.3, 0.2).tensor(),
                               rtol=1e-12)
    tube = inertia.hollow_cylinder(m, r * (1 - 1e-9), r, 1e-9).tensor()
    np.testing.assert_allclose(np.diag(tube), [m * r**2 / 2, m * r**2 / 2, m * r**2], rtol=1e-8)


def test_point_masses_and_the_parallel_axis_shift():
    masses, positions = [1.0, 2.0, 3.0], [(1, 0, 0), (0, 2, 0), (0, 0, -1)]
    body = inertia.points(masses, positions)
    direct = sum(m * (np.dot(p, p) * np.eye(3) - np.outer(p, p)) for m, p in zip(masses, np.array(positions, float)))
    np.testing.assert_allclose(body.tensor(), direct, rtol=1e-14, atol=1e-14 * np.abs(direct).max())
    np.testing.assert_allclose(body.centre, np.dot(masses, positions) / 6, rtol=1e-14)
    np.testing.assert_allclose(body.tensor(body.centre), body.inertia, atol=1e-14 * np.abs(direct).max())


def tilted_body():
    """A composite with no symmetry: a box, a ball off to one side and a triangle, each placed."""
    return (inertia.box(1.0, 0.3, 0.2, 0.1).placed(Rotation.from_euler("xyz", [0.3, -0.2, 1.0]), (0.1, 0, 0))
            + inertia.sphere(0.4, 0.05).placed(position=(0.3, 0.2, -0.1))
            + inertia.polygon(0.2, COURSE_PLATE).placed(Rotation.from_euler("x", 1.2), (0, 0.4, 0)))


def test_principal_moments_do_not_change_when_the_body_turns():
    body = tilted_body()
    moments, axes = inertia.principal(body.inertia)
    for seed in range(5):
        turn = Rotation.random(random_state=seed)
        turned = body.placed(turn, (1.0, -2.0, 0.5))
        turned_moments, turned_axes = inertia.principal(turned.inertia)
        np.testing.assert_allclose(turned_moments, moments, rtol=1e-13)
        # each principal axis turns with the body (up to its sign)
        overlap = np.abs(np.sum(turn.as_matrix() @ axes * turned_axes, axis=0))
        np.testing.assert_allclose(overlap, 1.0, rtol=1e-9)


def test_principal_axes_are_a_right_handed_frame_with_fixed_signs():
    for tensor in (tilted_body().tensor((0.2, 0.1, 0)), inertia.polygon(1.0, COURSE_PLATE).tensor(),
                   inertia.cylinder(1.0, 0.1, 1.0).placed(Rotation.from_euler("y", 0.4)).tensor()):
        moments, axes = inertia.principal(tensor)
        np.testing.assert_allclose(axes.T @ axes, np.eye(3), atol=1e-14)
        assert np.linalg.det(axes) == pytest.approx(1.0, abs=1e-14)
        np.testing.assert_allclose(tensor @ axes, axes * moments, atol=1e-13 * moments.max())
        for column in (axes[:, 0], axes[:, 2]):
            assert column[np.argmax(np.abs(column) > np.abs(column).max() * (1 - 1e-9))] > 0
        again = inertia.principal(-(-tensor))
        np.testing.assert_array_equal(again[1], axes)


def test_shapes_accept_arrays_one_body_each():
    masses, outer = np.array([0.1, 0.2, 0.3]), np.array([0.13, 0.15, 0.2])
    bodies = inertia.annulus(masses, 0.1, outer)
    assert bodies.inertia.shape == (3, 3, 3)
    for i in range(3):
        np.testing.assert_allclose(bodies.inertia[i], inertia.annulus(masses[i], 0.1, outer[i]).inertia, rtol=0)


def run_inertia(capsys, *argv):
    """ensemble inertia ... in this process: (exit status, stdout, stderr)."""
    try:
        status = cli.main(["inertia", *argv])
    except SystemExit as e:
        status = e.code
    out = capsys.readouterr()
    return status, out.out, out.err


def test_command_prints_the_course_plate_as_json(capsys):
    status, out, _ = run_inertia(capsys, "polygon", "--mass", "1", "--vertices", "0,0 1,0 0,1", "--json")
    assert status == 0
    result = json.loads(out)
    np.testing.assert_allclose(result["tensor"], np.array([[2, -1, 0], [-1, 2, 0], [0, 0, 4]]) / 12, atol=1e-15)
    np.testing.assert_allclose(result["principal_moments"], np.array([1, 3, 4]) / 12, rtol=1e-14)
    np.testing.assert_allclose(result["principal_axes"], [[ROOT_HALF, -ROOT_HALF, 0], [ROOT_HALF, ROOT_HALF, 0],
                                                          [0, 0, 1]], atol=1e-15)


def test_command_prints_tensor_moments_and_axes_with_units(capsys):
    status, out, _ = run_inertia(capsys, "polygon", "--mass", "1", "--vertices", "0,0 1,0 0,1")
    assert status == 0 and "kg m2" in out
    for number in ("0.1666666667", "-0.08333333333", "0.3333333333", "0.25", "0.7071067812", "-0.7071067812"):
        assert number in out


@pytest.mark.parametrize("shape, dims", [(name, shape.lengths) for name, shape in SHAPES.items()])
def test_command_builds_every_shape_and_moves_the_origin(capsys, shape, dims):
    sizes = dict(zip(dims, (0.1, 0.3, 0.5)))  # r_inner < r_outer where both appear
    options = [item for dim, size in sizes.items() for item in (f"--{dim.replace('_', '-')}", str(size))]
    status, out, _ = run_inertia(capsys, shape, "--mass", "2", *options, "--origin", "0.1,0.2,0.3", "--json")
    assert status == 0
    body = SHAPES[shape].build(2.0, **sizes)
    np.testing.assert_allclose(json.loads(out)["tensor"], body.tensor((0.1, 0.2, 0.3)), rtol=1e-14)


@pytest.mark.parametrize("argv, where", [
    (["polygon", "--mass", "1", "--vertices", "0,0 1,1 1,0 0,1"], "intersects itself"),
    (["polygon", "--mass", "1", "--vertices", "0,0 1,0 0.5,0 0,1"], "intersects itself"),
    (["polygon", "--mass", "1", "--vertices", "0,0 1,1 2,2"], "zero area"),
    (["polygon", "--mass", "1", "--vertices", "0,0 1,1 0,0"], "at least 3 distinct"),
    (["polygon", "--mass", "0", "--vertices", "0,0 1,0 0,1"], "--mass"),
    (["polygon", "--mass", "1", "--vertices", "0,0 1,0 0;1"], "--vertices"),
    (["disk", "--mass", "-1", "--radius", "1"], "--mass"),
    (["disk", "--mass", "1", "--radius", "0"], "--radius"),
    (["box", "--mass", "1", "--width", "1", "--height", "nan", "--depth", "1"], "--height"),
    (["annulus", "--mass", "1", "--r-inner", "0.2", "--r-outer", "0.2"], "--r-inner: must be < --r-outer"),
    (["hollow_sphere", "--mass", "1", "--r-inner", "0.3", "--r-outer", "0.2"], "--r-inner"),
    (["annulus", "--mass", "1", "--r-inner", "0.1"], "--r-outer"),
    (["points", "--points", "1,0,0,0 -1,1,0,0"], "--points"),
    (["cylinder", "--mass", "1", "--radius", "1", "--height", "1", "--origin", "1,2"], "--origin"),
])
def test_bad_shapes_get_one_line_and_exit_2(capsys, argv, where):
    status, out, err = run_inertia(capsys, *argv)
    assert status == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("ensemble: error:") and where in err


# --- tops built from their shapes ------------------------------------------------------------------

def ring_runfile(body, sweep=None, **parameters):
    from tests.conftest import top_runfile

    text = top_runfile(method="exact", members=5, t_end=20.0, save_dt=0.5,
                       parameters={"lambda1": None, "lambda3": None, "tilt0": 0.1, **parameters}, sweep=sweep)
    return text.replace("[parameters]\n", f"[parameters]\nbody = {body}\n")


def test_a_swept_and_drawn_annulus_gives_each_member_its_moments():
    from ensemble.spec import members_table, parse

    text = ring_runfile('{ shape = "annulus", mass = { uniform = [0.09, 0.11] }, r_inner = 0.1 }',
                        sweep={"body.r_outer": [0.12, 0.13]})
    table = members_table(parse(text))
    assert np.array_equal(table["body_r_outer"], np.repeat([0.12, 0.13], 5))
    assert len(set(table["body_mass"])) == 10 and np.all((0.09 <= table["body_mass"]) & (table["body_mass"] <= 0.11))
    squares = 0.1**2 + table["body_r_outer"] ** 2
    np.testing.assert_allclose(table["lambda1"], table["body_mass"] * squares / 4, rtol=1e-14)
    np.testing.assert_allclose(table["lambda3"], table["body_mass"] * squares / 2, rtol=1e-14)


@pytest.mark.parametrize("body, lambda1, lambda3", [
    ('{ shape = "disk", mass = 0.2, radius = 0.1 }', 0.2 * 0.01 / 4, 0.2 * 0.01 / 2),
    ('{ shape = "cylinder", mass = 0.2, radius = 0.1, height = 0.3 }', 0.2 * (0.03 + 0.09) / 12, 0.2 * 0.01 / 2),
    ('{ shape = "hollow_cylinder", mass = 0.1, r_inner = 0.1, r_outer = 0.13, height = 0.01 }',
     0.1 * (3 * 0.0269 + 0.0001) / 12, 0.1 * 0.0269 / 2),
    ('{ shape = "rectangle", mass = 0.3, width = 0.2, height = 0.2 }', 0.3 * 0.04 / 12, 0.3 * 0.08 / 12),
    ('{ shape = "sphere", mass = 1.0, radius = 0.1 }', 0.004, 0.004),
])
def test_symmetric_shapes_give_lambda1_and_lambda3(body, lambda1, lambda3):
    from ensemble.spec import members_table, parse

    table = members_table(parse(ring_runfile(body)))
    np.testing.assert_allclose(table["lambda1"], lambda1, rtol=1e-13)
    np.testing.assert_allclose(table["lambda3"], lambda3, rtol=1e-13)


@pytest.mark.parametrize("body, extra, key, words", [
    ('{ shape = "rectangle", mass = 0.1, width = 0.1, height = 0.2 }', {}, "parameters.body",
     "not a symmetric top"),
    ('{ shape = "annulus", mass = 0.1, r_inner = 0.13, r_outer = 0.1 }', {}, "parameters.body.r_inner", "r_outer"),
    ('{ shape = "annulus", mass = 0.0, r_inner = 0.1, r_outer = 0.13 }', {}, "parameters.body.mass", "> 0"),
    ('{ shape = "annulus", mass = 0.1, r_inner = 0.1 }', {}, "parameters.body.r_outer", "missing"),
    ('{ shape = "annulus", mass = 0.1, r_inner = 0.1, r_outer = 0.13, radius = 1 }', {}, "parameters.body.radius",
     "unknown key"),
    ('{ shape = "triangle", mass = 0.1 }', {}, "parameters.body.shape", "unknown shape"),
    ('{ shape = "disk", mass = 0.1, radius = 0.1 }', {"lambda1": 1e-3}, "parameters.lambda1", "not both"),
    ("0.5", {}, "parameters.body", "shape table"),
    ('{ shape = ["disk"], mass = 0.1 }', {}, "parameters.body.shape", "unknown shape"),
    ('{ shape = "disk", mass = 0.1, radius = 0.1 }', {"body_mass": 0.2}, "parameters.body_mass", "parameters.body"),
])
def test_bad_bodies_are_named(body, extra, key, words):
    from ensemble.spec import SpecError, parse

    with pytest.raises(SpecError) as error:
        parse(ring_runfile(body, **extra))
    assert error.value.key == key and words in str(error.value)


def test_not_a_top_names_its_three_moments():
    from ensemble.spec import SpecError, parse

    # M / 12 (h^2 + d^2, w^2 + d^2, w^2 + h^2) = 0.1 (0.13, 0.10, 0.05)
    with pytest.raises(SpecError, match=r"are 0\.005, 0\.01, 0\.013 kg m2"):
        parse(ring_runfile('{ shape = "box", mass = 1.2, width = 0.1, height = 0.2, depth = 0.3 }'))


def test_an_annulus_top_decays_at_the_course_rate_and_records_its_body():
    from ensemble.runner import simulate
    from ensemble.scenes.top import fits as top_fit
    from ensemble.spec import parse

    ds = simulate(parse(ring_runfile('{ shape = "annulus", mass = 0.1, r_inner = 0.1, r_outer = 0.13 }')))
    assert ds.attrs["body_shape"] == "annulus" and ds.body_r_outer.attrs["units"] == "m"
    assert "annulus" in ds.lambda1.attrs["comment"]
    lambda1 = 0.1 * (0.1**2 + 0.13**2) / 4
    np.testing.assert_allclose(ds.lambda1, lambda1, rtol=1e-14)
    rates = top_fit.tilt_decay(ds)
    # flat: 1/lambda1 - 1/lambda3 = 1/(2 lambda1)
    np.testing.assert_allclose(rates.rate, 1e-4 / (2 * lambda1), rtol=1e-9)


def test_the_ring_run_file_sweeps_the_outer_radius():
    from pathlib import Path

    from ensemble.spec import load, members_table

    spec = load(Path(__file__).resolve().parent.parent / "runs" / "aerobie_ring.toml")
    table = members_table(spec)
    assert spec.sweep == {"body_r_outer": (0.12, 0.13, 0.15)} and spec.constants == {"body_shape": "annulus"}
    np.testing.assert_allclose(table["lambda3"], 2 * table["lambda1"], rtol=1e-14)
    np.testing.assert_allclose(table["lambda1"], 0.1 * (0.01 + table["body_r_outer"] ** 2) / 4, rtol=1e-14)
