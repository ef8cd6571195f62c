"""The API on a database file it must not use: /readyz is 503 with the reason, every route a 503
problem (never a 500), the file untouched; damage found while serving turns /readyz 503 too."""
from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from service.settings import ApiSettings
from tests.support.api_fixtures import ApiServer, assert_problem
from tests.support.bad_databases import BAD_FILES, corrupt_pages, good_database

REASONS = {
    "garbage": "database_damaged",
    "truncated": "database_damaged",
    "other-format": "database_damaged",
    "foreign-sqlite": "foreign_database",
    "corrupt-pages": "database_damaged",
}


@pytest.mark.parametrize("kind", sorted(BAD_FILES))
def test_a_bad_file_is_not_ready_with_its_reason_and_no_route_answers_500(kind: str, tmp_path: Path):
    path = tmp_path / "api.db"
    BAD_FILES[kind](path)
    before = path.read_bytes()
    with ApiServer(ApiSettings(database_url=f"sqlite:///{path}")) as server:
        assert httpx.get(f"{server.base_url}/healthz").status_code == 200
        body = assert_problem(httpx.get(f"{server.base_url}/readyz"), 503, REASONS[kind].replace("_", "-"))
        assert body["reason"] == REASONS[kind]
        assert str(path) not in body["detail"]
        for route in ("/api/v1/nodes", "/api/v1/detections", "/metrics"):
            response = httpx.get(f"{server.base_url}{route}", headers={"Authorization": "Bearer psk_x"})
            assert response.status_code == 503, (route, response.text)
    assert path.read_bytes() == before


def test_damage_found_by_the_scheduled_check_makes_readyz_503(tmp_path: Path):
    path = good_database(tmp_path / "api.db")
    settings = ApiSettings(database_url=f"sqlite:///{path}", integrity_check_every_s=0.001)
    with ApiServer(settings) as server:
        assert httpx.get(f"{server.base_url}/readyz").status_code == 200
        corrupt_pages(path)
        for _ in range(50):  # each probe starts a quick_check in the background when the last one is due
            response = httpx.get(f"{server.base_url}/readyz")
            if response.status_code == 503:
                break
        body = assert_problem(response, 503, "database-damaged")
        assert body["reason"] == "database_damaged"
