"""The progress line of `greyfit discover` on stderr: phase, candidate, refits, elapsed time."""
from __future__ import annotations

import time
from typing import TextIO

PHASES = {"base_fit": "fitting the declared model", "screening": "screening the effect library",
          "refit": "refitting with", "done": "done"}
WIDTH = 110   # a terminal line; longer candidates are cut


class DiscoveryProgress:
    """A `solvers.discovery.loop.Progress` callback: one line rewritten in place on a terminal,
    one line per event otherwise (a log file, a CI job)."""

    def __init__(self, stream: TextIO, quiet: bool = False):
        self.stream, self.quiet = stream, quiet
        self.started = time.monotonic()
        self.tty = stream.isatty()
        self.last = 0

    def __call__(self, phase: str, candidate: str, refits: int) -> None:
        if self.quiet:
            return
        what = PHASES.get(phase, phase)
        text = f"greyfit discover [{time.monotonic() - self.started:5.1f} s] {what}"
        if candidate:
            text += f" {candidate}" if phase == "refit" else f" ({candidate})" if phase != "done" else f": {candidate}"
        text += f"  refits used: {refits}"
        if len(text) > WIDTH and self.tty:
            text = text[: WIDTH - 1] + "…"
        if self.tty:
            self.stream.write("\r" + text.ljust(self.last))
            self.last = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self.last and not self.quiet:
            self.stream.write("\n")
            self.stream.flush()
