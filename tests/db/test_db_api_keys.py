"""Specification of API keys: the token is shown once, only its hash is kept, revocation works."""
from __future__ import annotations

from sqlalchemy import select, text

from db.api_keys import authenticate_api_key, create_api_key, list_api_keys, revoke_api_key
from db.models import ApiKeyRow, Role


def test_a_created_key_authenticates_and_only_its_hash_is_stored(any_db):
    with any_db.write() as session:
        row, token = create_api_key(session, name="scada", role=Role.OPERATOR)
        key_id = row.id
    with any_db.session() as session:
        found = authenticate_api_key(session, token)
        assert (found.id, found.role, found.name) == (key_id, Role.OPERATOR, "scada")
        assert token.startswith(found.key_prefix) and len(found.key_prefix) < len(token) // 3
        stored_text = " ".join(str(v) for v in session.execute(text("SELECT * FROM api_keys")).one())
        assert token not in stored_text


def test_wrong_or_revoked_tokens_do_not_authenticate(any_db):
    with any_db.write() as session:
        row, token = create_api_key(session, name="old", role=Role.ADMIN)
        key_id = row.id
    with any_db.session() as session:
        assert authenticate_api_key(session, token + "x") is None
    with any_db.write() as session:
        revoked = revoke_api_key(session, key_id)
        first_revocation = revoked.revoked_at
        assert revoke_api_key(session, key_id).revoked_at == first_revocation  # idempotent
    with any_db.session() as session:
        assert authenticate_api_key(session, token) is None
        assert [k.id for k in list_api_keys(session)] == [key_id]  # kept for the audit trail


def test_every_key_gets_a_distinct_token(any_db):
    with any_db.write() as session:
        tokens = {create_api_key(session, name=f"k{i}", role=Role.VIEWER)[1] for i in range(5)}
        assert len(tokens) == 5
        assert len(session.scalars(select(ApiKeyRow.key_hash)).all()) == 5
