"""Inertia tensors of uniform bodies, composite bodies, principal moments and axes.

Units: masses in kg, lengths in m, inertia in kg m2. A `Body` holds its mass,
its centre of mass and its inertia tensor about that centre, in the body's own
coordinates. Laminae lie in the xy plane (z is their normal); solids of
revolution have their symmetry axis along z. Every shape is centred on its own
origin except a polygon and a set of point masses, whose origin is the
coordinate origin of their vertices or positions.

Shapes accept arrays for mass and dimensions (one body per element, broadcast
together): a run file's members each get their own body in one call.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from .parameter import ParameterError

# Principal moments closer than this, relative to the largest, are equal (a symmetry, up to rounding).
EQUAL_RTOL = 1e-9


class ShapeError(ParameterError):
    """A bad shape dimension; `name` is the dimension (e.g. "r_inner")."""


@dataclass(frozen=True)
class Body:
    """A rigid body: mass (kg, shape S), centre of mass (m, S + (3,)), inertia about it (kg m2, S + (3, 3))."""

    mass: np.ndarray
    centre: np.ndarray
    inertia: np.ndarray

    def tensor(self, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Inertia tensor about `origin` (m, body coordinates): the centre-of-mass tensor plus the parallel-axis
        shift."""
        return self.inertia + parallel_axis_shift(self.mass, self.centre - np.asarray(origin, dtype=float))

    def placed(self, rotation=None, position=(0.0, 0.0, 0.0)) -> Body:
        """The body turned by `rotation` about its own origin, then moved by `position` (m).

        `rotation` is a 3x3 rotation matrix or a scipy.spatial.transform.Rotation.
        """
        turn = np.eye(3) if rotation is None else np.asarray(
            rotation.as_matrix() if hasattr(rotation, "as_matrix") else rotation, dtype=float)
        if turn.shape != (3, 3) or not np.allclose(turn @ turn.T, np.eye(3), atol=1e-12) \
                or np.linalg.det(turn) < 0:
            raise ShapeError("rotation", "must be a 3x3 proper rotation matrix (orthonormal, determinant +1)")
        centre = self.centre @ turn.T + np.asarray(position, dtype=float)
        return Body(self.mass, centre, turn @ self.inertia @ turn.T)

    def __add__(self, other: Body) -> Body:
        return composite((self, other))


def parallel_axis_shift(mass, offset) -> np.ndarray:
    """M (|d|^2 1 - d d^T): inertia about a point at -d from the centre of mass minus that about the centre.

    mass: kg, shape S; offset d = centre - origin: m, S + (3,); returns kg m2, S + (3, 3).
    """
    d = np.asarray(offset, dtype=float)
    outer = d[..., :, None] * d[..., None, :]
    return np.asarray(mass, dtype=float)[..., None, None] * (np.sum(d * d, -1)[..., None, None] * np.eye(3) - outer)


def composite(parts: Iterable[Body]) -> Body:
    """One body made of several (each already placed): masses add, tensors add about the common centre."""
    parts = list(parts)
    if not parts:
        raise ShapeError("parts", "a composite body needs at least one part")
    mass = sum(p.mass for p in parts)
    centre = sum(p.mass[..., None] * p.centre for p in parts) / mass[..., None]
    inertia = sum(p.inertia + parallel_axis_shift(p.mass, p.centre - centre) for p in parts)
    return Body(mass, centre, inertia)


def principal(tensor) -> tuple[np.ndarray, np.ndarray]:
    """Principal moments (ascending, kg m2) and unit axes (3x3, column i for moment i) of one tensor.

    Signs are deterministic: the first and third axes have their largest
    component positive (the first of equal ones), and the second is third x
    first, so the axes form a right-handed frame. Within equal moments (a
    symmetry) the axes are not fixed by the tensor; the free axis is taken
    along the projection of the first coordinate axis that projects longest.
    """
    tensor = np.asarray(tensor, dtype=float)
    if tensor.shape != (3, 3) or not np.all(np.isfinite(tensor)):
        raise ShapeError("tensor", "must be a finite 3x3 matrix")
    moments, axes = np.linalg.eigh(0.5 * (tensor + tensor.T))
    scale = max(float(np.abs(moments).max()), np.finfo(float).tiny)
    low_pair = moments[1] - moments[0] <= EQUAL_RTOL * scale
    high_pair = moments[2] - moments[1] <= EQUAL_RTOL * scale
    if low_pair and high_pair:
        return moments, np.eye(3)
    first, third = axes[:, 0], axes[:, 2]
    if low_pair:  # first and second span the plane normal to the third
        first = _in_plane(third)
    elif high_pair:
        third = _in_plane(first)
    first, third = _sign_fixed(first), _sign_fixed(third)
    return moments, np.column_stack((first, np.cross(third, first), third))


