"""``python -m alerts deliver --config gateway.toml``: the documented alias of ``pipesentry alerts deliver``.

The command lives with the other commands (pipesentry/commands/alerts.py), above every
package it uses; this alias runs it as that program (same process id, arguments, signals and
exit code), so the alerts package never imports the layers above it.
"""
from __future__ import annotations

import os
import sys


def main() -> None:
    os.execv(sys.executable, [sys.executable, "-m", "pipesentry", "alerts", *sys.argv[1:]])


if __name__ == "__main__":
    main()
