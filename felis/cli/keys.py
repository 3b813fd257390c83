"""`Keyboard`: key presses from the terminal without Enter and without blocking, for ``felis teleop --keyboard``.

On entry the terminal on standard input goes to cbreak mode (no line buffering, no echo; Ctrl-C still sends
SIGINT, so the one shutdown path stays in charge, `felis.shutdown`); ``keys()`` returns what was typed since the
last call, polled with ``select`` at zero timeout. The terminal's settings are restored on every way out: the
``with`` block's end, an exception, a signal (the block unwinds), and once more at interpreter exit in case
the block was never left (``atexit``). Escape sequences of the arrow keys become ``"up"``, ``"down"``,
``"right"``, ``"left"``; a lone Escape is ``"esc"``.
"""

from __future__ import annotations

import atexit
import io
import os
import select
import sys
import termios
import tty

from felis.errors import ParameterError

_ARROWS = {"\x1b[A": "up", "\x1b[B": "down", "\x1b[C": "right", "\x1b[D": "left",
           "\x1bOA": "up", "\x1bOB": "down", "\x1bOC": "right", "\x1bOD": "left"}


def split_keys(text: str) -> list[str]:
    """Typed text → key names (module doc): arrows by name, a lone Escape as ``"esc"``, other characters as they
    are; an unknown escape sequence is dropped whole."""
    out, i = [], 0
    while i < len(text):
        if text[i] == "\x1b":
            seq = text[i:i + 3]
            if seq in _ARROWS:
                out.append(_ARROWS[seq])
                i += 3
                continue
            if i + 1 >= len(text):
                out.append("esc")
                i += 1
                continue
            j = i + 2  # CSI … final byte: skip the whole sequence
            while j < len(text) and not ("@" <= text[j] <= "~"):
                j += 1
            i = j + 1
            continue
        out.append(text[i])
        i += 1
    return out


class Keyboard:
    """The terminal on ``fd`` (default standard input) in cbreak mode while the block runs (module doc)."""

    def __init__(self, fd: int | None = None):
        if fd is None:
            try:
                fd = sys.stdin.fileno()
            except (AttributeError, ValueError, io.UnsupportedOperation):  # closed, or replaced by a non-file
                fd = -1
        self.fd = fd
        if fd < 0 or not os.isatty(fd):
            raise ParameterError("--keyboard reads keys from a terminal: run it in one (standard input is not a "
                                 "terminal)")
        self._saved: list | None = None

    def __enter__(self) -> Keyboard:
        self._saved = termios.tcgetattr(self.fd)
        atexit.register(self.restore)
        tty.setcbreak(self.fd, termios.TCSANOW)
        return self

    def keys(self) -> list[str]:
        """Keys typed since the last call (never blocks)."""
        chunks = []
        while select.select([self.fd], [], [], 0)[0]:
            data = os.read(self.fd, 256)
            if not data:
                break
            chunks.append(data)
        return split_keys(b"".join(chunks).decode("utf-8", errors="ignore")) if chunks else []

    def restore(self) -> None:
        """The terminal's settings as they were (idempotent)."""
        saved, self._saved = self._saved, None
        if saved is not None:
            try:
                termios.tcsetattr(self.fd, termios.TCSADRAIN, saved)
            except termios.error:  # the terminal is gone (SIGHUP): nothing to restore
                pass
            atexit.unregister(self.restore)

    def __exit__(self, *exc) -> None:
        self.restore()
