"""The Lorenz system, x' = sigma (y - x), y' = x (rho - z) - y, z' = x y - beta z: a scene of your own.

The yardstick of GPU ensemble papers (DiffEqGPU's GPUODEBenchmarks, MPGOS): sigma = 10, beta = 8/3, rho swept or
drawn over [0, 21], from (1, 0, 0), 1000 fixed steps of dt = 0.001. runs/lorenz.toml is that benchmark;
docs/gpu.md gives its rates beside the published ones. See docs/scenes.md for the contract.
"""
from ensemble import Parameter

NAME = "lorenz"

STATE = {"x": ("1", "convection intensity"), "y": ("1", "horizontal temperature difference"),
         "z": ("1", "vertical temperature difference")}

PARAMETERS = {  # x0, y0 and z0 start the state; the others are the right-hand side's, in this order
    "sigma": Parameter("1", "Prandtl number", default=10.0),
    "rho": Parameter("1", "Rayleigh number over its critical value"),
    "beta": Parameter("1", "the cell's aspect factor", default=8.0 / 3.0),
    "x0": Parameter("1", "x at t = 0", default=1.0),
    "y0": Parameter("1", "y at t = 0", default=0.0),
    "z0": Parameter("1", "z at t = 0", default=0.0),
}


def rhs(t, x, y, z, sigma, rho, beta):
    """(x', y', z') of one member at time t."""
    return sigma * (y - x), x * (rho - z) - y, x * y - beta * z
