"""Running a validated spec: members in chunks through a kernel into NetCDF."""
from __future__ import annotations

import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from . import kernels
from .scenes import SCENES
from .spec import Spec, members_table, observation_noise
from .store import Writer

CHUNK_BYTES = 32 * 2**20  # saved data held in memory per chunk


@dataclass(frozen=True)
class Summary:
    members: int
    steps: int
    seconds: float

    def __str__(self) -> str:
        rate = self.members * self.steps / self.seconds if self.seconds > 0 else float("inf")
        return (f"{self.members} members x {self.steps} steps in {self.seconds:.3g} s: "
                f"{rate:.3g} member-steps/s")


def default_chunk(spec: Spec) -> int:
    """Members per chunk: a multiple of the kernel block that keeps a chunk within CHUNK_BYTES."""
    scene = SCENES[spec.scene]
    sizes = {"axis": 3, **scene.sizes(spec.constants)}
    state_rows, _ = scene.kernel_rows(spec.constants)
    saved = sum(math.prod(sizes[d] for d in scene.OBSERVABLES[v][0][2:]) for v in spec.save)
    values_per_member = spec.n_save * (state_rows + saved)  # kernel samples and the saved variables
    block = kernels.block_size(spec.scene, scene.kernel_key(spec.constants))
    chunk = CHUNK_BYTES // (8 * values_per_member) // block * block
    return min(max(chunk, block), spec.n_members)  # at least one kernel block


def run(spec: Spec, out: str | Path, *, chunk: int | None = None, progress: bool = True) -> Summary:
    """Integrate every member of `spec` and write the dataset to `out` (NetCDF)."""
    scene = SCENES[spec.scene]
    table = members_table(spec)
    n = spec.n_members
    chunk = chunk or default_chunk(spec)
    kernels.prepare(spec.scene, spec.method, spec.constants)  # compile or load before the clock starts
    start = time.perf_counter()
    with Writer(out, spec, table, chunk) as writer, tqdm(
        total=n, unit="member", file=sys.stderr, disable=not progress, leave=False
    ) as bar:
        for j0 in range(0, n, chunk):
            j1 = min(j0 + chunk, n)
            values = {name: v[j0:j1] for name, v in table.items()}
            samples = kernels.integrate(scene, spec.method, values, spec.constants,
                                        spec.dt, spec.steps_per_save, spec.n_save)
            data = scene.observe(samples, spec.save, values, spec.constants)
            for name in spec.noise:
                data[name] = data[name] + observation_noise(spec, name, j0, data[name].shape)
            writer.write(j0, data)
            bar.update(j1 - j0)
    return Summary(n, spec.steps, time.perf_counter() - start)


def simulate(spec: Spec, *, chunk: int | None = None):
    """Run `spec` and return its dataset in memory (xarray), through the same file path as `run`."""
    import xarray as xr

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "result.nc"
        run(spec, path, chunk=chunk, progress=False)
        return xr.load_dataset(path)
