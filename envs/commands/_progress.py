"""Progress of long jobs on stderr: a tqdm bar on a terminal, plain lines otherwise."""

from __future__ import annotations

import sys
from typing import TextIO


class QuantityProgress:
    """Progress over a quantity (flight seconds, episodes, steps): a tqdm bar on a
    terminal; off a terminal a plain line each ``every`` units (no carriage returns)."""

    def __init__(self, desc: str, total: float, unit: str, *, enabled: bool = True,
                 every: float | None = None, stream: TextIO | None = None) -> None:
        self.desc, self.total, self.unit = desc, float(total), unit
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.every = every if every is not None else max(self.total / 10.0, 1e-9)
        self.value = 0.0
        self._next_line = self.every
        self.bar = None
        if enabled and self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, desc=desc, unit=unit, file=self.stream,
                            bar_format="{desc}: {n:.0f}/{total:.0f} " + unit
                            + " [{elapsed}<{remaining}]{postfix}")

    def update(self, value: float, note: str = "") -> None:
        """Set the progress to ``value`` (absolute)."""
        value = min(float(value), self.total)
        if self.bar is not None:
            self.bar.update(value - self.value)
            if note:
                self.bar.set_postfix_str(note, refresh=False)
        elif self.enabled and value >= self._next_line:
            extra = f" {note}" if note else ""
            print(f"{self.desc}: {value:.0f}/{self.total:.0f} {self.unit}{extra}",
                  file=self.stream, flush=True)
            while self._next_line <= value:
                self._next_line += self.every
        self.value = value

    def close(self, note: str = "done", *, line: bool = True) -> None:
        """End the progress with ``note``; off a terminal as a line of its own unless
        ``line`` is False (a failure the caller states in its one line)."""
        if self.bar is not None:
            self.bar.set_postfix_str(note)
            self.bar.close()
        elif self.enabled and line:
            print(f"{self.desc}: {note}", file=self.stream, flush=True)
