"""SIGINT and SIGTERM in garmentnerf: what they raise, and holding them while work that must not be
cut short runs (they act when it ends).

What they raise is :class:`Interrupted` (:func:`interrupting`), a KeyboardInterrupt that the
commands catch to stop cleanly and exit with status 130. Holding: a training step's update, so
that a checkpoint never holds a half-updated step (see :mod:`garmentnerf.train.trainer`'s
"Interruption, kills and a full disk"), and native work that runs on threads the main thread waits
for (:func:`deferred_interrupts`).
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["HeldInterrupts", "Interrupted", "deferred_interrupts", "interrupting", "raise_interrupted"]


class Interrupted(KeyboardInterrupt):
    """A KeyboardInterrupt raised by garmentnerf's SIGINT and SIGTERM handlers (its message: the
    signal's name); ``except KeyboardInterrupt`` catches it.

    Not a plain KeyboardInterrupt because CPython (3.11) marks a KeyboardInterrupt that leaves an
    ``exec()`` of a string as never handled, and then ends the process by SIGINT at exit even after
    the program caught it and chose its exit status: ``garmentnerf train`` interrupted while a lazy
    import built a dataclass (``dataclasses`` creates ``__init__`` with ``exec``) saved its
    checkpoint, returned 130 and died of SIGINT (exit -2). CPython checks for the exact type, so a
    subclass passes through.
    """


def raise_interrupted(signum, frame) -> None:
    """A signal handler: raise :class:`Interrupted` named after the signal."""
    raise Interrupted(signal.Signals(signum).name)


@contextlib.contextmanager
def interrupting(*signals: signal.Signals):
    """While the block runs, each of ``signals`` raises :class:`Interrupted` (default: SIGINT and
    SIGTERM); ``with`` restores their handlers. A signal that is ignored stays ignored (a command
    started in the background by a shell without job control has SIGINT ignored). Off the main
    thread, where no handler can be set, it only runs the body."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    try:
        for sig in signals or (signal.SIGINT, signal.SIGTERM):
            handler = signal.getsignal(sig)
            if handler is not signal.SIG_IGN:
                previous[sig] = signal.signal(sig, raise_interrupted)
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


class HeldInterrupts:
    """SIGINT and SIGTERM wait while :meth:`hold` is active, then act (e.g. raise KeyboardInterrupt).

    The handlers are wrapped only from the main thread and only where they are Python functions
    (Python's default SIGINT handler, ``garmentnerf train``'s SIGTERM one); ``with`` restores them.
    """

    def __init__(self):
        self._previous: dict = {}
        self._holding = False
        self._pending = None

    def __enter__(self) -> "HeldInterrupts":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                handler = signal.getsignal(sig)
                if callable(handler):
                    self._previous[sig] = handler
                    signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _handle(self, signum, frame) -> None:
        if self._holding:
            self._pending = (signum, frame)
            return
        self._previous[signum](signum, frame)

    @contextlib.contextmanager
    def hold(self):
        """Run the body without interruption by SIGINT/SIGTERM; one that came meanwhile acts after it."""
        self._holding = True
        try:
            yield
        finally:
            self._holding = False
        pending, self._pending = self._pending, None
        if pending is not None:
            self._previous[pending[0]](*pending)


@contextlib.contextmanager
def deferred_interrupts():
    """Run the body without interruption by SIGINT/SIGTERM; one that came meanwhile acts after it.

    For native work on threads the main thread joins: scipy's ``cKDTree.query(workers=-1)`` joins
    its threads where a KeyboardInterrupt can land, and returns while they still write into arrays
    it then frees (a segfault on Ctrl-C). Off the main thread, where no signal handler runs, it
    only runs the body.
    """
    with HeldInterrupts() as held, held.hold():
        yield
