"""A serial port nobody answers on: a real pseudo-terminal whose other end reads and discards what
the gateway sends (so its writes never fill the pty's buffer) and never writes a byte back."""
from __future__ import annotations

import os
import select
import threading
from pathlib import Path


class SilentPty:
    """``link`` points at the pty's slave while the port is open; ``close()`` ends it (the gateway's
    open port then fails as an unplugged adapter does) and removes the link."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self._master, slave = os.openpty()
        self.slave_path = os.ttyname(slave)
        os.close(slave)  # the gateway opens it by its path
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(self.slave_path)
        self.discarded = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, name="silent-pty", daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while not self._stop.is_set():  # bounded by close(), which sets the event
            readable, _, _ = select.select([self._master], [], [], 0.1)
            if not readable:
                continue
            try:
                self.discarded += len(os.read(self._master, 4096))
            except OSError:  # no slave open at the moment (EIO): wait for the next opening
                self._stop.wait(0.05)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(5)
        os.close(self._master)
        self.link.unlink(missing_ok=True)

    def __enter__(self) -> SilentPty:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
