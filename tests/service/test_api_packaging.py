"""What can be checked of the container without a Docker engine: the Dockerfile parses and says
what we mean, and the wheel built from exactly what it copies runs the entry points it names."""
from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(240)]  # runs the system's real processes

REPO = Path(__file__).resolve().parents[2]
DOCKERFILE = REPO / "docker" / "Dockerfile"
INSTRUCTIONS = {
    "FROM", "RUN", "CMD", "LABEL", "EXPOSE", "ENV", "ADD", "COPY", "ENTRYPOINT", "VOLUME", "USER", "WORKDIR",
    "ARG", "ONBUILD", "STOPSIGNAL", "HEALTHCHECK", "SHELL",
}
EXEC_FORM = {"CMD", "ENTRYPOINT", "SHELL", "VOLUME"}


def parse_dockerfile(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) per instruction: comments dropped, backslash continuations joined."""
    instructions: list[tuple[str, str]] = []
    pending = ""
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if pending and line.startswith("#"):
            continue  # a comment inside a continued instruction is dropped, as Docker does
        pending += (" " if pending else "") + line
        if pending.endswith("\\"):
            pending = pending[:-1].rstrip()
            continue
        keyword, _, arguments = pending.partition(" ")
        if keyword.upper() not in INSTRUCTIONS:
            raise ValueError(f"line {number}: unknown instruction {keyword!r}")
        instructions.append((keyword.upper(), arguments.strip()))
        pending = ""
    if pending:
        raise ValueError("the file ends inside a continued instruction")
    return instructions


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


@pytest.fixture(scope="module")
def installed_wheel(dockerfile, tmp_path_factory) -> Path:
    """The wheel built from the Dockerfile's build context, installed into a fresh venv.

    The venv sees the project venv's site-packages for the dependencies (no download) but
    not the editable checkout: the code it runs is the wheel's.
    """
    root = tmp_path_factory.mktemp("wheel")
    context = root / "context"
    context.mkdir()
    for keyword, arguments in dockerfile:
        if keyword == "COPY" and not arguments.startswith("--from"):
            *sources, _ = shlex.split(arguments)
            for source in sources:
                src = REPO / source
                if src.is_dir():
                    shutil.copytree(src, context / source, ignore=shutil.ignore_patterns("__pycache__"))
                else:
                    shutil.copy2(src, context / source)
    pip = [sys.executable, "-m", "pip"]
    run = dict(capture_output=True, text=True, timeout=180, cwd=root)
    built = subprocess.run([*pip, "wheel", "--no-deps", "--wheel-dir", str(root / "dist"), "./context"], **run)
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=60)
    site = Path(subprocess.run([str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True, timeout=30).stdout.strip())
    (site / "project_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    wheel = next((root / "dist").glob("pipesentry-*.whl"))
    installed = subprocess.run([*pip, "--python", str(venv / "bin" / "python"), "install", "--no-deps", "--no-index",
                                str(wheel)], **run)
    assert installed.returncode == 0, installed.stdout[-2000:] + installed.stderr[-2000:]
    return venv


def run_in(venv: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(venv / "bin" / args[0]), *args[1:]], capture_output=True, text=True, timeout=60,
                          cwd=venv.parent, env=env)


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
