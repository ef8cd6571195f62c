"""Schema maintenance from the command line: ``python -m db upgrade|current|revision --url URL``.

``upgrade`` migrates to head with the production engine set-up, ``current`` prints the
database's revision, ``revision -m MSG`` autogenerates a new migration from the models.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from alembic import command
from sqlalchemy import create_engine
from sqlalchemy.exc import DBAPIError

from db import migrate
from db.database import open_database
from db.errors import StorageError, translate_db_error
from db.urls import DatabaseUrlError, check_database_url


def main(argv: list[str] | None = None) -> int:
    """Run one action; storage errors become one line on stderr and exit code 2."""
    try:
        return _run(argv)
    except StorageError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except DBAPIError as error:
        typed = translate_db_error(error)
        if typed is None:
            raise
        print(f"error: {typed}", file=sys.stderr)
        return 2


def _run(argv: list[str] | None) -> int:
    parser = argparse.ArgumentParser(prog="python -m db", description=__doc__)
    parser.add_argument("action", choices=["upgrade", "current", "revision"])
    parser.add_argument("--url", required=True, help="database URL, e.g. sqlite:///var/pipesentry.db")
    parser.add_argument("-m", "--message", help="revision message (for 'revision')")
    args = parser.parse_args(argv)
    url = check_database_url(args.url, writable=args.action == "upgrade")  # before anything is opened or created
    if args.action == "upgrade":
        open_database(args.url, upgrade=True).dispose()
        return 0
    if url.get_backend_name() == "sqlite" and not Path(str(url.database)).exists():
        raise DatabaseUrlError(f"no database file at {url.database} (`upgrade` creates it)")
    engine = create_engine(args.url)
    try:
        with engine.connect() as connection:
            if args.action == "current":
                print(migrate.current_revision(connection) or "empty")
                return 0
            if not args.message:
                parser.error("revision needs -m/--message")
            command.revision(migrate.alembic_config(connection), message=args.message, autogenerate=True)
            return 0
    finally:
        engine.dispose()


if __name__ == "__main__":
    raise SystemExit(main())
