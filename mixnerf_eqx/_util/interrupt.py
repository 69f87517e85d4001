"""Ctrl-C at safe points only.

A `KeyboardInterrupt` raised by Python's default handler can land anywhere: between a step's
update and the line that keeps its result, inside JAX's dispatch, or while XLA still runs a
computation that a dying interpreter then tears down (which can crash the process). Inside
`deferred_interrupts()`, Ctrl-C only records the request; long loops call
`raise_if_interrupted()` at points where stopping is safe (between training steps, between
chunks of rays), and the `KeyboardInterrupt` is raised there. A second Ctrl-C while the first
waits for such a point is raised at once, for a user who does not want to wait.

Outside these blocks Python's own handler raises the `KeyboardInterrupt`. Where that lands in
code whose exceptions Python cannot pass on (a garbage-collection callback such as JAX's, a
`__del__`), Python prints "Exception ignored in ..." and drops it, and the program runs on as if
Ctrl-C had not been pressed. `redeliver_dropped_interrupts()`, which the commands and `fit` call
as they start (importing the package does not), hands such an interrupt to the main thread
again, where it is raised (or recorded, inside `deferred_interrupts()`) as soon as Python can.
"""

import _thread
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

_requested = False
_active = 0


def _handler(signum, frame) -> None:
    global _requested
    if _requested:
        raise KeyboardInterrupt
    _requested = True


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Within this block, Ctrl-C is raised by `raise_if_interrupted()` only.

    Outside the main thread (where signals cannot be handled) it changes nothing. Blocks nest.
    """
    global _requested, _active
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if _active == 0:
        _requested = False
        signal.signal(signal.SIGINT, _handler)
    _active += 1
    try:
        yield
    finally:
        _active -= 1
        if _active == 0:
            signal.signal(signal.SIGINT, previous)
            pending, _requested = _requested, False
            if pending:
                # A request that arrived after the last safe point is not lost.
                raise KeyboardInterrupt


def raise_if_interrupted() -> None:
    """Raises `KeyboardInterrupt` here if Ctrl-C was pressed since the block began."""
    global _requested
    if _requested:
        _requested = False
        raise KeyboardInterrupt


_redelivering = False


def _interrupt_main_soon() -> None:
    time.sleep(0.05)
    _thread.interrupt_main()


def redeliver_dropped_interrupts() -> None:
    """Makes a `KeyboardInterrupt` that Python would drop as unraisable interrupt the main thread
    again (see the module's docstring); other unraisable exceptions go to the hook that was there."""
    global _redelivering
    if _redelivering:
        return
    previous = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        # Where it cannot be handed back (Python shutting down, or SIGINT not handled by a
        # Python handler, so that `interrupt_main` would do nothing), Python reports it as before.
        handled = callable(signal.getsignal(signal.SIGINT)) and not sys.is_finalizing()
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and handled:
            # As if Ctrl-C were pressed again once this hook has returned: the main thread would
            # handle an interrupt made here inside the hook, where Python drops it once more.
            threading.Thread(target=_interrupt_main_soon, daemon=True).start()
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    _redelivering = True


STOPPED_WHILE_LOADING = "stopped while loading; nothing was done"
