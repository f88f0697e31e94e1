"""Progress bars on stderr (tqdm): redrawn in place on a terminal, a plain line every few seconds
otherwise (logs, CI, `2> file`), so a long command never runs silent."""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager
from typing import Iterator, TextIO

from tqdm import tqdm

LOG_INTERVAL_S = 5.0  # seconds between lines when stderr is not a terminal


class _Lines:
    """A stream for tqdm that turns each redraw into one line: no carriage returns in a log."""

    def __init__(self, stream: TextIO):
        self.stream = stream

    def write(self, text: str) -> None:
        text = text.replace("\r", "").rstrip()
        if text:
            self.stream.write(text + "\n")

    def flush(self) -> None:
        self.stream.flush()


@contextmanager
def progress(total: float | None, *, desc: str, unit: str, enabled: bool = True, initial: float = 0,
             position: int | None = None, leave: bool = True) -> Iterator[tqdm]:
    """A tqdm bar on stderr, closed on exit. A heartbeat redraws it (every second on a terminal,
    every LOG_INTERVAL_S otherwise) so that elapsed time and ETA move while one long step runs:
    tqdm itself redraws only on updates."""
    stream = sys.stderr
    tty = stream.isatty()
    bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=not enabled, position=position, leave=leave,
               file=stream if tty else _Lines(stream), mininterval=0.2 if tty else LOG_INTERVAL_S,
               dynamic_ncols=tty, ascii=not tty)
    stop = threading.Event()

    def heartbeat() -> None:
        while not stop.wait(1.0 if tty else LOG_INTERVAL_S):
            bar.refresh()

    thread = threading.Thread(target=heartbeat, daemon=True)
    if enabled:
        thread.start()
    try:
        yield bar
    finally:
        stop.set()
        if enabled:
            thread.join()
        bar.close()
