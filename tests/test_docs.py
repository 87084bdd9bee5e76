"""The READMEs stay true: their Python examples run and give what they say, and every command they give names a
script, an option and a run file that exist."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .test_analysis import run_small

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", ROOT / "analysis" / "README.md", ROOT / "analysis" / "bench" / "README.md",
        *sorted((ROOT / "docs").glob("*.md"))]


# The reference pages the README points to, whose examples open the README's run files' results
REFERENCE = [ROOT / "docs" / name for name in ("running.md", "resume.md", "cluster.md", "runfiles.md", "dataset.md",
                                              "physics.md", "methods.md", "contributing.md")]


def python_examples() -> list[str]:
    """The Python examples of the README and of its reference pages."""
    return [example for doc in (ROOT / "README.md", *REFERENCE)
            for example in re.findall(r"^```python\n(.*?)^```", doc.read_text(), re.S | re.M)]


def commands(text: str) -> list[str]:
    """The commands a document gives: each line of its sh blocks (a line ending in a backslash joined to the next)
    and each inline code span, whitespace made one space, cut at a comment or a `&&`."""
    blocks = re.findall(r"^```sh\n(.*?)^```", text, re.S | re.M)
    lines = [line for block in blocks for line in block.replace("\\\n", " ").splitlines()]
    spans = [" ".join(span.split()) for span in re.findall(r"(?<!`)`([^`]+)`(?!`)", re.sub(r"```.*?```", "", text,
                                                                                          flags=re.S))]
    parts = [part.split(" #")[0].strip() for line in lines + spans for part in line.split("&&")]
    return [part for part in parts if part]


def test_every_python_example_in_the_readme_runs_and_gives_what_it_says(tmp_path, monkeypatch):
    """The examples open results the README's run files make (here with 4 members a sweep point); the notebook
    tour runs runs/aerobie.toml itself, whole, and its fit's means are the course's law."""
    for name in ("aerobie.toml", "aerobie_noisy.toml", "two_mass.toml"):
        run_small(name, tmp_path / "results", 4)
    (tmp_path / "runs").symlink_to(ROOT / "runs")
    monkeypatch.chdir(tmp_path)
    examples = python_examples()
    assert len(examples) >= 6
    done = []
    for example in examples:
        namespace = {}
        exec(compile(example, "README.md", "exec"), namespace)
        done.append(namespace)
    modes = next(n for n in done if "shapes" in n)
    assert modes["omega"] == pytest.approx([1.0, np.sqrt(3.0)])  # the comment's [1, 1.732...]
    tour = next(n for n in done if "fits" in n and "ensemble" in n)
    assert tour["ds"].sizes["member"] == 12  # the last line opened the result written above (4 a sweep point)
    law = tour["fits"].c * (1 / 1.0e-3 - 1 / 2.0e-3)  # the run file's lambda1 and lambda3
    assert tour["fits"].sizes["member"] == 600 and np.allclose(tour["fits"].rate, law, rtol=1e-8)
    outcome = next(n for n in done if "outcome" in n)["outcome"]
    assert outcome.samples.shape == (11, 3, 1)  # (n_save, state, members), as the comment says


def help_texts(commands: list[tuple[str, ...]]) -> list[str]:
    """The --help of each command (python's arguments), the processes run side by side."""
    processes = [subprocess.Popen([sys.executable, *command, "--help"], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, cwd=ROOT) for command in commands]
    texts = []
    for command, process in zip(commands, processes):
        out, err = process.communicate()
        assert process.returncode == 0, f"{' '.join(command)} --help: {err.strip().splitlines()[-1:]}"
        texts.append(out)
    return texts


RUN_FILES = sorted((ROOT / "runs").glob("*.toml"))


def runfile_commands(text: str) -> list[str]:
    """The commands a run file's comments give: from `ensemble ` or `python ` to the end of the line or of the
    code span, cut at a `&&`."""
    comments = [line.split("#", 1)[1] for line in text.splitlines() if "#" in line]
    found = [c for line in comments for c in re.findall(r"((?:ensemble|python) [^`;]*?)(?:`|$|\.(?: |$))", line)]
    return [part.strip() for command in found for part in command.split("&&") if part.strip()]


@pytest.mark.parametrize("doc", DOCS + RUN_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_command_in_the_docs_names_what_exists(doc):
    """`python analysis/X.py --option`: X.py exists and its --help lists --option; `ensemble SUB --option`:
    `ensemble SUB --help` lists it; runs/X.toml: the run file exists. The same for the commands in run files'
    comments, which are all `python analysis/...` or `ensemble ...`."""
    if doc.suffix == ".toml":
        given = runfile_commands(doc.read_text())
        strays = [c for c in given if c.split()[0] == "python" and not c.split()[1].startswith("analysis/")]
        assert not strays, f"{doc.name}: {strays}"
    else:
        given = commands(doc.read_text())
    options = {}  # the command whose --help must list them (script, or -m ensemble SUB): options
    for command in given:
        words = command.split()
        if words[:2] == ["python", "-m"] or words[0] not in ("python", "ensemble") or len(words) < 2:
            continue
        if words[0] == "python":
            if not words[1].startswith("analysis/"):
                continue
            assert (ROOT / words[1]).is_file(), f"{doc.name}: {command}: no {words[1]}"
            key = (words[1],)
        else:
            key = ("-m", "ensemble", words[1])
        options.setdefault(key, set()).update(w.split("=")[0] for w in words if w.startswith("--") and len(w) > 2)
        for word in words:
            if word.startswith("runs/"):
                assert (ROOT / word).is_file(), f"{doc.name}: {command}: no {word}"
    assert any(key[0] == "-m" for key in options) or doc.parent.name in ("analysis", "bench", "docs", "runs"), given
    for (key, wanted), text in zip(options.items(), help_texts(list(options))):
        listed = set(re.findall(r"--[a-z][a-z0-9-]*", text))
        assert wanted <= listed, f"{doc.name}: {' '.join(key)} has no {sorted(wanted - listed)}"


def test_every_image_the_docs_show_is_in_the_checkout():
    """The README's and docs' pictures are committed files (docs/figures.py makes them; *.png is otherwise
    ignored): each image link names an existing PNG."""
    shown = []
    for doc in DOCS:
        for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", doc.read_text()):
            shown.append(target)
            assert (doc.parent / target).is_file(), f"{doc.name}: no {target}"
    assert len(shown) >= 6, shown
