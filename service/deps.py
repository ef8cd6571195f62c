"""Injected dependencies of the routes: the database, sessions, and the caller's API key and role."""
from __future__ import annotations

import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.concurrency import run_in_threadpool
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from db.api_keys import authenticate_api_key, hash_token
from db.database import Database
from db.models import Role
from service.database import DatabaseGate
from service.problems import FORBIDDEN, UNAUTHORIZED, ApiProblem
from service.settings import ApiSettings

ROLE_RANK = {Role.GATEWAY: -1, Role.VIEWER: 0, Role.OPERATOR: 1, Role.ADMIN: 2}  # a gateway key reads nothing
MAX_TOKEN_CHARS = 256  # our tokens are ~47 characters; anything far longer is not one

bearer_scheme = HTTPBearer(auto_error=False, description="`Authorization: Bearer <key>`")
header_scheme = APIKeyHeader(name="X-API-Key", auto_error=False, description="`X-API-Key: <key>`")


@dataclass(frozen=True)
class Caller:
    """Who is making the request: the API key's id, name (recorded as 'who') and role."""

    key_id: int
    name: str
    role: Role
    site: str | None = None  # a gateway key's site

    def allows(self, needed: Role) -> bool:
        return ROLE_RANK[self.role] >= ROLE_RANK[needed]


def get_settings(request: Request) -> ApiSettings:
    return request.app.state.settings


async def get_database(request: Request) -> Database:
    gate: DatabaseGate = request.app.state.database
    opened = gate.opened()
    return opened if opened is not None else await run_in_threadpool(gate.get)


DatabaseDep = Annotated[Database, Depends(get_database)]


# Routes open their session inside their own worker thread (``with database.session()``)
# instead of through a yield-dependency: a dependency's session would hold a pooled
# connection across thread hops, and under load the threads waiting for a connection can
# starve the ones holding one (a deadlock until the pool times out).
#
# The dependencies below are ``async def`` and never block: FastAPI runs a plain ``def``
# dependency in the thread pool, and on a loaded 2-core edge computer every such hop is a
# wait for the scheduler. Only what does I/O (the first open, a key not in the cache) goes
# to a worker thread; a request then costs one hop, its route's.


async def presented_token(
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)],
    header_key: Annotated[str | None, Security(header_scheme)],
) -> str:
    token = bearer.credentials if bearer is not None else header_key
    if not token:
        raise ApiProblem(UNAUTHORIZED, "send an API key as 'Authorization: Bearer <key>' or 'X-API-Key: <key>'",
                         headers={"WWW-Authenticate": "Bearer"})
    return token


class VerifiedKeys:
    """Keys verified in the last ``ttl_s`` seconds, by token hash: most requests skip the key lookup.

    A key revoked elsewhere (the CLI, another API process) stops working within ``ttl_s``; a key
    revoked through this process stops at once (``forget``). Bounded: at most ``max_entries``.
    """

    def __init__(self, ttl_s: float, max_entries: int = 1024, clock: Callable[[], float] = time.monotonic) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: dict[str, tuple[float, Caller]] = {}

    def get(self, token_hash: str) -> Caller | None:
        with self._lock:
            entry = self._entries.get(token_hash)
            if entry is None or self._clock() - entry[0] > self.ttl_s:
                self._entries.pop(token_hash, None)
                return None
            return entry[1]

    def put(self, token_hash: str, caller: Caller) -> None:
        with self._lock:
            if len(self._entries) >= self.max_entries:
                self._entries.clear()
            self._entries[token_hash] = (self._clock(), caller)

    def forget(self, key_id: int) -> None:
        with self._lock:
            for token_hash in [h for h, (_, c) in self._entries.items() if c.key_id == key_id]:
                del self._entries[token_hash]


async def verified_keys(request: Request) -> VerifiedKeys:
    return request.app.state.verified_keys


def _look_up_key(database: Database, token: str) -> Caller | None:
    with database.session() as session:
        row = authenticate_api_key(session, token)
        return None if row is None else Caller(key_id=row.id, name=row.name, role=row.role, site=row.site)


async def current_caller(
    token: Annotated[str, Depends(presented_token)],
    database: DatabaseDep,
    cache: Annotated[VerifiedKeys, Depends(verified_keys)],
) -> Caller:
    caller = None
    if len(token) <= MAX_TOKEN_CHARS:
        token_hash = hash_token(token)
        caller = cache.get(token_hash)
        if caller is None:
            caller = await run_in_threadpool(_look_up_key, database, token)
            if caller is not None:
                cache.put(token_hash, caller)
    if caller is None:
        raise ApiProblem(UNAUTHORIZED, "unknown or revoked API key", headers={"WWW-Authenticate": "Bearer"})
    return caller


def require(role: Role) -> Callable[[Caller], Awaitable[Caller]]:
    """A dependency that admits callers whose role is at least ``role``."""

    async def check(caller: Annotated[Caller, Depends(current_caller)]) -> Caller:
        if not caller.allows(role):
            raise ApiProblem(FORBIDDEN, f"needs the {role.value} role; this key is {caller.role.value}")
        return caller

    check.__name__ = f"require_{role.value}"
    return check


async def require_gateway(caller: Annotated[Caller, Depends(current_caller)]) -> Caller:
    """Only a gateway key (scoped to its site) may ingest."""
    if caller.role is not Role.GATEWAY:
        raise ApiProblem(FORBIDDEN, f"needs a gateway key; this key is {caller.role.value}")
    return caller


require_viewer = require(Role.VIEWER)
require_operator = require(Role.OPERATOR)
require_admin = require(Role.ADMIN)
Viewer = Annotated[Caller, Depends(require_viewer)]
Operator = Annotated[Caller, Depends(require_operator)]
Admin = Annotated[Caller, Depends(require_admin)]
GatewayCaller = Annotated[Caller, Depends(require_gateway)]
