"""The flying ring: does each top's tilt decay at the rate the course derives, c (1/lambda1 - 1/lambda3)?

    ensemble run runs/aerobie.toml && python analysis/tilt_decay.py results/aerobie.nc

Prints, per drag coefficient, the mean fitted rate beside the law computed here from the result's own
parameters; exits 1 when a member misses it by more than TOLERANCE (relative).
"""
import argparse
import sys

import numpy as np

import ensemble

TOLERANCE = 1e-6  # rk4 at the run file's step moves the rates by less than 1e-9

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("result", nargs="?", default="results/aerobie.nc", help="a result of runs/aerobie.toml")
ds = ensemble.open(parser.parse_args().result)
fits = ensemble.fit(ds)  # per member: rate, rate_stderr, ...
law = ds["c"] * (1 / ds["lambda1"] - 1 / ds["lambda3"])  # 1/s, per member
miss = np.abs(fits["rate"] / law - 1)
for c, members in miss.groupby(ds["c"]):
    rate = fits["rate"].sel(member=members["member"])
    print(f"c = {c:g} kg m2/s: fitted rate {float(rate.mean()):.8g} 1/s over {rate.size} tops, "
          f"law {float(law.sel(member=members['member']).mean()):.8g} 1/s, largest miss {float(members.max()):.1e}")
sys.exit(0 if bool((miss <= TOLERANCE).all()) else 1)
