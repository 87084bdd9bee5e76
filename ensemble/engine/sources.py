"""The engine's files whose code the CPU kernels compile in, relative to this folder: every kernel's file holds a
hash of them (blocks.HELPERS), and so does this machine's tuning (tuning.engine_hash). No Numba here, so that
reading a tuning imports none."""
ENGINE_SOURCES = ("blocks.py", "tuples.py", "frames.py", "runge_kutta.py", "adaptive.py", "control.py",
                  "splitting.py", "../results.py")
