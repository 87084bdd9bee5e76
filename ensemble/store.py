"""NetCDF output: the dataset contract, written as a run's chunks finish.

The result is written as `OUT.tmp`, fsynced, and renamed to OUT only when
every member is in, so no run leaves a file that looks complete and is not.
Its saved variables and records are stored contiguously, and HDF5 gives a
contiguous variable all its space at its first write: the Writer makes that
write as it creates the file (Writer._allocate). So once the file is created
and flushed, writing members changes only their own bytes, never the file's
structure. That is what lets a run killed midway keep OUT.tmp and resume into
it (see ensemble.parts).
"""
from __future__ import annotations

import datetime
import math
import os
from pathlib import Path

import netCDF4
import numpy as np

from .errors import EnsembleError
from .events import dimensions as event_dimensions
from .events import variables as event_variables
from .members import grid_points, point_settings
from .results import Status
from .spec import Spec, given_values
from .version import __version__

TIMES_AT_ONCE = 2**20  # saved times written at a time: a member may save 10^8 samples


class StoreError(EnsembleError):
    """An unfinished result that cannot be continued as it is (exit status 2)."""


def temporary_path(path: Path) -> Path:
    """Where the result is written before it is complete."""
    return path.with_name(path.name + ".tmp")


def fsync_path(path: Path, release: bool = False) -> None:
    """Flush a file's (or a folder's: its entries') bytes to the disk; with `release`, then let the system drop
    the file's pages from its page cache (they are on the disk). A run's later chunks then write into pages just
    freed: on a virtual machine whose host takes back freed memory, new pages cost several times the copy
    (analysis/bench/fresh_pages.py)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
        if release and hasattr(os, "posix_fadvise"):  # not on macOS
            try:
                os.posix_fadvise(descriptor, 0, 0, os.POSIX_FADV_DONTNEED)
            except OSError:
                pass  # advice only: a file system that refuses it loses nothing
    finally:
        os.close(descriptor)


def output_bytes(spec: Spec) -> int:
    """Bytes the result of `spec` takes on disk, about: its saved variables and per-member records, uncompressed."""
    scene = spec.model
    sizes = {"member": spec.n_members, "t": spec.n_save, **scene.sizes(spec.constants)}
    saved = sum(math.prod(sizes[d] for d in scene.OBSERVABLES[name][0]) for name in spec.save)
    records = max(len(RUN_RECORDS), record_values(spec))  # every record there is, or what this run stores
    return 8 * (saved + spec.n_members * (records + len(spec.declared)))


def record_values(spec: Spec) -> int:
    """Values per member in the records a run of `spec` stores."""
    sizes = {**spec.model.sizes(spec.constants), **event_dimensions(spec.events)} if spec.events else {}
    return sum(math.prod(sizes[d] for d in dims[1:]) for _, dims, *_ in record_variables(spec).values())


# Per-member records of how each member ran: name -> (type, units, long_name, comment). A long_name is short
# (plots use it as a label); the comment says how the value is made.
RUN_RECORDS = {
    "steps_accepted": ("i8", "1", "steps taken", "integration steps accepted"),
    "steps_rejected": ("i8", "1", "steps rejected", "trial steps rejected by the step-size control"),
    "rhs_evals": ("i8", "1", "rhs evaluations", "right-hand-side (force) evaluations"),
    "error_max": ("f8", "1", "largest relative error", "largest relative error against the exact solution over "
                                                       "the saved samples: max |y - y_exact| / max |y_exact| over "
                                                       "the state"),
    "error_final": ("f8", "1", "relative error at t_end", "relative error against the exact solution at t_end: "
                                                          "max |y - y_exact| / max |y_exact| over the state"),
    "seconds_per_step": ("f8", "s", "kernel time per member-step", "kernel alone, one thread, best of the timed "
                                                                   "repeats, over whole blocks of repeated members "
                                                                   "saving only the end state"),
    "status": ("i1", "1", "how the member ended", ""),
    "failure_time": ("f8", "s", "time of failure", "first saved time at which the member had failed (for a step "
                                                   "size underflow: the time it reached); NaN when it did not fail"),
    "growth_per_step": ("f8", "1", "growth factor per step", "measured amplitude growth factor per step of the "
                                                             "member's fastest-growing motion, from the slope of log "
                                                             "amplitude over the second half of its samples before "
                                                             "any failure (per mean accepted step for adaptive "
                                                             "methods)"),
}
SETTING_UNITS = {"dt": ("s", "integration step", "for adaptive methods: the first trial step"),
                 "rtol": ("1", "relative tolerance", "of the step-size control"),
                 "atol": ("1", "absolute tolerance", "of the step-size control, in the SI units of each state "
                                                     "variable")}


def device_name(device: str) -> str:
    """"cpu", or "cuda: <the GPU's name>"."""
    if device != "cuda":
        return device
    from .engine.gpu import require_gpu

    return f"cuda: {require_gpu()}"


def global_attributes(spec: Spec, command: str | None = None) -> dict[str, object]:
    """The run's provenance; a setting (method, dt, rtol, atol) is an attribute when every member shares it.
    `command` is the command line that made the run (default: `ensemble run <run file>`)."""
    now = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0).isoformat()
    methods = " ".join(spec.methods)
    shared = {}
    settings = point_settings(spec, grid_points(spec))
    for key in SETTING_UNITS:
        values = {s[key] for s in settings} - {None}
        if len(values) == 1 and key not in spec.sweep:
            shared[key] = float(values.pop())
    return {
        **spec.constants,
        "Conventions": "CF-1.9",
        "title": f"ensemble {spec.model.NAME} run{'' if spec.path == '<string>' else ' ' + Path(spec.path).stem} "
                 f"({methods})",
        "history": f"{now} ensemble {__version__}: {command or 'ensemble run ' + spec.path}",
        "source": f"ensemble {__version__}",
        "comment": "Each member's parameters are variables over member; `spec` holds the run file.",
        "scene": spec.model.NAME,
        **({"scene_source": spec.scene} if spec.scene != spec.model.NAME else {}),  # a user's scene file or module
        "method": methods,
        **shared,
        "save_dt": spec.save_dt,
        "t_end": spec.t_end,
        "seed": spec.seed,
        "draws": spec.draws,
        **({"parameters_given": given} if (given := given_values(spec)) else {}),  # files or the API
        "blowup_factor": spec.blowup_factor,
        "device": device_name(spec.device),  # where the kernels ran, the GPU's name included
        **kernels_identity(spec),
        "precision": spec.precision,
        "members_per_sweep_point": spec.members,
        "sweep_axes": " ".join(spec.sweep),
        "members_written": spec.n_members,  # always every member: the file appears only when complete
        "spec": spec.text,
    }


def kernels_identity(spec: Spec) -> dict[str, str]:
    """What the kernels were made of: the scene's sources (its file and the user's modules it imports), the
    engine's kernel sources, and (on the CPU) the compile target."""
    from .engine.kernels import compile_target, scene_identity
    from .tuning import engine_hash

    target = {"compile_target": compile_target()} if spec.device == "cpu" else {}
    return {"scene_sources_sha256": scene_identity(spec.model), "engine_sha256": engine_hash(), **target}


