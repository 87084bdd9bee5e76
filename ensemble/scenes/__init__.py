"""Scenes: the physical systems, each with its equations in its own module."""
from __future__ import annotations

from types import ModuleType

from . import chain, top

SCENES: dict[str, ModuleType] = {"top": top, "chain": chain}
