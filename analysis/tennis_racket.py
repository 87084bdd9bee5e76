"""The tennis-racket effect: do small tilts about the intermediate axis grow at the rate Euler's equations give?

    ensemble run runs/tennis_racket.toml && python analysis/tennis_racket.py results/tennis_racket.nc

Linearized about a spin Omega around the intermediate axis, a small tilt grows as exp(s t) with
s = Omega sqrt((lambda3 - lambda2)(lambda2 - lambda1) / (lambda1 lambda3)). Computes s from the result's own
moments and spins, compares each body's fitted growth rate, and its flip period where it flipped three times;
exits 1 when a growth rate misses by more than TOLERANCE (relative).
"""
import argparse
import sys

import numpy as np

import ensemble

TOLERANCE = 1e-4  # the fit reads the growth off a record of tilts that are small, not infinitesimal

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("result", nargs="?", default="results/tennis_racket.nc", help="a result of runs/tennis_racket.toml")
ds = ensemble.open(parser.parse_args().result)
fits = ensemble.fit(ds)  # per member: growth_rate (1/s), flip_period (s), ...
l1, l2, l3 = ds["lambda1"], ds["lambda2"], ds["lambda3"]  # kg m2, ascending
growth = ds["spin0"] * np.sqrt((l3 - l2) * (l2 - l1) / (l1 * l3))
miss = np.abs(fits["growth_rate"] / growth - 1)
flipped = fits["flip_period_theory"].where(fits["flip_period"].notnull())  # bodies that flipped 3 times
for spin, members in miss.groupby(ds["spin0"]):
    chosen = {"member": members["member"]}
    print(f"spin {spin:g} rad/s: growth rate {float(fits['growth_rate'].sel(chosen).mean()):.6g} 1/s, "
          f"Euler {float(growth.sel(chosen).mean()):.6g} 1/s, largest miss {float(members.max()):.1e}; "
          f"flip period {float(fits['flip_period'].sel(chosen).mean()):.5g} s "
          f"(elliptic formula {float(flipped.sel(chosen).mean()):.5g} s)")
sys.exit(0 if bool((miss <= TOLERANCE).all()) else 1)
