"""API keys: a random token is shown once; only its SHA-256 and a display prefix are stored."""
from __future__ import annotations

import hashlib
import secrets
from collections.abc import Sequence
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import NotFound
from db.models import ApiKeyRow, Role

TOKEN_PREFIX = "psk_"
TOKEN_BYTES = 32  # 256 bits of entropy: a plain (unsalted) hash cannot be brute-forced
DISPLAY_PREFIX_CHARS = 12


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def create_api_key(
    session: Session, *, name: str, role: Role, site: str | None = None, now: datetime | None = None
) -> tuple[ApiKeyRow, str]:
    """Store a new key and return it with the token (which is not stored anywhere).

    A ``gateway`` key needs the ``site`` it may write for; no other role has one.
    """
    if (role is Role.GATEWAY) != (site is not None):
        raise ValueError("a gateway key needs its site, and only a gateway key has one")
    token = TOKEN_PREFIX + secrets.token_urlsafe(TOKEN_BYTES)
    row = ApiKeyRow(
        name=name,
        role=role,
        key_hash=hash_token(token),
        key_prefix=token[:DISPLAY_PREFIX_CHARS],
        created_at=now or utc_now(),
        revoked_at=None,
        site=site,
    )
    session.add(row)
    session.flush()
    return row, token


def authenticate_api_key(session: Session, token: str) -> ApiKeyRow | None:
    """The unrevoked key matching ``token``, or None."""
    return session.scalars(
        select(ApiKeyRow).where(ApiKeyRow.key_hash == hash_token(token), ApiKeyRow.revoked_at.is_(None))
    ).first()


def revoke_api_key(session: Session, key_id: int, *, now: datetime | None = None) -> ApiKeyRow:
    """Revoke a key (idempotent; the row stays for the audit trail)."""
    row = session.get(ApiKeyRow, key_id)
    if row is None:
        raise NotFound(f"no API key {key_id}")
    if row.revoked_at is None:
        row.revoked_at = now or utc_now()
        session.flush()
    return row


def list_api_keys(session: Session) -> Sequence[ApiKeyRow]:
    return session.scalars(select(ApiKeyRow).order_by(ApiKeyRow.id)).all()