def _sign_fixed(axis: np.ndarray) -> np.ndarray:
    largest = np.abs(axis) >= np.abs(axis).max() * (1 - 1e-9)
    return axis if axis[np.argmax(largest)] > 0 else -axis


def _in_plane(normal: np.ndarray) -> np.ndarray:
    """The unit projection of the coordinate axis that projects longest onto the plane normal to `normal`."""
    projections = np.eye(3) - np.outer(normal, normal)  # column k: e_k projected
    lengths = np.linalg.norm(projections, axis=0)
    k = np.argmax(lengths >= lengths.max() * (1 - 1e-9))
    return projections[:, k] / lengths[k]


# --- validation -----------------------------------------------------------------------------------

def _positive(name: str, value) -> np.ndarray:
    value = np.asarray(value, dtype=float)
    bad = ~(np.isfinite(value) & (value > 0))
    if np.any(bad):
        raise ShapeError(name, f"must be > 0 and finite, got {value[bad].flat[0]:g}")
    return value


def _hollow(mass, r_inner, r_outer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mass, r_outer = _positive("mass", mass), _positive("r_outer", r_outer)
    r_inner = np.asarray(r_inner, dtype=float)
    bad = ~(np.isfinite(r_inner) & (r_inner >= 0))
    if np.any(bad):
        raise ShapeError("r_inner", f"must be >= 0 and finite, got {r_inner[bad].flat[0]:g}")
    inside_out = r_inner >= r_outer
    if np.any(inside_out):
        i = np.argmax(np.broadcast_to(inside_out, np.broadcast(r_inner, r_outer).shape))
        ri, ro = np.broadcast_to(r_inner, inside_out.shape).flat[i], np.broadcast_to(r_outer, inside_out.shape).flat[i]
        raise ShapeError("r_inner", f"must be < r_outer, got {ri:g} >= {ro:g}")
    return mass, r_inner, r_outer


def _axial(mass, transverse, axial) -> Body:
    """A body centred on its origin with diagonal inertia (transverse, transverse, axial) about it."""
    mass, transverse, axial = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (mass, transverse, axial)))
    return _diagonal(mass, transverse, transverse, axial)


def _diagonal(mass, ixx, iyy, izz) -> Body:
    mass, ixx, iyy, izz = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (mass, ixx, iyy, izz)))
    inertia = np.zeros(mass.shape + (3, 3))
    inertia[..., 0, 0], inertia[..., 1, 1], inertia[..., 2, 2] = ixx, iyy, izz
    return Body(mass, np.zeros(mass.shape + (3,)), inertia)


# --- shapes ---------------------------------------------------------------------------------------

def disk(mass, radius) -> Body:
    """Uniform disk in the xy plane, centred: M R^2 / 4 about x and y, M R^2 / 2 about z."""
    mass, radius = _positive("mass", mass), _positive("radius", radius)
    return _axial(mass, mass * radius**2 / 4, mass * radius**2 / 2)


def annulus(mass, r_inner, r_outer) -> Body:
    """Uniform flat ring in the xy plane, centred: M (R1^2 + R2^2) / 4 about x and y, twice that about z."""
    mass, r_inner, r_outer = _hollow(mass, r_inner, r_outer)
    squares = r_inner**2 + r_outer**2
    return _axial(mass, mass * squares / 4, mass * squares / 2)


def rectangle(mass, width, height) -> Body:
    """Uniform rectangular plate in the xy plane, centred; width along x, height along y."""
    mass, width, height = _positive("mass", mass), _positive("width", width), _positive("height", height)
    return _diagonal(mass, mass * height**2 / 12, mass * width**2 / 12, mass * (width**2 + height**2) / 12)


