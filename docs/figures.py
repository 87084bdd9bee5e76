"""Make the charts the README and docs/ show, docs/images/*.png, from the run files in runs/.

    pip install -e ".[plot]" && python docs/figures.py [RUN ...]

With run names (work_precision_top, say), makes only their charts.

Runs each run file below through the public API (results in a temporary folder), then draws its charts with
`ensemble fit`, `ensemble stability` or `ensemble work-precision` --charts, and keeps the ones the docs show.
About a minute, most of it compiling kernels on a machine that has not run them yet.
"""
import shutil
import sys
import tempfile
from pathlib import Path

import ensemble
from ensemble.cli import main as command

ROOT = Path(__file__).resolve().parent.parent
IMAGES = ROOT / "docs" / "images"

# run file: (the command that charts its result, the charts kept)
FIGURES = {
    "aerobie": ("fit", ["tilt_decay_tilt", "tilt_decay_rates"]),
    "prolate": ("fit", ["tilt_decay_tilt"]),
    "two_mass": ("fit", ["mode_frequencies_spectrum"]),
    "tennis_racket": ("fit", ["body_rates_tilt", "body_rates_flips"]),
    "tennis_racket_noisy": ("fit", ["body_rates_flip_z"]),
    "stability_chain": ("stability", ["stability_map"]),
    "work_precision_top": ("work-precision", ["work_precision"]),
    "pendulum": ("fit", ["fit_period"]),
    "heavy_top": ("fit", ["fit_nutation", "fit_precession"]),
    "sleeping_top": ("fit", ["fit_max_tilt"]),
}


def main(names: list[str]) -> int:
    unknown = sorted(set(names) - set(FIGURES))
    if unknown:
        print(f"figures.py: no figure of {', '.join(unknown)}; known: {', '.join(FIGURES)}", file=sys.stderr)
        return 2
    IMAGES.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as folder:
        for name in names or FIGURES:
            analysis, keep = FIGURES[name]
            result = Path(folder) / f"{name}.nc"
            ensemble.run(ROOT / "runs" / f"{name}.toml", result, progress=False)
            status = command([analysis, str(result), "--charts", folder])
            if status not in (0, 1):
                return status
            for chart in keep:
                shutil.copy(Path(folder) / f"{name}_{chart}.png", IMAGES / f"{name}_{chart}.png")
                print(f"docs/images/{name}_{chart}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
