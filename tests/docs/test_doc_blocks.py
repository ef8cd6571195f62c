"""Every fenced block in README.md, docs/*.md and docker/README.md is checked, so no example can rot.

The rule, on purpose hard to dodge:

* every block is tagged, and the tag is one this module checks: ``toml``, ``yaml``, ``json``,
  ``python``, ``sh`` or ``text``. An untagged block, or any other tag, fails.
* ``toml``: parses, and is a gateway config or a mock-node scenario, completed the documented way:
  a fragment goes into the one-node example (``examples/gateway-one-node.toml``) or the paper's
  notch scenario (``examples/scenarios/paper_notch.toml``): its tables merge into the example's,
  a ``[nodes.x]`` table into the example's node, a ``[[nodes]]`` list replaces the example's
  nodes. The result must pass what ``pipesentry gateway --check`` (or the mock node) checks.
* ``yaml`` and ``json``: parse.
* ``python``: parses, and every module and name it imports exists.
* ``sh``: ``bash -n`` accepts it; every ``pipesentry`` command and option it uses exists, every
  ``make`` target, ``python -m`` module and repository path it names exists. Then it *runs*, in a
  fresh copy of the checkout (no ``out/``), with ``.venv/bin`` on the PATH, under ``set -e`` with
  ``curl`` failing on HTTP errors, unless it starts something long-running (``make``, ``docker``,
  ``systemctl``, pytest, ``pipesentry demo|api|mock-node|alerts deliver``, a gateway without ``--check``, or a
  ``python -m`` action listed in ``LONG_RUNNING_MODULE_ACTIONS``).
  A block that talks to ``http://127.0.0.1:8000`` runs against a real API server on an ephemeral
  port over the test fleet's database, with ``psk_...`` replaced by an admin key and ``node-7``
  by the fleet's damaged node.
* ``text`` (diagrams, wire formats, sample output) must be neither TOML nor a command line: those
  are tagged ``toml`` / ``sh`` so that they are checked.

Everywhere, ``/var/lib/pipesentry`` (the systemd unit's ``StateDirectory``, created by systemd) is
a temporary directory. A failure names the file, the block's line and the tag.
"""
from __future__ import annotations

import ast
import copy
import importlib
import importlib.util
import json
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import typer
import yaml

from gateway.config import ConfigError, settings_from_mapping
from mocknode.scenario import ScenarioError, scenario_from_dict
from tests.support.api_fixtures import DAMAGED_NODE, in_ci
from tests.support.doc_blocks import REPO, Block, all_blocks, shell_commands

CHECKED_TAGS = ("toml", "yaml", "json", "python", "sh", "text")
STATE_DIR = "/var/lib/pipesentry"
GATEWAY_BASE = REPO / "examples" / "gateway-one-node.toml"
SCENARIO_BASE = REPO / "examples" / "scenarios" / "paper_notch.toml"
DOC_API = "http://127.0.0.1:8000"
REPO_DIRS = ("tests", "docs", "examples", "pipesentry", "deploy", "docker", "scripts", "bench", "imaging",
             "gateway", "service", "db", "alerts", "mocknode", "protocol")
LONG_RUNNING = {"make", "docker", "systemctl", "journalctl", "pytest"}
LONG_RUNNING_SUBCOMMANDS = {("demo",), ("api",), ("mock-node",), ("alerts", "deliver")}
# `python -m <module> <action>` that serve forever or compute for minutes (checked, not started here).
LONG_RUNNING_MODULE_ACTIONS = {("alerts", "deliver"), ("fullwave", "generate")}
RUN_TIMEOUT_S = 120


def _toml_error_line(block: Block, exc: tomllib.TOMLDecodeError) -> int:
    found = re.search(r"line (\d+)", str(exc))
    return block.line + int(found[1]) if found else block.line