def polygon(mass, vertices) -> Body:
    """Uniform lamina bounded by a simple polygon in the xy plane; vertices (n, 2) in m, either orientation.

    The body's origin is the origin of the vertex coordinates. Area moments
    come from Green's theorem edge by edge, about the centroid.
    """
    mass = _positive("mass", mass)
    points = _simple_polygon(vertices)
    x, y = points.T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2
    cx, cy = ((x + xn) * cross).sum() / (6 * area), ((y + yn) * cross).sum() / (6 * area)
    x, y, xn, yn = x - cx, y - cy, xn - cx, yn - cy  # about the centroid, where the sums are smallest
    cross = x * yn - xn * y
    yy = (cross * (y * y + y * yn + yn * yn)).sum() / (12 * area)  # mean of y^2 over the area
    xx = (cross * (x * x + x * xn + xn * xn)).sum() / (12 * area)
    xy = (cross * (2 * x * y + x * yn + xn * y + 2 * xn * yn)).sum() / (24 * area)
    per_mass = np.array([[yy, -xy, 0.0], [-xy, xx, 0.0], [0.0, 0.0, xx + yy]])
    centre = np.broadcast_to(np.array([cx, cy, 0.0]), mass.shape + (3,))
    return Body(mass, centre.copy(), mass[..., None, None] * per_mass)


def cylinder(mass, radius, height) -> Body:
    """Uniform solid cylinder along z, centred: M (3 R^2 + h^2) / 12 about x and y, M R^2 / 2 about z."""
    mass, radius, height = _positive("mass", mass), _positive("radius", radius), _positive("height", height)
    return _axial(mass, mass * (3 * radius**2 + height**2) / 12, mass * radius**2 / 2)


def hollow_cylinder(mass, r_inner, r_outer, height) -> Body:
    """Uniform thick-walled tube along z, centred: M (3 (R1^2 + R2^2) + h^2) / 12 about x, y;
    M (R1^2 + R2^2) / 2 about z."""
    mass, r_inner, r_outer = _hollow(mass, r_inner, r_outer)
    height = _positive("height", height)
    squares = r_inner**2 + r_outer**2
    return _axial(mass, mass * (3 * squares + height**2) / 12, mass * squares / 2)


def sphere(mass, radius) -> Body:
    """Uniform solid ball, centred: 2 M R^2 / 5 about every axis."""
    mass, radius = _positive("mass", mass), _positive("radius", radius)
    moment = 2 * mass * radius**2 / 5
    return _axial(mass, moment, moment)


def hollow_sphere(mass, r_inner, r_outer) -> Body:
    """Uniform spherical shell, centred: (2 M / 5) (R2^5 - R1^5) / (R2^3 - R1^3) about every axis.

    The ratio is evaluated in factored form, so a thin shell (R1 close to R2)
    gives 2 M R^2 / 3 without cancellation.
    """
    mass, a, b = _hollow(mass, r_inner, r_outer)
    ratio = (a**4 + a**3 * b + a**2 * b**2 + a * b**3 + b**4) / (a**2 + a * b + b**2)
    moment = 2 * mass * ratio / 5
    return _axial(mass, moment, moment)


def box(mass, width, height, depth) -> Body:
    """Uniform solid box, centred; width along x, height along y, depth along z."""
    mass = _positive("mass", mass)
    width, height, depth = _positive("width", width), _positive("height", height), _positive("depth", depth)
    return _diagonal(mass, mass * (height**2 + depth**2) / 12, mass * (width**2 + depth**2) / 12,
                     mass * (width**2 + height**2) / 12)


def points(masses, positions) -> Body:
    """Point masses (kg, shape (n,)) at positions (m, (n, 3)); the body's origin is the coordinate origin."""
    masses = np.asarray(masses, dtype=float)
    positions = np.asarray(positions, dtype=float)
    if masses.ndim != 1 or masses.size == 0 or positions.shape != (masses.size, 3):
        raise ShapeError("points", f"need n masses and n positions of 3 coordinates, got masses of shape "
                                   f"{masses.shape} and positions of shape {positions.shape}")
    if not np.all(np.isfinite(masses) & (masses > 0)) or not np.all(np.isfinite(positions)):
        raise ShapeError("points", "masses must be > 0 and finite, positions finite")
    return composite(Body(m, p, np.zeros((3, 3))) for m, p in zip(masses, positions))


