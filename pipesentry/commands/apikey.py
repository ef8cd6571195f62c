"""`pipesentry apikey create|list|revoke`: manage API keys in the database (tokens stored hashed)."""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Annotated

import typer

from pipesentry.errors import fail

if TYPE_CHECKING:  # imported lazily at run time: the CLI's --help stays fast
    from db.database import Database

apikey_app = typer.Typer(help="Create, list and revoke API keys of the operator API.", no_args_is_help=True,
                         add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)

DatabaseUrl = Annotated[
    str | None,
    typer.Option("--database-url", help="database URL (env PIPESENTRY_API_DATABASE_URL; default sqlite:///pipesentry.db)"),
]


@contextmanager
def _database(url: str | None) -> Iterator[Database]:
    from db.errors import StorageError
    from db.urls import DatabaseUrlError, check_database_url
    from service.database import DatabaseGate
    from service.settings import ApiSettings

    url = url or os.environ.get("PIPESENTRY_API_DATABASE_URL") or ApiSettings.model_fields["database_url"].default
    try:
        check_database_url(url)
    except DatabaseUrlError as exc:
        fail(f"--database-url: {exc}")
    try:
        database = DatabaseGate(url, busy_timeout_ms=ApiSettings.model_fields["busy_timeout_ms"].default).get()
    except (StorageError, ValueError) as exc:
        fail(f"{url}: {exc}")
    try:
        yield database
    except StorageError as exc:
        fail(str(exc))
    finally:
        database.dispose()


@apikey_app.command("create")
def create(
    name: Annotated[str, typer.Option(help="who or what uses the key (recorded with baseline changes etc.)")],
    role: Annotated[str, typer.Option(help="viewer | operator | admin | gateway (a gateway reporting to this central site)")] = "viewer",
    site: Annotated[str | None, typer.Option(help="a gateway key's site: the only one it may write for (needed with --role gateway)")] = None,
    database_url: DatabaseUrl = None,
) -> None:
    """Create a key and print it once (only its hash is stored)."""
    import re

    from db.api_keys import create_api_key
    from db.models import Role

    try:
        parsed = Role(role)
    except ValueError:
        fail(f"--role must be one of {', '.join(r.value for r in Role)}, got {role!r}")
    if not name.strip() or len(name) > 128:
        fail("--name must be 1..128 characters")
    if (parsed is Role.GATEWAY) != (site is not None):
        fail("--site is needed with --role gateway, and only with it")
    if site is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", site):
        fail(f"--site must be 1..64 letters, digits, '.', '_' or '-', starting with a letter or digit; got {site!r}")
    with _database(database_url) as database:
        with database.write() as session:
            row, token = create_api_key(session, name=name, role=parsed, site=site)
            key_id = row.id
    scope = f", site {site}" if site else ""
    typer.echo(f"created key {key_id} ({name}, {parsed.value}{scope}); it is shown only now:", err=True)
    typer.echo(token)


@apikey_app.command("list")
def list_keys(database_url: DatabaseUrl = None) -> None:
    """List keys: id, prefix, role, name, created, revoked."""
    from db.api_keys import list_api_keys

    with _database(database_url) as database:
        with database.session() as session:
            rows = [(k.id, k.key_prefix, k.role.value, k.site, k.name, k.created_at, k.revoked_at)
                    for k in list_api_keys(session)]
    typer.echo("id\tprefix\trole\tsite\tname\tcreated_at\trevoked_at")
    for key_id, prefix, role, site, name, created, revoked in rows:
        typer.echo(f"{key_id}\t{prefix}\t{role}\t{site or '-'}\t{name}\t{created.isoformat()}\t"
                   f"{revoked.isoformat() if revoked else '-'}")


@apikey_app.command("revoke")
def revoke(
    key_id: Annotated[int, typer.Argument(help="the key's id (see `list`)")],
    database_url: DatabaseUrl = None,
) -> None:
    """Revoke a key at once (idempotent; the record stays for the audit trail)."""
    from db.api_keys import revoke_api_key
    from db.errors import NotFound

    with _database(database_url) as database:
        try:
            with database.write() as session:
                row = revoke_api_key(session, key_id)
                revoked_at = row.revoked_at
        except NotFound as exc:
            fail(str(exc))
    typer.echo(f"key {key_id} revoked at {revoked_at.isoformat() if revoked_at else '?'}")