def member_variables(spec: Spec, table: dict[str, np.ndarray], start: int) -> dict[str, np.ndarray]:
    """The result's variables over member that the members `table` (ensemble.members.members_table) of members
    start, start + 1, ... gives: the member and sweep_point coordinates, each parameter, and the settings the
    run sweeps (method as its flag code). A range writes them with its records."""
    n = len(table["sweep_point"])
    values = {**table, "member": np.arange(start, start + n, dtype=member_type(spec)),
              "sweep_point": table["sweep_point"].astype(np.int32)}
    if "method" in spec.sweep:
        values["method"] = np.empty(n, dtype=np.int8)
        for code, name in enumerate(spec.methods):  # in order of first use, as the flag_meanings list them
            values["method"][table["method"] == name] = code
    return {name: values[name] for name in member_variable_names(spec)}


def member_variable_names(spec: Spec) -> list[str]:
    """The names of member_variables(spec, ...), in order."""
    settings = [key for key in ("method", *SETTING_UNITS) if key in spec.sweep]
    return ["member", "sweep_point", *spec.declared, *settings]


def member_type(spec: Spec) -> np.dtype:
    """The member coordinate's type: int32, or int64 for a run of more members than an int32 counts."""
    return np.dtype(np.int32 if spec.n_members <= np.iinfo(np.int32).max else np.int64)


