"""How the command line reports a user's bad input: one line on stderr, exit code 2."""
from __future__ import annotations

from typing import NoReturn

import typer

EXIT_BAD_INPUT = 2


def fail(message: str) -> NoReturn:
    """Never a traceback for bad input: print ``error: message`` and exit 2."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)