@dataclass(frozen=True)
class Shape:
    """A shape given by its mass and named lengths (m), for the command line and run files."""

    build: Callable[..., Body]
    lengths: tuple[str, ...]
    summary: str


SHAPES: dict[str, Shape] = {
    "disk": Shape(disk, ("radius",), "uniform disk in the xy plane, centred at the origin"),
    "annulus": Shape(annulus, ("r_inner", "r_outer"), "uniform flat ring in the xy plane, centred"),
    "rectangle": Shape(rectangle, ("width", "height"), "uniform plate in the xy plane, width along x, centred"),
    "cylinder": Shape(cylinder, ("radius", "height"), "uniform solid cylinder along z, centred"),
    "hollow_cylinder": Shape(hollow_cylinder, ("r_inner", "r_outer", "height"), "uniform tube along z, centred"),
    "sphere": Shape(sphere, ("radius",), "uniform solid ball, centred"),
    "hollow_sphere": Shape(hollow_sphere, ("r_inner", "r_outer"), "uniform spherical shell, centred"),
    "box": Shape(box, ("width", "height", "depth"), "uniform solid box (x, y, z sizes), centred"),
}


# --- polygon checks -------------------------------------------------------------------------------

def _simple_polygon(vertices) -> np.ndarray:
    """Vertices as an (n, 2) array, checked: finite, >= 3 distinct, non-zero area, no self-intersection."""
    points = np.asarray(vertices, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ShapeError("vertices", f"must be a list of (x, y) pairs, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ShapeError("vertices", "must be finite")
    repeated = np.all(points == np.roll(points, 1, axis=0), axis=1)  # a vertex equal to the one before it
    points = points[~repeated] if not repeated.all() else points[:1]  # also drops a closed ring's last vertex
    distinct = len(np.unique(points, axis=0))
    if distinct < 3:
        raise ShapeError("vertices", f"a polygon needs at least 3 distinct vertices, got {distinct}")
    spread = points - points.mean(axis=0)
    if np.linalg.svd(spread, compute_uv=False)[1] <= 1e-12 * np.abs(spread).max():
        raise ShapeError("vertices", "the polygon has zero area (its vertices are collinear)")
    n = len(points)
    for i in range(n):
        for j in range(i + 1, n):
            if _edges_cross(points, i, j):
                raise ShapeError("vertices", f"the polygon intersects itself: edge {i + 1} "
                                             f"({_pair(points[i])} to {_pair(points[(i + 1) % n])}) meets edge {j + 1} "
                                             f"({_pair(points[j])} to {_pair(points[(j + 1) % n])})")
    return points


def _pair(point) -> str:
    return f"{point[0]:g},{point[1]:g}"


def _orientation(a, b, c) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _on_segment(a, b, p) -> bool:
    """p, collinear with a and b, lies within the segment ab."""
    return min(a[0], b[0]) <= p[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= p[1] <= max(a[1], b[1])


def _edges_cross(points, i: int, j: int) -> bool:
    """Edges i and j (from vertex i to i+1) share a point they should not."""
    n = len(points)
    a, b, c, d = points[i], points[(i + 1) % n], points[j], points[(j + 1) % n]
    if (i + 1) % n == j or (j + 1) % n == i:  # neighbours share one vertex; they must not fold back
        shared, p, q = (b, a, d) if (i + 1) % n == j else (a, b, c)
        return _orientation(shared, p, q) == 0 and np.dot(p - shared, q - shared) > 0
    o1, o2, o3, o4 = _orientation(a, b, c), _orientation(a, b, d), _orientation(c, d, a), _orientation(c, d, b)
    if o1 * o2 < 0 and o3 * o4 < 0:
        return True
    return any(o == 0 and _on_segment(s, e, p) for o, s, e, p in
               ((o1, a, b, c), (o2, a, b, d), (o3, c, d, a), (o4, c, d, b)))
