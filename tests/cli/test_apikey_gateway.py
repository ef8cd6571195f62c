"""`pipesentry apikey create --role gateway --site S`: a central site's key for one gateway's site."""
from __future__ import annotations

from typer.testing import CliRunner

from db.database import open_database
from pipesentry.commands.apikey import apikey_app


def apikey(*args: str):
    return CliRunner().invoke(apikey_app, list(args))


def test_a_gateway_key_is_made_for_one_site_and_listed_with_it(sqlite_url: str):
    open_database(sqlite_url).dispose()
    created = apikey("create", "--name", "gw-north-1", "--role", "gateway", "--site", "north",
                     "--database-url", sqlite_url)
    assert created.exit_code == 0, created.output
    assert created.stdout.strip().splitlines()[-1].startswith("psk_")
    assert "\tgateway\tnorth\tgw-north-1\t" in apikey("list", "--database-url", sqlite_url).stdout


def test_a_gateway_key_without_a_site_and_a_site_on_another_role_are_refused(sqlite_url: str):
    open_database(sqlite_url).dispose()
    for args in (("--role", "gateway"), ("--role", "viewer", "--site", "north"), ("--role", "gateway", "--site", "no/slash")):
        refused = apikey("create", "--name", "x", *args, "--database-url", sqlite_url)
        assert refused.exit_code != 0 and "--site" in refused.output, refused.output
    assert apikey("list", "--database-url", sqlite_url).stdout.count("\n") == 1  # the header only