def put_samples(variables, offset: int, first: int, data: dict[str, np.ndarray]) -> None:
    """Saved variables (member, t, ...) of `data` into `variables` (netCDF4 variables or arrays by name) at
    members offset, offset + 1, ... and samples first, first + 1, ..."""
    for name, values in data.items():
        variables[name][offset:offset + values.shape[0], first:first + values.shape[1]] = values


def put_records(variables, offset: int, data: dict[str, np.ndarray]) -> None:
    """Per-member records (member, ...) of `data` into `variables` at members offset, offset + 1, ..."""
    for name, values in data.items():
        variables[name][offset:offset + len(values)] = values


def record_names(spec: Spec) -> list[str]:
    """The per-member records (RUN_RECORDS) a run of `spec` stores: how each member ran, what [measure]
    asks for, and its events' (ensemble.events.variables)."""
    return list(record_variables(spec))


def record_variables(spec: Spec) -> dict[str, tuple]:
    """The per-member records a run of `spec` stores: name -> (type, dims, units, long_name, comment, attributes),
    dims member first."""
    records = ["steps_accepted", "steps_rejected", "rhs_evals", "status", "failure_time"]
    records += ["growth_per_step"] if spec.measure["growth"] else []
    records += ["error_max", "error_final"] if spec.measure["error"] else []
    records += ["seconds_per_step"] if spec.measure["timing"] else []
    out = {name: (kind, ("member",), units, long_name, comment, {})
           for name, (kind, units, long_name, comment) in ((name, RUN_RECORDS[name]) for name in records)}
    return {**out, **event_variables(spec.events, spec.model, spec.save, spec.noise)} if spec.events else out


