"""What can be checked of the container without a Docker engine: the Dockerfile parses and says
what we mean, and the wheel built from exactly what it copies runs the entry points it names."""
from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from tests.support.wheel_fixtures import DOCKERFILE, REPO, parse_dockerfile, run_in

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(240)]  # runs the system's real processes
EXEC_FORM = {"CMD", "ENTRYPOINT", "SHELL", "VOLUME"}


def exec_form(arguments: str) -> list[str]:
    value = json.loads(arguments)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), arguments
    return value


def final_stage(instructions: list[tuple[str, str]]) -> list[tuple[str, str]]:
    last_from = max(i for i, (keyword, _) in enumerate(instructions) if keyword == "FROM")
    return instructions[last_from:]


@pytest.fixture(scope="module")
def dockerfile() -> list[tuple[str, str]]:
    return parse_dockerfile(DOCKERFILE.read_text())


def test_dockerfile_parses_and_exec_forms_are_json_arrays(dockerfile):
    assert dockerfile[0][0] == "FROM"
    for keyword, arguments in dockerfile:
        if keyword in EXEC_FORM or (keyword == "HEALTHCHECK" and "CMD [" in arguments):
            exec_form(arguments.split("CMD", 1)[1].strip() if keyword == "HEALTHCHECK" else arguments)


def test_image_runs_pipesentry_as_an_unprivileged_user_with_the_api_by_default(dockerfile):
    stage = final_stage(dockerfile)
    keywords = [k for k, _ in stage]
    user = [a for k, a in stage if k == "USER"]
    assert user and user[-1].split(":")[0] not in ("root", "0")
    assert keywords.index("USER") < keywords.index("ENTRYPOINT")
    assert exec_form(dict(stage)["ENTRYPOINT"]) == ["pipesentry"]
    assert exec_form(dict(stage)["CMD"]) == ["api"]
    assert "8000" in dict(stage)["EXPOSE"].split()


def test_healthcheck_probes_healthz(dockerfile):
    healthcheck = dict(final_stage(dockerfile))["HEALTHCHECK"]
    options, _, command = healthcheck.partition("CMD")
    assert "--interval=" in options and "--timeout=" in options
    probe = exec_form(command.strip())
    assert probe[0] == "python" and "/healthz" in probe[-1]
    compile(probe[-1], "<healthcheck>", "exec")


def test_every_package_the_wheel_ships_is_copied_into_the_build(dockerfile):
    copied = {shlex.split(a)[0].rstrip("/") for k, a in dockerfile if k == "COPY" and not a.startswith("--from")}
    for source in copied:
        assert (REPO / source).exists(), f"COPY {source}: not in the repository"
    import tomllib

    includes = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = {pattern.rstrip("*") for pattern in includes}
    assert packages <= copied, f"not copied: {packages - copied}"


def test_installed_wheel_holds_the_service_code_dashboard_and_migrations(installed_wheel):
    probe = ("import service, service.app, db.migrate, pathlib; "
             "print(service.__file__); "
             "print((pathlib.Path(service.__file__).parent / 'static' / 'index.html').exists()); "
             "print(db.migrate.head_revision())")
    result = run_in(installed_wheel, "python", "-c", probe)
    assert result.returncode == 0, result.stderr[-2000:]
    location, has_page, head = result.stdout.split()
    assert Path(location).is_relative_to(installed_wheel), location
    assert has_page == "True" and head


def test_installed_api_command_shows_its_help(installed_wheel):
    result = run_in(installed_wheel, "python", "-c",
                    "import typer; from pipesentry.commands.api import api; typer.run(api)", "--help")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--database-url" in result.stdout and "--port" in result.stdout


def test_installed_entry_points_named_by_the_image_run(installed_wheel):
    gateway = run_in(installed_wheel, "pipesentry", "gateway", "--help")
    assert gateway.returncode == 0, gateway.stderr[-2000:]
    api = run_in(installed_wheel, "pipesentry", "api", "--help")
    assert api.returncode == 0, api.stderr[-2000:]
    assert "--database-url" in api.stdout
    apikey = run_in(installed_wheel, "pipesentry", "apikey", "--help")
    assert apikey.returncode == 0 and "create" in apikey.stdout
