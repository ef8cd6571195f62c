"""A size-limited file system the test makes and removes: a tmpfs mount of a few MiB (needs root).

Without the permission to mount, a test skips with the reason, except with CI=true, where it fails.
"""
from __future__ import annotations

import errno
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

MIB = 1024 * 1024


def free_bytes(path: Path) -> int:
    stats = os.statvfs(path)
    return stats.f_bavail * stats.f_frsize


@contextmanager
def small_filesystem(where: Path, size_mib: int) -> Iterator[Path]:
    """``where`` (created) with a tmpfs of ``size_mib`` MiB mounted on it, unmounted at the end."""
    where.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mib}m,mode=0755", "tmpfs", str(where)],
                          capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        reason = f"cannot mount a tmpfs (root needed): {done.stderr.strip()}"
        if os.environ.get("CI") == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=30, check=False)


def fill(directory: Path, leave_bytes: int, name: str = "filler") -> Path:
    """A file that takes all free space of ``directory``'s file system but ``leave_bytes``.

    A process writing to the same file system meanwhile (the gateway under test) may take the
    last bytes first: the file system is then full before the filler is, which is what was wanted
    (unbuffered, so that it shows at a write, not at close)."""
    path = directory / name
    size = max(0, free_bytes(directory) - leave_bytes)
    with path.open("wb", buffering=0) as file:
        chunk = b"\0" * MIB
        while size > 0:
            try:
                written = file.write(chunk[: min(size, MIB)])
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                break
            if not written:  # nothing more goes in: as full as it gets
                break
            size -= written
    return path


def shrink(path: Path, by_bytes: int) -> None:
    """Free ``by_bytes`` of the filler (the operator deleting old logs)."""
    os.truncate(path, max(0, path.stat().st_size - by_bytes))
