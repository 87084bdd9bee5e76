"""`ensemble tune`: times the candidate layouts on this machine (ensemble.tuning says what they are and keeps the
winners). The tuner runs the engine's kernels; the engine reads only the kept tuning, so neither imports the other
both ways."""
from __future__ import annotations

import json
import math

from .tuning import TIMED_BLOCKS, Tuning, apply, host_key, set_features, vector_features, width_name

CANDIDATE_MARGIN = 1.05  # a candidate replaces the default only when this much faster: blocks within 5% are noise here
ROUNDS = 2  # each candidate's process runs this many times, the candidates in turn


def tune(say=print) -> tuple[Tuning, dict]:
    """Time the candidates on this machine and return (the winning Tuning, the rates measured). Each vector width
    runs in a process of its own (it is fixed once Numba has compiled), ROUNDS times in turn; the top's rk4
    kernel at the engine's block and the chain's verlet at 16 masses vote with the geometric mean of their rates.
    Then, under the winning width, all in one process, ROUNDS times: the blocks and the loop order of the
    generated kernels (the top's rk4, top_layouts), and a field of sites' splitting layouts (the chain's verlet
    at 16 and 1024 masses: blocks of one, two or four SIMD vectors, fused sweeps in tiles or one piece at a time;
    sites_layouts). A candidate replaces the default only when CANDIDATE_MARGIN faster."""
    widths = [512, 256] if "avx512f" in host_key()["vectors"].split(",") else [None]
    from .engine.kernels import BLOCK

    _compiled([(bits, [BLOCK], True, []) for bits in widths])
    rounds = [{bits: _measured(bits, [BLOCK]) for bits in widths} for _ in range(ROUNDS)]
    rates = {bits: {case: sum(r[bits][case] for r in rounds) / ROUNDS for case in rounds[0][bits]} for bits in widths}
    for bits in widths:
        say(f"  vectors {width_name(bits):>14}: " + ", ".join(f"{k} {v:.3g}" for k, v in rates[bits].items()))
    spread = max(_spread([r[bits] for r in rounds]) for bits in widths)
    score = {bits: math.prod(rates[bits].values()) ** (1 / len(rates[bits])) for bits in widths}
    # LLVM's own choice is one of the two widths: a width is kept only when clearly faster than the other
    bits = _pick({None: min(score.values()), **score}, None, spread)
    tops, layouts = top_layouts(BLOCK), sites_layouts()
    _compiled([(bits, tops[1:], False, layouts[1:2]), (bits, [], False, layouts[2:])])  # tops[0] is compiled
    timed = [_measured(bits, tops, chain=False, layouts=layouts) for _ in range(ROUNDS)]
    mean = {name: sum(t[name] for t in timed) / ROUNDS for name in timed[0]}
    spread = max(spread, _spread(timed))
    say("  generated kernels under the chosen vectors: " + ", ".join(f"{top_name(top)} {mean[top_name(top)]:.3g}"
                                                                     for top in tops))
    say("  fields of sites under the chosen vectors: " + ", ".join(f"{layout_name(*lay)} {mean[layout_name(*lay)]:.3g}"
                                                                    for lay in layouts))
    say(f"  spread of one case's rate between rounds: up to {spread:.3f}x; a candidate replaces the engine's rule "
        f"only when faster than it by more (and by {CANDIDATE_MARGIN}x at least)")
    block = _pick({b: mean[top_name(b)] for b in tops}, BLOCK, spread)
    short = _pick({b: mean[layout_name(n, b, fused)] for n, b, fused in layouts if n == 16}, layouts[0][1], spread)
    fused = _pick({fused: mean[layout_name(n, b, fused)] for n, b, fused in layouts if n > 16}, True, spread)
    measured = {"vectors": {width_name(b): rates[b] for b in widths}, "layouts": mean, "spread": spread,
                "units": "member-steps/s (top), mass-steps/s (chain)"}
    return Tuning(vector_bits=bits, block=None if block == BLOCK else block,
                  sites_block=None if short == layouts[0][1] else short,
                  fused_sweeps=None if fused else False), measured


def _pick(rates: dict, default, spread: float = 1.0):
    """The fastest candidate of `rates`, where any but `default` must be faster by CANDIDATE_MARGIN and by more
    than `spread` (how far one case's rate moved between rounds) to win."""
    margin = max(CANDIDATE_MARGIN, spread)
    return max(rates, key=lambda c: rates[c] / (1.0 if c == default else margin))


def _spread(rounds: list[dict]) -> float:
    """The largest ratio between two rounds' rates of one case (rounds: case -> rate, one dict a round)."""
    return max(max(r[case] for r in rounds) / min(r[case] for r in rounds) for case in rounds[0])


def top_layouts(block: int) -> list[int]:
    """The generated kernels' blocks (members per block) `ensemble tune` times on the top's rk4: the engine's
    block first, then the other TIMED_BLOCKS."""
    return [block, *(b for b in TIMED_BLOCKS if b != block)]


def top_name(block: int) -> str:
    return f"top rk4, block {block}"