class Description:
    """Writes everything a result says besides its samples, records and member variables (member_variables) into
    `nc` (a new netCDF4 Dataset): attributes, dimensions, coordinates, with every variable declared. The member
    variables, the saved variables and the records are contiguous (member-major, as ranges write them)."""

    def __init__(self, nc: netCDF4.Dataset, spec: Spec):
        self.nc, self.spec, self.scene = nc, spec, spec.model

    def describe(self, command: str | None) -> None:
        """Everything the file says besides what ranges of members write: attributes, dimensions, coordinates."""
        self.nc.setncatts(global_attributes(self.spec, command))
        self._dimensions()
        self._parameters()
        self._settings()
        self._records()
        self._observables()

    def _dimensions(self) -> None:
        """member, t and the scene's dimensions that a saved variable or a parameter uses, with coordinates."""
        spec = self.spec
        used = {d for name in spec.save for d in self.scene.OBSERVABLES[name][0]}
        used |= {p.per for p in spec.declared.values() if p.per}
        sizes = {"member": spec.n_members, "t": spec.n_save, **self.scene.sizes(spec.constants),
                 **event_dimensions(spec.events)}
        for dim, size in sizes.items():
            self.nc.createDimension(dim, size)
        self._per_member("member", member_type(spec), ("member",), units="1", long_name="ensemble member index")
        times = self._coordinate("t", np.empty(0), "time since the start of the run", units="s", dims=("t",))
        for first in range(0, spec.n_save, TIMES_AT_ONCE):
            times[first:first + TIMES_AT_ONCE] = spec.times(first, first + TIMES_AT_ONCE)
        for dim, (values, long_name) in self.scene.coordinates(spec.constants).items():
            if dim in used:
                self._coordinate(dim, values, long_name)
        for name, count in event_dimensions(spec.events).items():
            self._coordinate(name, np.arange(count, dtype=np.int32), f"occurrence of event {name}, in order")
        self._per_member("sweep_point", np.int32, ("member",), units="1",
                         long_name="index of the member's point on the sweep grid")

    def _parameters(self) -> None:
        """Every member's parameter values; those a shape derives say so."""
        spec = self.spec
        derived = {name: source for source, p in self.scene.PARAMETERS.items() if f"{source}_shape" in spec.constants
                   for name in p.derives}
        for name, parameter in spec.declared.items():
            var = self._per_member(name, "f8", ("member", parameter.per) if parameter.per else ("member",),
                                   units=parameter.units, long_name=parameter.long_name)
            if name in derived:
                var.setncattr("comment", f"from the principal moments of the {derived[name]} "
                                         f"({spec.constants[derived[name] + '_shape']}) about its centre of mass")

    def _settings(self) -> None:
        """method, dt, rtol and atol per member, where the run sweeps them."""
        spec = self.spec
        if "method" in spec.sweep:
            methods = spec.methods  # in order of first use, as member_variables codes them
            self._per_member("method", "i1", ("member",), long_name="integration method",
                             flag_values=np.arange(len(methods), dtype=np.int8), flag_meanings=" ".join(methods))
        for key, (units, long_name, comment) in SETTING_UNITS.items():
            if key in spec.sweep:
                self._per_member(key, "f8", ("member",), fill_value=np.nan, units=units, long_name=long_name,
                                 comment=comment)

    def _records(self) -> None:
        """How each member ran: step counts, status, failure time, growth, and what [measure] asks for."""
        for name, (kind, dims, units, long_name, comment, attributes) in record_variables(self.spec).items():
            if name == "status":
                self._per_member(name, kind, dims, long_name=long_name, flag_values=Status.flag_values(),
                                 flag_meanings=Status.flag_meanings())
            else:
                self._per_member(name, kind, dims, fill_value=np.nan if kind == "f8" else None, units=units,
                                 long_name=long_name, comment=comment, **attributes)

    def _observables(self) -> None:
        """The saved variables; NaN marks a member's samples after it failed."""
        spec = self.spec
        for name in spec.save:
            dims, units, long_name = self.scene.OBSERVABLES[name]
            var = self._per_member(name, "f8", dims, fill_value=np.nan, units=units, long_name=long_name)
            if name in spec.noise:
                var.setncattr("observation_noise_stddev", spec.noise[name])
                var.setncattr("comment", "includes Gaussian observation noise of stddev observation_noise_stddev "
                                         "(same units), drawn per member from the run's seed")

    def _per_member(self, name, kind, dims, fill_value=None, **attributes):
        """A contiguous variable over member (and more), declared: ranges of members write its values."""
        var = self.nc.createVariable(name, kind, dims, contiguous=True, fill_value=fill_value)
        var.setncatts(attributes)
        return var

    def _coordinate(self, name, values, long_name, units="1", dims=None):
        var = self.nc.createVariable(name, values.dtype, dims or (name,))
        var.setncatts({"units": units, "long_name": long_name})
        if len(values):
            var[:] = values
        return var


def described(spec: Spec, command: str | None = None) -> netCDF4.Dataset:
    """The description of the result of `spec` (Description) in a diskless netCDF4 Dataset; close it after use.
    What ranges of members write is declared, never written: its size does not grow with the members."""
    nc = netCDF4.Dataset("description.nc", "w", diskless=True, persist=False)
    try:
        Description(nc, spec).describe(command)
    except BaseException:
        nc.close()
        raise
    return nc