# ---------------------------------------------------------------------------------------------- toml
def _merged(base: dict, fragment: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in fragment.items():
        if key == "nodes" and isinstance(value, dict):  # [nodes.x]: a table of the example's node
            out["nodes"] = [_merged(out["nodes"][0], value)]
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merged(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _in_state_dir(value: object, state_dir: Path) -> object:
    if isinstance(value, str):
        return value.replace(STATE_DIR, str(state_dir))
    if isinstance(value, dict):
        return {k: _in_state_dir(v, state_dir) for k, v in value.items()}
    if isinstance(value, list):
        return [_in_state_dir(v, state_dir) for v in value]
    return value


def gateway_config_from(fragment: dict, state_dir: Path, source: str):
    """The fragment completed with the one-node example and validated as `--check` does."""
    base = tomllib.loads(GATEWAY_BASE.read_text(encoding="utf-8"))
    return settings_from_mapping(_in_state_dir(_merged(base, fragment), state_dir), source)  # type: ignore[arg-type]


def _check_toml(block: Block, tmp_path: Path, _request: pytest.FixtureRequest) -> None:
    try:
        data = tomllib.loads(block.text)
    except tomllib.TOMLDecodeError as exc:
        pytest.fail(f"{block.where}: not TOML, line {_toml_error_line(block, exc)}: {exc}")
    state_dir = tmp_path / "state"
    state_dir.mkdir()
    errors = []
    try:
        gateway_config_from(data, state_dir, block.where)
        return
    except ConfigError as exc:
        errors.append(f"as a gateway config: {exc}")
    try:
        scenario_from_dict(_merged(tomllib.loads(SCENARIO_BASE.read_text(encoding="utf-8")), data))
        return
    except ScenarioError as exc:
        errors.append(f"as a mock-node scenario: {exc}")
    pytest.fail(f"{block.where}: a TOML block must be a gateway config or a mock-node scenario (or a fragment "
                f"of one); {' | '.join(errors)}")


# ------------------------------------------------------------------------------------- yaml, json, python
def _check_yaml(block: Block, _tmp_path: Path, _request: pytest.FixtureRequest) -> None:
    try:
        assert yaml.safe_load(block.text) is not None, "empty"
    except (yaml.YAMLError, AssertionError) as exc:
        pytest.fail(f"{block.where}: not YAML: {exc}")


def _check_json(block: Block, _tmp_path: Path, _request: pytest.FixtureRequest) -> None:
    try:
        json.loads(block.text)
    except json.JSONDecodeError as exc:
        pytest.fail(f"{block.where}: not JSON, line {block.line + exc.lineno}: {exc.msg}")


def _check_python(block: Block, _tmp_path: Path, _request: pytest.FixtureRequest) -> None:
    try:
        tree = ast.parse(block.text)
    except SyntaxError as exc:
        pytest.fail(f"{block.where}: not Python, line {block.line + (exc.lineno or 0)}: {exc.msg}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                _assert_module(block, node, alias.name)
        elif isinstance(node, ast.ImportFrom) and node.module:
            module = _assert_module(block, node, node.module)
            missing = [a.name for a in node.names
                       if not hasattr(module, a.name) and importlib.util.find_spec(f"{node.module}.{a.name}") is None]
            assert not missing, f"{block.where}, line {block.line + node.lineno}: {node.module} has no {missing}"


def _assert_module(block: Block, node: ast.stmt, name: str):
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        pytest.fail(f"{block.where}, line {block.line + node.lineno}: cannot import {name}: {exc}")


# ---------------------------------------------------------------------------------------------- text
def _check_text(block: Block, _tmp_path: Path, _request: pytest.FixtureRequest) -> None:
    try:
        data = tomllib.loads(block.text)
    except tomllib.TOMLDecodeError:
        data = {}
    assert not data, f"{block.where}: this is TOML: tag it toml so that it is checked"
    for number, words in shell_commands(block.text):
        assert not _is_project_command(words), (
            f"{block.where}, line {block.line + number}: `{' '.join(words)}` is a command: tag the block sh"
        )


def _is_project_command(words: list[str]) -> bool:
    """A line a reader would paste into a shell: a pipesentry subcommand, a make target, a curl of a URL..."""
    program, rest = Path(words[0]).name, words[1:]
    if program == "pipesentry":
        return bool(rest) and (rest[0].startswith("-") or rest[0] in _cli().commands)  # type: ignore[attr-defined]
    if program == "make":
        return bool(rest) and rest[0] in _make_targets()
    if program == "curl":
        return any(w.startswith(("http://", "https://", "$")) for w in rest)
    return (program.startswith("python") and rest[:1] == ["-m"]) or words[0].startswith(".venv/bin/")


# ------------------------------------------------------------------------------------------------ sh
def _cli():
    from pipesentry.cli import app

    return typer.main.get_command(app)


def _check_pipesentry(block: Block, number: int, words: list[str]) -> None:
    command = _cli()
    where = f"{block.where}, line {block.line + number}"
    for word in words[1:]:
        if word.startswith("-"):
            name = word.split("=", 1)[0]
            known = {opt for p in command.params for opt in (*p.opts, *p.secondary_opts)} | {"--help"}
            assert name in known, f"{where}: `{' '.join(words)}`: {command.name} has no option {name}"
        elif hasattr(command, "commands"):
            assert word in command.commands, f"{where}: `{' '.join(words)}`: no command {word!r}"
            command = command.commands[word]


def _make_targets() -> set[str]:
    text = (REPO / "Makefile").read_text(encoding="utf-8")
    return set(re.findall(r"^([A-Za-z0-9_.-]+):", text, flags=re.MULTILINE))


def _check_command(block: Block, number: int, words: list[str]) -> None:
    where = f"{block.where}, line {block.line + number}: `{' '.join(words)}`"
    program = Path(words[0]).name
    if words[0].startswith(".venv/bin/"):
        assert program in {"python", "python3"} or shutil.which(program, path=str(REPO / ".venv" / "bin")), (
            f"{where}: {words[0]} is not installed by `make .venv/.installed`")
    if program == "pipesentry":
        _check_pipesentry(block, number, words)
    elif program == "make":
        for target in (w for w in words[1:] if not w.startswith("-") and "=" not in w):
            assert target in _make_targets(), f"{where}: the Makefile has no target {target!r}"
    elif program.startswith("python") and "-m" in words:
        module = words[words.index("-m") + 1]
        assert importlib.util.find_spec(module) is not None, f"{where}: no module {module}"
    for word in words[1:]:
        path = word.split("=", 1)[-1]
        if path.split("/", 1)[0] in REPO_DIRS and "/" in path and "$" not in path:
            assert list(REPO.glob(path)), f"{where}: {path} does not exist in the repository"


def _long_running(words: list[str]) -> bool:
    program = Path(words[0]).name
    if program in LONG_RUNNING or (program.startswith("python") and words[1:3] == ["-m", "pytest"]):
        return True
    if program.startswith("python") and words[1:2] == ["-m"] and tuple(words[2:4]) in LONG_RUNNING_MODULE_ACTIONS:
        return True
    if program == "pipesentry":
        subs = tuple(w for w in words[1:3] if not w.startswith("-"))
        if any(subs[: len(long)] == long for long in LONG_RUNNING_SUBCOMMANDS):
            return True
        return subs[:1] == ("gateway",) and "--check" not in words
    return False


def _fresh_checkout(tmp_path: Path) -> Path:
    """The repository as a new user has it: everything linked, no out/; examples with the state directory."""
    clone = tmp_path / "clone"
    clone.mkdir()
    for entry in REPO.iterdir():
        if entry.name not in {"out", "examples", ".git"}:
            (clone / entry.name).symlink_to(entry)
    state_dir = tmp_path / "state"
    state_dir.mkdir(exist_ok=True)
    for source in (REPO / "examples").rglob("*"):
        target = clone / "examples" / source.relative_to(REPO / "examples")
        if source.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif source.suffix == ".toml":
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(source.read_text(encoding="utf-8").replace(STATE_DIR, str(state_dir)), encoding="utf-8")
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(source)
    return clone


PRELUDE = """set -eo pipefail
shopt -s inherit_errexit
trap 'echo "::failed at script line $LINENO (exit $?): $BASH_COMMAND" >&2' ERR
"""


def _strict_curl(bin_dir: Path) -> None:
    """A `curl` first on the PATH that fails on HTTP errors (the docs' `curl -s` would print a problem and go on)."""
    real = shutil.which("curl")
    assert real, "curl is not installed"
    bin_dir.mkdir()
    wrapper = bin_dir / "curl"
    wrapper.write_text(f'#!/bin/sh\nexec {real} --fail-with-body --show-error "$@"\n')
    wrapper.chmod(0o755)


def _run_shell(block: Block, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    script = block.text
    if DOC_API in script:
        api = request.getfixturevalue("api")  # the real API over the test fleet's database
        script = script.replace(DOC_API, api.base_url).replace("psk_...", api.keys.admin)
        script = script.replace("node-7", DAMAGED_NODE)
    clone = _fresh_checkout(tmp_path)
    script = script.replace(STATE_DIR, str(tmp_path / "state"))
    _strict_curl(tmp_path / "bin")
    path = os.pathsep.join([str(tmp_path / "bin"), str(REPO / ".venv" / "bin"), os.environ.get("PATH", "")])
    env = {**os.environ, "PATH": path}
    proc = subprocess.run(["bash", "-c", PRELUDE + script], cwd=clone, env=env, capture_output=True, text=True,
                          timeout=RUN_TIMEOUT_S)
    if proc.returncode != 0:
        found = re.search(r"::failed at script line (\d+) \(exit (\d+)\): (.*)", proc.stderr)
        where = block.where
        if found:
            where += f", line {block.line + int(found[1]) - PRELUDE.count(chr(10))}: `{found[3]}` exited {found[2]}"
        pytest.fail(f"{where}\n--- stderr ---\n{proc.stderr[-3000:]}\n--- stdout ---\n{proc.stdout[-2000:]}")


def _check_sh(block: Block, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    syntax = subprocess.run(["bash", "-n"], input=block.text, capture_output=True, text=True, timeout=30)
    assert syntax.returncode == 0, f"{block.where}: bash -n: {syntax.stderr.strip()}"
    commands = shell_commands(block.text)
    for number, words in commands:
        _check_command(block, number, words)
    if any(_long_running(words) for _, words in commands):
        return  # checked above; not started here
    if shutil.which("jq") is None and "jq" in block.text:
        message = "jq is not installed (scripts/ensure-test-deps.sh installs it)"
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)
    _run_shell(block, tmp_path, request)


CHECKS = {"toml": _check_toml, "yaml": _check_yaml, "json": _check_json, "python": _check_python,
          "sh": _check_sh, "text": _check_text}
assert set(CHECKS) == set(CHECKED_TAGS)


def _runs(block: Block) -> bool:
    return block.tag == "sh" and not any(_long_running(words) for _, words in shell_commands(block.text))


BLOCKS = all_blocks()


@pytest.mark.parametrize(
    "block",
    [pytest.param(b, id=b.where, marks=[pytest.mark.e2e] if _runs(b) else []) for b in BLOCKS],
)
def test_doc_block(block: Block, tmp_path: Path, request: pytest.FixtureRequest):
    assert block.tag, f"{block.where}: tag the block with one of {', '.join(CHECKED_TAGS)} (text: not checked code)"
    assert block.tag in CHECKS, (
        f"{block.where}: no check for the tag {block.tag!r}; use one of {', '.join(CHECKED_TAGS)}"
    )
    CHECKS[block.tag](block, tmp_path, request)


def test_the_docs_have_blocks_of_every_checked_kind():
    """A guard on the extraction itself: if it found nothing, every test above would pass vacuously."""
    assert {b.tag for b in BLOCKS} >= {"toml", "sh", "yaml", "json", "python", "text"}
    assert any(b.path == "README.md" and "analyze" in b.text for b in BLOCKS)
