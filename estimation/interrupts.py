"""Interrupts: SIGTERM taken as Ctrl-C, and critical sections that a signal cannot cut in two.

A run stops the same way on Ctrl-C (SIGINT: Python raises KeyboardInterrupt) and on SIGTERM
(``timeout``, ``docker stop``, a job scheduler), once the command line has called
``terminate_as_interrupt``: the handler raises ``Terminated``, a KeyboardInterrupt, so every
``except KeyboardInterrupt`` of the interrupt path (``runner.run(interruptible=True)``) takes it
as Ctrl-C, and ``sigterm_received`` tells the command line to exit 143 instead of 130.

``held_signals`` holds SIGINT and SIGTERM for the length of a block that must not be left half
done (an innovation log's compaction, the writing of a run's results): a signal that arrives in
it is recorded, not acted on, and the caller decides, after the block, to deliver it
(``deliver``: the interrupt is raised there, as if it had come just after the block) or to
note it (the runner then finishes what it had, as after Ctrl-C in its loop). A second
signal of the same block is acted on at once: a user who presses Ctrl-C twice gets out.
Outside the main thread signals cannot be handled and nothing is held.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Terminated", "deliver", "held_signals", "interrupt_in", "interrupt_name",
           "sigterm_received", "terminate_as_interrupt"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_received: list[int] = []  # SIGTERM once the handler of terminate_as_interrupt ran


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C's KeyboardInterrupt would be (``terminate_as_interrupt``)."""


def _raise_terminated(signum, frame) -> None:
    _received.append(signum)
    raise Terminated("terminated (SIGTERM)")


def terminate_as_interrupt() -> None:
    """From now on SIGTERM raises ``Terminated`` in the main thread (a no-op in another
    thread): the command line's runs then stop on it as on Ctrl-C."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)


def sigterm_received() -> bool:
    """Whether this process has taken a SIGTERM as an interrupt (exit code 143, not 130)."""
    return bool(_received)


def interrupt_name(what: BaseException | int) -> str:
    """How the run's messages name what stopped it: 'SIGTERM' for ``Terminated`` or the signal
    number SIGTERM (one ``held_signals`` held), else 'Ctrl-C'."""
    return "SIGTERM" if isinstance(what, Terminated) or what == signal.SIGTERM else "Ctrl-C"


def interrupt_in(exc: BaseException) -> KeyboardInterrupt | None:
    """The interrupt (KeyboardInterrupt: Ctrl-C, or ``Terminated``) that ``exc`` is, or carries
    as its cause or context; None when it carries none. A signal whose handler runs while a C
    function is being called (numba's dispatcher preparing a kernel's arguments) can leave its
    KeyboardInterrupt pending when the function returns a result: Python then raises
    ``SystemError('... returned a result with an exception set')`` from it, which an ``except
    Exception`` meant for an estimator's own failure would take for one, and the interrupt would
    be lost."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


@contextmanager
def held_signals() -> Iterator[list[int]]:
    """Hold SIGINT and SIGTERM during the block (module docstring), each where its handler is
    a Python one (one that raises: Ctrl-C's, ``terminate_as_interrupt``'s); yields the list of
    the signal numbers held, filled as they come. The handlers are restored on leaving it;
    nothing held is acted on unless the caller ``deliver``s it."""
    if threading.current_thread() is not threading.main_thread():
        yield []
        return
    held: list[int] = []
    # only a signal that raises (a Python handler: Ctrl-C's, terminate_as_interrupt's) is held;
    # one left to the system (SIGTERM's default: the process ends) keeps its effect
    previous = {s: h for s in _SIGNALS if callable(h := signal.getsignal(s))}

    def hold(signum, frame) -> None:
        if signum in held:  # the second one: act on it now
            _restore(previous)
            signal.raise_signal(signum)
            return
        if signum == signal.SIGTERM:
            _received.append(signum)  # the exit code is SIGTERM's, delivered or only noted
        held.append(signum)

    for s in previous:
        signal.signal(s, hold)
    try:
        yield held
    finally:
        _restore(previous)


def _restore(previous: dict) -> None:
    for s, h in previous.items():
        signal.signal(s, h)


def deliver(held: list[int]) -> None:
    """Act on the first signal ``held_signals`` held, now that its block is over (its own
    handler, restored: Ctrl-C raises KeyboardInterrupt, SIGTERM ``Terminated`` or ends the
    process as without a handler)."""
    if held:
        signal.raise_signal(held[0])