def written_by_ranges(spec: Spec) -> list[str]:
    """The variables that each range of members writes (over member): its member variables, records and saved
    variables."""
    return [*member_variable_names(spec), *record_names(spec), *spec.save]


class Writer:
    """Creates the file with every variable declared; the members' values, records and samples arrive by member
    ranges.

    Use as a context manager: on success the file is fsynced and renamed into
    place; on an exception the temporary file is closed and left to the caller.
    """

    def __init__(self, path: str | Path, spec: Spec, command: str | None = None, reopen: bool = False):
        """`reopen`: continue the OUT.tmp an interrupted run of the same spec left (ensemble.parts checked it)."""
        self.path = Path(path)
        self.temporary = temporary_path(self.path)
        self.scene = spec.model
        self.spec = spec
        self.nc = netCDF4.Dataset(self.temporary, "a" if reopen else "w", format="NETCDF4")
        self.nc.set_fill_off()  # every value is written (NaN after a failure too): HDF5 need not pre-fill the storage
        try:
            if reopen:
                self._describe_again(command)
            else:
                Description(self.nc, spec).describe(command)
                self._allocate()
        except BaseException as error:
            self.__exit__(type(error), error, None)
            raise

    def _describe_again(self, command: str | None) -> None:
        """A resumed OUT.tmp's attributes and the variables that no range writes, written again from the run file
        (an edit of them since, of a unit or a coordinate, must not reach the result); StoreError when its
        variables are not the run file's."""
        found = self.nc
        fresh = described(self.spec, command)
        try:
            shape = {name: (v.dimensions, v.dtype) for name, v in fresh.variables.items()}
            if {name: (v.dimensions, v.dtype) for name, v in found.variables.items()} != shape:
                raise StoreError(f"{self.temporary}: its variables were changed since the run stopped; use --force "
                                 f"to start over")
            for source, target in [(fresh, found), *((fresh[n], found[n]) for n in fresh.variables)]:
                for name in set(target.ncattrs()) - set(source.ncattrs()) - {"_FillValue"}:
                    target.delncattr(name)
                target.setncatts({k: source.getncattr(k) for k in source.ncattrs() if k != "_FillValue"})
            for name in set(fresh.variables) - set(written_by_ranges(self.spec)):
                found[name][:] = fresh[name][:]
        finally:
            fresh.close()

    def _allocate(self) -> None:
        """Give every variable that ranges write its whole space now, by writing each one's last value (NaN, or
        0 for an integer; the run writes its own later): the records are written only when every member is in
        (ensemble.parts), and a change of the file's structure then, by a run killed midway, would cost every
        part."""
        for name in written_by_ranges(self.spec):
            variable = self.nc.variables[name]
            variable[tuple(size - 1 for size in variable.shape)] = np.nan if variable.dtype.kind == "f" else 0

    def write_samples(self, start: int, first: int, data: dict[str, np.ndarray]) -> None:
        """Store saved variables (member, t, ...) of members start, start + 1, ... at samples first, first + 1,
        ..."""
        put_samples(self.nc.variables, start, first, data)

    def write(self, start: int, data: dict[str, np.ndarray]) -> None:
        """Store the per-member records or member variables (member, ...) of members start, start + 1, ..."""
        put_records(self.nc.variables, start, data)

    def sync(self) -> None:
        """Hand what is written to the system (HDF5 holds small writes back): fsync_path(temporary) then puts it on
        the disk. Call it from the thread that writes."""
        self.nc.sync()

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        """On success: close, fsync and rename OUT.tmp to OUT. On an exception: close OUT.tmp and leave it; the
        caller keeps it for a resume or deletes it (ensemble.parts)."""
        try:
            self.nc.close()
        except (OSError, RuntimeError):
            if kind is None:
                raise
            # a write already failed (a full disk): closing fails too, and the first error is the one to report
        if kind is None:
            fsync_path(self.temporary)
            os.replace(self.temporary, self.path)
            fsync_path(self.path.parent)
        return False
