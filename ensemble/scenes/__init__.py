"""Scenes: the physical systems. A built-in scene is one folder: `model.py` (numpy only) and `physics.py` (its
right-hand side and exactly solved pieces, from which ensemble.engine builds its kernels). A user's scene is a
file or module written to the short contract of `ensemble.scenes.contract`.

A new built-in scene is its folder, one line in SCENES, its run files and its tests; `Scene` lists what it
provides.
"""
from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Protocol

import numpy as np

from ..methods import METHODS, Method
from ..parameter import Parameter
from . import body, chain, top
from .contract import SceneError, UserScene, UserSitesScene, load


class Scene(Protocol):
    """What a scene's model provides (its package's names). Arrays are over members on their first axis in
    `values` (name -> (members,) or (members, site)); kernel arrays are (rows, members).

    PHYSICS names the module (or file) whose functions the engine's kernels call: rhs(t, *state, *parameters)
    and each piece's flow (ensemble.engine.kernels); or, for a scene with SITES = True, whose member is n sites
    each moved by its two neighbours (the chain), acceleration(x_left, x, x_right, c_left, c_right)
    (ensemble.engine.sites_kernels, with n and boundary among its constants).
    """

    NAME: str
    PHYSICS: str  # its physics module, by dotted name or file path
    SITES: bool  # a member is a field of sites (the chain: n and boundary among its constants), else D values
    PARAMETERS: dict[str, Parameter]  # run-file parameters
    OBSERVABLES: dict[str, tuple[tuple[str, ...], str, str]]  # saved variables: name -> (dims, units, long_name)
    PIECES: tuple[str, ...]  # the exactly solved pieces its splitting methods take (see methods.Splitting)
    EVALUATING_PIECES: tuple[str, ...]  # the pieces that evaluate the right-hand side (counted as rhs_evals)
    STABILITY_AXES: tuple[str, ...]  # the dimensionless steps its stability is read against
    EVENT_VALUES: dict[str, tuple]  # what events watch: name -> ("state", row) or ("function", physics function[,
    # its watch: ensemble.events])

    def sizes(self, constants: dict) -> dict[str, int]: ...  # dimensions besides member and t
    def coordinates(self, constants: dict) -> dict[str, tuple[np.ndarray, str]]: ...  # dim -> (values, long_name)
    def check_constants(self, constants: dict) -> None: ...  # raises ParameterError
    def check(self, values: dict) -> None: ...  # raises ParameterError
    def derive(self, values: dict, constants: dict) -> dict: ...  # parameters computed from others
    def inputs(self, values: dict, constants: dict) -> tuple[np.ndarray, np.ndarray]: ...  # state0, rate
    def kernel_rows(self, constants: dict) -> tuple[int, int]: ...  # rows of state0 and rate
    def exact(self, values: dict, constants: dict, t: np.ndarray) -> np.ndarray: ...  # (times, state, members)
    # t: (times,), or (times, members): each member's own (closed_form.times_by_members)
    def observe(self, samples: np.ndarray, names, values: dict, constants: dict) -> dict: ...  # saved variables
    def amplitudes(self, samples: np.ndarray, values: dict, constants: dict) -> np.ndarray: ...  # (M, motions, t)
    def axis_growth(self, method: Method, axis: str, x: np.ndarray) -> np.ndarray: ...
    def stability_axis(self, values: dict, constants: dict, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def step_growth(self, method: Method, values: dict, constants: dict, h: np.ndarray) -> np.ndarray: ...
    def conserved_energy(self, ds) -> np.ndarray: ...  # (member, t), NaN where not conserved
    def fit(self, ds): ...  # the scene's fit of a result (ensemble fit), an xarray.Dataset over members
    def charts(self, plt, ds, fits, rows, stem, members=None) -> list: ...  # its charts of that fit, PNG paths
    # Optional: check_exact(values) raises ParameterError where the closed form does not hold (runs that use
    # `exact` or [measure] error call it); from_body(body, source) for a parameter that `derives` others.


SCENES: dict[str, Scene] = {"top": top, "chain": chain, "body": body}


def resolve(name: str) -> Scene:
    """A scene by a run file's `scene`: a built-in name, a Python file (a path ending in .py), or a module by its
    dotted name. Raises SceneError (one line) for an unknown name or a file that breaks the contract."""
    if name in SCENES:
        return SCENES[name]
    if name.endswith(".py") or "." in name:
        return _user_scene(name)
    raise SceneError(f"unknown scene {name!r}; scenes: {', '.join(SCENES)}, or a scene file (path/to/scene.py) or "
                     f"module (package.scene)")


def of_result(attrs: dict) -> Scene | None:
    """The scene a result was run with, from its attributes (`scene_source` for a user's scene, else `scene`);
    None for a file ensemble did not write or a scene that cannot be found here."""
    name = attrs.get("scene_source") or attrs.get("scene")
    try:
        return resolve(name) if isinstance(name, str) else None
    except SceneError:
        return None


def _user_scene(where: str) -> UserScene | UserSitesScene:
    return _scene_of(load(where), where)


@cache
def _scene_of(module, where: str) -> UserScene | UserSitesScene:
    """A user's scene for its module as imported (load imports an edited file anew: a new module, a new scene): a
    field of sites where it sets SITES = True."""
    return UserSitesScene(module, where) if getattr(module, "SITES", False) is True else UserScene(module, where)


def absolute(name: str, folder: Path) -> str:
    """A run file's `scene` with a relative file path made absolute against the run file's folder."""
    if name.endswith(".py") and not Path(name).expanduser().is_absolute():
        return str((folder / Path(name).expanduser()).resolve())
    return str(Path(name).expanduser()) if name.endswith(".py") else name


def applies(method: Method, scene: Scene) -> bool:
    """Whether `method` can integrate `scene`: any tableau; a splitting of the scene's own pieces; the closed form
    of a scene that has one."""
    if method.splitting is not None:
        return method.splitting.pieces == scene.PIECES
    if method.closed_form:
        return hasattr(scene, "exact")
    return True


def methods_for(scene: Scene) -> list[Method]:
    """The methods that apply to `scene`, in listing order."""
    return [m for m in METHODS.values() if applies(m, scene)]


def scenes_of(method: Method) -> list[str]:
    """Names of the scenes `method` applies to."""
    return [name for name, scene in SCENES.items() if applies(method, scene)]