def sites_layouts() -> list[tuple[int, int, bool]]:
    """The fields of sites' layouts `ensemble tune` times, (sites, members per block, fused sweeps): at 16 sites,
    whose blocks' rows fit the L1 cache, blocks of two SIMD vectors (the rule's) and four; at 1024, whose rows
    outgrow it, blocks of one vector fused in tiles (the rule's) and swept one piece at a time. The rule's first
    in each."""
    from .engine.sites import vector_doubles

    vector = vector_doubles()
    return [(16, 2 * vector, True), (16, 4 * vector, True), (1024, vector, True), (1024, vector, False)]


def layout_name(n: int, block: int, fused: bool) -> str:
    return f"chain verlet N={n}, block {block}" + ("" if fused else ", one piece at a time")


def _measured(bits: int | None, tops: list, chain: bool = True, layouts: list = ()) -> dict[str, float]:
    """measure_here's rates, from a process of its own."""
    return _in_processes([(bits, tops, chain, list(layouts), False)])[0]


def _compiled(asks: list[tuple]) -> None:
    """Compile (into Numba's cache) the kernels of each of `asks`, (bits, tops, chain, layouts) as _measured
    takes them, in processes that run at once: the timed processes then load them. Compiling is most of
    `ensemble tune`'s minute, and it needs no quiet machine."""
    _in_processes([(*ask, True) for ask in asks])


def _in_processes(asks: list[tuple]) -> list[dict]:
    """measure_here's answer to each of `asks` (its arguments), each from a process of its own, started at once."""
    import subprocess
    import sys

    started = [(ask[0], subprocess.Popen([sys.executable, "-c", "from ensemble.tuner import _serve; "
                                          f"_serve({json.dumps(ask)!r})"],
                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
               for ask in asks]
    answers = []
    for bits, process in started:
        out, err = process.communicate()
        if process.returncode != 0:
            raise RuntimeError(f"timing the {width_name(bits)} vectors failed: "
                               f"{(err.strip().splitlines() or ['?'])[-1]}")
        answers.append(json.loads(out.strip().splitlines()[-1]))
    return answers


def _serve(asked: str) -> None:
    print(json.dumps(measure_here(*json.loads(asked))))


def measure_here(bits: int | None, tops: list, chain: bool = True, layouts: list = (),
                 compile_only: bool = False) -> dict[str, float]:
    """In a process that has compiled nothing yet, with LLVM preferring `bits`-bit vectors: the top's rk4 kernel
    in each of `tops` (members per block), in member-steps/s; the chain's verlet at 16 masses in the engine's
    layout (with chain) and in each of `layouts`, (n, block, fused), in mass-steps/s. Each the median of 5 calls,
    the kernels called in turn. compile_only: call each once (compiling it or loading it from the cache), and
    measure nothing."""
    import numpy as np

    set_features(vector_features(bits))
    from .engine import launch
    from .methods import METHODS
    from .scenes import SCENES

    members, steps = 32768, 1000
    rng = np.random.default_rng(0)
    top = {"lambda1": np.full(members, 1e-3), "lambda3": np.full(members, 2e-3), "c": np.full(members, 1e-4),
           "spin0": np.full(members, 60.0), "tilt0": rng.uniform(0.02, 0.2, members),
           "azimuth0": rng.uniform(0.0, 6.28, members)}
    calls = {}  # name: (launch, steps it makes)
    for block in tops:
        apply(Tuning(block=block))
        calls[top_name(block)] = (launch.Launch(SCENES["top"], METHODS["rk4"], top, {}, n_save=2,
                                                          save_dt=steps * 1e-3, dt=1e-3), members * steps)
    chains = [(16, None, None), (2, None, None)] if chain else []  # a short chain too: its rate falls otherwise
    for n, block, fused in chains + [tuple(layout) for layout in layouts]:
        # sites_block sets the block where rows fit the L1 cache; at 1024 sites the rule gives the layout's own
        apply(Tuning(sites_block=block, fused_sweeps=None if fused is not False else False))
        count = 65536 // n  # chains
        masses = {"m": np.ones((count, n)), "k": np.ones((count, n + 1)), "x0": rng.normal(0, 0.1, (count, n)),
                  "v0": np.zeros((count, n))}
        name = f"chain verlet N={n}" if block is None else layout_name(n, block, fused)
        calls[name] = (launch.Launch(SCENES["chain"], METHODS["verlet"], masses, {"n": n, "boundary": "fixed"},
                                     n_save=2, save_dt=steps * 0.01, dt=0.01), n * count * steps)
    apply(None)
    if compile_only:
        for call, _ in calls.values():
            call.run()
        return {}
    seconds = _seconds_in_turn([call for call, _ in calls.values()])
    return {name: work / s for (name, (_, work)), s in zip(calls.items(), seconds)}


def _seconds_in_turn(calls: list, repeats: int = 5) -> list[float]:
    """Median seconds of each launch's run, the launches called in turn `repeats` times (after one call each that
    compiles or loads its kernel), so that a slow spell of the machine hits them all."""
    import statistics
    import time

    for call in calls:
        call.run()
    seconds = [[] for _ in calls]
    for _ in range(repeats):
        for call, timed in zip(calls, seconds):
            start = time.perf_counter()
            call.run()
            timed.append(time.perf_counter() - start)
    return [statistics.median(timed) for timed in seconds]
