"""``python -m fullwave generate --out DIR`` (see fullwave/cli.py)."""
import sys

from fullwave.cli import main

sys.exit(main())
