"""API keys over HTTP (admin): list, create (the token is shown once), revoke."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, status

from db.api_keys import create_api_key, list_api_keys, revoke_api_key
from db.models import Role
from service import schemas
from service.deps import Admin, DatabaseDep, VerifiedKeys, require_admin, verified_keys
from service.problems import problem_responses
from service.routes.parameters import MAX_ID

router = APIRouter(prefix="/keys", tags=["keys"], dependencies=[Depends(require_admin)],
                   responses=problem_responses(401, 403, 503))

KeyId = Annotated[int, Path(ge=1, le=MAX_ID)]


@router.get("")
def list_keys(database: DatabaseDep) -> list[schemas.ApiKey]:
    with database.session() as session:
        return [schemas.ApiKey.model_validate(k) for k in list_api_keys(session)]


@router.post("", status_code=status.HTTP_201_CREATED, responses=problem_responses(413))
def create_key(body: schemas.AnyKeyCreate, _: Admin, database: DatabaseDep) -> schemas.ApiKeyCreated:
    site = body.site if isinstance(body, schemas.GatewayKeyCreate) else None
    with database.write() as session:
        row, token = create_api_key(session, name=body.name, role=Role(body.role), site=site)
        return schemas.ApiKeyCreated(**schemas.ApiKey.model_validate(row).model_dump(), token=token)


@router.delete("/{key_id}", responses=problem_responses(404), summary="Revoke a key (idempotent; kept for audit)")
def revoke_key(
    key_id: KeyId, _: Admin, database: DatabaseDep, cache: Annotated[VerifiedKeys, Depends(verified_keys)]
) -> schemas.ApiKey:
    with database.write() as session:
        revoked = schemas.ApiKey.model_validate(revoke_api_key(session, key_id))
    cache.forget(key_id)  # effective at once in this process
    return revoked
