"""Ctrl-C, honoured whenever it lands: remembered, so that one a library swallowed still stops the run at its
next chunk; held at the moments it must not cut short (while a run makes its result complete or cleans up),
then raised, or dropped when the run is stopping anyway."""
from __future__ import annotations

import signal
import threading

_requested = threading.Event()


def _remember_and_raise(*_) -> None:
    _requested.set()
    raise KeyboardInterrupt


def remember() -> None:
    """Have SIGINT remembered as well as raised (the command line calls it): a KeyboardInterrupt raised inside a
    library call that swallows it (seen in set() over a large numpy array) is then raised again by check()."""
    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _remember_and_raise)


def check() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C came (since remember()) and was lost: a run calls it between chunks."""
    if _requested.is_set():
        raise KeyboardInterrupt


class LateInterrupt(KeyboardInterrupt):
    """Ctrl-C that came while the run made its result complete: the result is whole, nothing is left to resume."""

    def __init__(self, summary):
        super().__init__()
        self.summary = summary  # what the run did (runner.Summary)


class HeldInterrupts:
    """While held (start .. stop), SIGINT is recorded instead of raised. Python runs signal handlers in the main
    thread only, so elsewhere, or when SIGINT is neither Python's default handler nor remember()'s (ignored, or a
    caller's own), this does nothing."""

    def __init__(self):
        self.previous = None
        self.caught = False

    def start(self) -> None:
        if self.previous is not None or threading.current_thread() is not threading.main_thread():
            return
        if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, _remember_and_raise):
            self.previous = signal.signal(signal.SIGINT, self._catch)

    def _catch(self, *_) -> None:
        self.caught = True

    def stop(self) -> bool:
        """End the hold; whether a SIGINT came during it."""
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
            self.previous = None
        return self.caught

    def __enter__(self):  # a hold whose interrupts are dropped: the block ends in an exception anyway
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


def on_a_thread(function, *args):
    """function(*args) on a daemon thread while the caller waits: a Ctrl-C reaches the caller at once, as a
    KeyboardInterrupt between two waits, never inside a C callback of the function's (LLVM calls back into Python
    while it compiles, and an interrupt raised there is only printed, "Exception ignored", and lost). The thread is
    left to finish on its own or to end with the process. Returns what function returns, or raises what it
    raised."""
    outcome = {}

    def call():
        try:
            outcome["value"] = function(*args)
        except BaseException as error:  # noqa: BLE001 (handed to the caller)
            outcome["error"] = error

    worker = threading.Thread(target=call, daemon=True, name="ensemble-compile")
    worker.start()
    while worker.is_alive():
        worker.join(0.1)
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]
