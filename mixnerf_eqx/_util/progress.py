"""Progress that suits where the output goes.

On a terminal: a tqdm bar updated in place. Elsewhere (CI, a cluster job, a redirect to a
file) carriage-return updates turn into a wall of repeated lines, so progress is one plain
line every `interval` seconds instead. Messages (`write`) are printed either way.
"""

import sys
import time
from typing import Any

from tqdm.auto import tqdm


class Progress:
    """Progress of `total` units of work, from `initial`.

    **Arguments:**

    - `total`, `initial`: the units of work, and how many are done already.
    - `unit`: what a unit is called (`"step"`, `"view"`).
    - `enabled`: `False` shows no progress (messages still appear).
    - `interval`: seconds between plain lines when the output is not a terminal.
    """

    def __init__(
        self, total: int, *, initial: int = 0, unit: str, enabled: bool = True, interval: float = 10.0
    ):
        self.total, self.unit, self.interval = total, unit, interval
        self.done = initial
        stream = sys.stderr
        self.terminal = enabled and hasattr(stream, "isatty") and stream.isatty()
        self.plain = enabled and not self.terminal
        self.bar = tqdm(
            total=total, initial=initial, unit=unit, dynamic_ncols=True, disable=not self.terminal
        )
        self.last_line = time.monotonic()

    def update(self, done: int, **postfix: Any) -> None:
        """`done` units are finished; `postfix` values are shown next to the count."""
        if self.terminal:
            self.bar.set_postfix(**postfix, refresh=False)
            self.bar.update(done - self.bar.n)
        self.done = done
        now = time.monotonic()
        if self.plain and (now - self.last_line >= self.interval or done >= self.total):
            shown = " ".join(f"{key} {value}" for key, value in postfix.items())
            print(f"{self.unit} {done}/{self.total} {shown}".rstrip(), file=sys.stderr, flush=True)
            self.last_line = now

    def write(self, message: str) -> None:
        """Prints a message without breaking the bar."""
        if self.terminal:
            self.bar.write(message)
        else:
            print(message, flush=True)

    def close(self) -> None:
        self.bar.close()
