"""Running a validated spec: members in chunks through a kernel into NetCDF."""
from __future__ import annotations

import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import kernels, stability
from .methods import METHODS
from .scenes import SCENES
from .spec import Spec, members_table, observation_noise
from .store import Writer

CHUNK_BYTES = 32 * 2**20  # saved data held in memory per chunk


@dataclass(frozen=True)
class Summary:
    members: int
    member_steps: int
    seconds: float
    steps_each: int | None = None  # when every member took the same number of steps
    blew_up: int = 0  # failed members (status 1)
    underflowed: int = 0  # failed members (status 2)

    def __str__(self) -> str:
        failed = self.blew_up + self.underflowed
        failures = (f"; {failed} of {self.members} members failed ({self.blew_up} blew up, {self.underflowed} "
                    f"step size underflow)" if failed else "")
        if self.member_steps == 0:
            return f"{self.members} members (closed form) in {self.seconds:.3g} s" + failures
        rate = self.member_steps / self.seconds if self.seconds > 0 else float("inf")
        steps = (f"{self.members} members x {self.steps_each} steps" if self.steps_each is not None
                 else f"{self.members} members, {self.member_steps} member-steps")
        return f"{steps} in {self.seconds:.3g} s: {rate:.3g} member-steps/s" + failures


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


def _same_settings(table: dict[str, np.ndarray], j0: int, j1: int):
    """Ranges [k0, k1) within [j0, j1) of consecutive members that one kernel call can run (same method and dt)."""
    key = [(m, d) for m, d in zip(table["method"][j0:j1], table["dt"][j0:j1])]
    k0 = j0
    for k in range(j0 + 1, j1 + 1):
        if k == j1 or key[k - j0] != key[k0 - j0]:
            yield k0, k
            k0 = k


def integrate(spec: Spec, values: dict[str, np.ndarray], repeats: int = 1) -> tuple[kernels.Outcome, float]:
    """Integrate members that share one method and dt; returns what the kernel did and its best seconds per
    member-step over `repeats` calls."""
    scene = SCENES[spec.scene]
    method = METHODS[str(values["method"][0])]
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        if method.adaptive:
            outcome = kernels.integrate_adaptive(scene, method.name, values, spec.constants, values["dt"],
                                                 values["rtol"], values["atol"], spec.save_dt, spec.n_save,
                                                 spec.blowup_factor)
        else:
            dt = float(values["dt"][0]) if np.isfinite(values["dt"][0]) else spec.save_dt
            outcome = kernels.integrate(scene, method.name, values, spec.constants, dt, round(spec.save_dt / dt),
                                        spec.n_save, spec.blowup_factor)
        best = min(best, time.perf_counter() - start)
    taken = outcome.counts[0].sum() + outcome.counts[1].sum()
    return outcome, best / taken if taken else np.nan


def growth_per_step(spec: Spec, values: dict[str, np.ndarray], outcome: kernels.Outcome) -> np.ndarray:
    """Each member's measured growth factor per step (see stability.measured_growth); per mean accepted step
    for adaptive methods; NaN for the closed form."""
    method = METHODS[str(values["method"][0])]
    if method.closed_form:
        return np.full(outcome.samples.shape[2], np.nan)
    scene = SCENES[spec.scene]
    step = values["dt"]
    if method.adaptive:
        reached = np.where(np.isnan(outcome.failure_time), spec.t_end, outcome.failure_time)
        with np.errstate(invalid="ignore", divide="ignore"):
            step = reached / outcome.counts[0]
    return stability.measured_growth(scene.amplitudes(outcome.samples, values, spec.constants), spec.times(), step)


def measured_error(samples: np.ndarray, exact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per member: max over saved samples, and at the last one, of max |y - y_exact| / max |y_exact| over the state.

    samples and exact: (n_save, state, members). A member with non-finite values has an infinite error.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.abs(samples - exact).max(axis=1) / np.abs(exact).max(axis=1)
    relative[~np.isfinite(relative) & np.isfinite(exact).all(axis=1)] = np.inf
    return relative[1:].max(axis=0) if len(relative) > 1 else relative[0], relative[-1]


def run(spec: Spec, out: str | Path, *, chunk: int | None = None, progress: bool = True) -> Summary:
    """Integrate every member of `spec` and write the dataset to `out` (NetCDF)."""
    scene = SCENES[spec.scene]
    table = members_table(spec)
    n = spec.n_members
    chunk = chunk or default_chunk(spec)
    for method in spec.methods:  # compile or load before the clock starts
        kernels.prepare(spec.scene, method, spec.constants)
    repeats = spec.measure["repeats"] if spec.measure["timing"] else 1
    member_steps = 0
    step_counts = set()
    failed = np.zeros(2, dtype=np.int64)  # members that blew up, whose step underflowed
    start = time.perf_counter()
    with Writer(out, spec, table, chunk) as writer, tqdm(
        total=n, unit="member", file=sys.stderr, disable=not progress, leave=False
    ) as bar:
        for j0 in range(0, n, chunk):
            for k0, k1 in _same_settings(table, j0, min(j0 + chunk, n)):
                values = {name: v[k0:k1] for name, v in table.items()}
                outcome, seconds_per_step = integrate(spec, values, repeats)
                counts = outcome.counts
                member_steps += int(counts[0].sum() + counts[1].sum())
                step_counts.update(np.unique(counts[0] + counts[1]).tolist())
                failed += np.bincount(outcome.status, minlength=3)[1:]
                data = scene.observe(outcome.samples, spec.save, values, spec.constants)
                for name in spec.noise:
                    data[name] = data[name] + observation_noise(spec, name, k0, data[name].shape)
                data.update(steps_accepted=counts[0], steps_rejected=counts[1], rhs_evals=counts[2],
                            status=outcome.status, failure_time=outcome.failure_time,
                            growth_per_step=growth_per_step(spec, values, outcome))
                if spec.measure["error"]:
                    data["error_max"], data["error_final"] = measured_error(
                        outcome.samples, scene.exact(values, spec.constants, spec.times()))
                if spec.measure["timing"]:
                    data["seconds_per_step"] = np.full(k1 - k0, seconds_per_step)
                writer.write(k0, data)
                bar.update(k1 - k0)
    return Summary(n, member_steps, time.perf_counter() - start, step_counts.pop() if len(step_counts) == 1 else None,
                   blew_up=int(failed[0]), underflowed=int(failed[1]))


def simulate(spec: Spec, *, chunk: int | None = None):
    """Run `spec` and return its dataset in memory (xarray), through the same file path as `run`."""
    import xarray as xr

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "result.nc"
        run(spec, path, chunk=chunk, progress=False)
        return xr.load_dataset(path)
