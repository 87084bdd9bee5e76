"""How a scene declares its run-file parameters, and the one error a scene raises about a value."""
from __future__ import annotations

from dataclasses import dataclass

from .errors import EnsembleError


class ParameterError(EnsembleError, ValueError):
    """A parameter value no scene member can have: `name` is the parameter, `problem` says why.

    The run file reports it as one line naming the key where the value was given.
    """

    def __init__(self, name: str, problem: str):
        super().__init__(f"{name}: {problem}")
        self.name = name
        self.problem = problem


@dataclass(frozen=True)
class Parameter:
    """One run-file parameter of a scene.

    Most parameters take one number per member (or, with `per`, one per site or
    spring): a number, a list (when `per` is set), a distribution drawn per
    member, or a sweep axis. Parameters with `choices` or `integer` are run
    constants: one value for the whole run, never drawn or swept.
    """

    units: str
    long_name: str
    default: object = None  # None: required
    per: str | None = None  # "site" or "spring": an array per member
    choices: tuple[str, ...] = ()  # a string run constant
    integer: bool = False  # an integer run constant
    mode: bool = False  # also accepts { mode = j, amplitude = A }
    derives: tuple[str, ...] = ()  # a shape table { shape = ..., mass = ..., lengths } that gives these parameters
    optional: bool = False  # absent (not recorded) unless the run file gives it

    @property
    def constant(self) -> bool:
        return bool(self.choices) or self.integer


@dataclass(frozen=True)
class Mode:
    """Start in normal mode `number` (1 = lowest frequency), largest entry `amplitude`."""

    number: int
    amplitude: float
