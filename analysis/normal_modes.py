"""Coupled oscillators: are the frequencies each chain rings at the roots of det(K - w^2 M) = 0?

    ensemble run runs/two_mass.toml && python analysis/normal_modes.py results/two_mass.nc

Builds each chain's stiffness matrix K and mass matrix M from the result's own masses and springs (walls at
both ends), solves K v = w^2 M v with scipy, and compares the fitted frequencies; exits 1 when one misses by
more than TOLERANCE (relative). For two equal masses and three equal springs: w^2 = k/m and 3 k/m.
"""
import argparse
import sys

import numpy as np
from scipy.linalg import eigh

import ensemble

TOLERANCE = 1e-6  # velocity Verlet at the run file's step moves the frequencies by about 1e-7

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("result", nargs="?", default="results/two_mass.nc", help="a result of runs/two_mass.toml")
ds = ensemble.open(parser.parse_args().result)
assert ds.attrs["boundary"] == "fixed", "this example builds K for walls at both ends"
fits = ensemble.fit(ds)  # per member and mode: frequency (rad/s), frequency_stderr, ...
worst = 0.0
for member in ds["member"].values:
    m, k = ds["m"].sel(member=member).values, ds["k"].sel(member=member).values  # kg per mass, N/m per spring
    stiffness = np.diag(k[:-1] + k[1:]) - np.diag(k[1:-1], 1) - np.diag(k[1:-1], -1)
    omega = np.sqrt(eigh(stiffness, np.diag(m), eigvals_only=True))  # rad/s, ascending as the modes are
    fitted = fits["frequency"].sel(member=member).values
    worst = max(worst, float(np.nanmax(np.abs(fitted / omega - 1))))
    if member < 3:
        print(f"member {member}: fitted {np.round(fitted, 9)} rad/s, det(K - w^2 M) = 0 at {np.round(omega, 9)}")
print(f"{ds.sizes['member']} chains; largest relative miss {worst:.1e}")
sys.exit(0 if worst <= TOLERANCE else 1)
