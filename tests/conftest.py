"""Fixtures shared by every test package (tests/support/); helpers are imported from there.

Markers (pyproject.toml): ``e2e`` runs real processes of the system (mock nodes, the gateway, the
API server, the installed commands); ``postgres`` needs the server on 127.0.0.1:5432; ``browser``
needs headless Chromium. ``make test-fast`` runs everything else.
"""
import pytest

pytest_plugins = [
    "tests.support.db_fixtures",
    "tests.support.alerts_fixtures",
    "tests.support.api_fixtures",
    "tests.support.mqtt_broker",
    "tests.support.browser_fixtures",
    "tests.support.wheel_fixtures",
    "tests.support.chaos_summary",
]

# Fixtures that start the whole system (mock nodes, a gateway and an API server): a test using one is e2e.
SYSTEM_FIXTURES = frozenset({"api", "fleet_db_path", "installed_wheel"})


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if SYSTEM_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.e2e)
