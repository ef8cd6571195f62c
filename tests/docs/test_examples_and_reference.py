"""The shipped example configs pass `--check`, the settings table in docs/gateway.md is what the models
accept, and the commands' help and reference pages name every option."""
from __future__ import annotations

import subprocess
import sys
import tomllib

import click
import pytest
import typer

from gateway.settings_reference import BEGIN, END, reference_table
from tests.support.doc_blocks import REPO

EXAMPLES = sorted((REPO / "examples").glob("gateway-*.toml"))
STATE_DIR = "/var/lib/pipesentry"  # the systemd unit's StateDirectory: a temporary directory here


def _installed_copy(example, tmp_path):
    """The example as installed by the documented steps: systemd has created the state directory."""
    state = tmp_path / "state"
    state.mkdir(exist_ok=True)
    target = tmp_path / example.name
    target.write_text(example.read_text(encoding="utf-8").replace(STATE_DIR, str(state)), encoding="utf-8")
    return target


def test_there_is_an_example_for_each_kind_of_installation():
    names = {p.name for p in EXAMPLES}
    assert {"gateway-one-node.toml", "gateway-several-nodes.toml", "gateway-postgresql.toml",
            "gateway-alert-sinks.toml"} <= names
    sinks = {s["type"] for p in EXAMPLES for s in tomllib.loads(p.read_text()).get("alerting", {}).get("sinks", [])}
    assert sinks == {"webhook", "alertmanager", "slack", "mqtt"}
    postgres = tomllib.loads((REPO / "examples" / "gateway-postgresql.toml").read_text())
    assert postgres["database"]["url"].startswith("postgresql+psycopg://")
    assert len(tomllib.loads((REPO / "examples" / "gateway-several-nodes.toml").read_text())["nodes"]) >= 3


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_every_example_is_commented(example):
    comments = [line for line in example.read_text().splitlines() if line.lstrip().startswith("#") or " # " in line]
    assert len(comments) >= 5, f"{example.name}: an example explains itself; it has {len(comments)} comments"


@pytest.mark.e2e
@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_every_example_passes_check(example, tmp_path):
    installed = _installed_copy(example, tmp_path)
    proc = subprocess.run([sys.executable, "-m", "pipesentry", "gateway", "--config", str(installed), "--check"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, f"examples/{example.name}: {proc.stderr.strip()}"
    nodes = len(tomllib.loads(example.read_text())["nodes"])
    assert f"ok, {nodes} node(s)" in proc.stdout


def test_the_settings_table_in_the_gateway_docs_is_what_the_models_accept():
    text = (REPO / "docs" / "gateway.md").read_text(encoding="utf-8")
    assert BEGIN in text and END in text, "docs/gateway.md lost its settings-reference markers"
    documented = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert documented == reference_table(), (
        "docs/gateway.md's settings table is stale: run `python -m gateway.settings_reference --write docs/gateway.md`"
    )


def test_the_calibration_minimum_is_documented():
    assert "| `nodes[].threshold.calibration_count` | `10` | integer, ≥ 5, ≤ 1000 |" in reference_table()


def _command(*path: str) -> click.Command:
    from pipesentry.cli import app

    command = typer.main.get_command(app)
    for name in path:
        command = command.commands[name]  # type: ignore[attr-defined]
    return command


def _option_names(command: click.Command) -> list[str]:
    return [opt for p in command.params if isinstance(p, click.Option) for opt in p.opts if opt != "--help"]


@pytest.mark.parametrize("path", [("mock-node",), ("gateway",), ("analyze",), ("api",), ("demo",), ("apikey", "create")])
def test_help_shows_every_option_in_full_at_80_columns(path):
    from typer.testing import CliRunner

    from pipesentry.cli import app

    result = CliRunner().invoke(app, [*path, "--help"], terminal_width=80, env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    for option in _option_names(_command(*path)):
        assert option in result.output, f"`pipesentry {' '.join(path)} --help` truncates or hides {option}"
    assert "…" not in result.output
    assert max(len(line) for line in result.output.splitlines()) <= 80


def test_the_simulator_docs_name_the_mock_node_command_and_every_fault_flag():
    text = (REPO / "docs" / "simulator.md").read_text(encoding="utf-8")
    assert "pipesentry mock-node" in text
    missing = [option for option in _option_names(_command("mock-node")) if f"`{option}" not in text]
    assert not missing, f"docs/simulator.md does not document {missing}"


REPO_DIRS = ("tests", "docs", "examples", "pipesentry", "deploy", "docker", "scripts", "bench", "imaging", "gateway",
             "service", "db", "alerts", "mocknode", "protocol", "fullwave", "retry_timing")


def test_every_repository_path_the_docs_name_exists():
    """A file named in prose (`tests/...`, `scripts/...`) moves with the code or the doc says where."""
    import re

    from tests.support.doc_blocks import doc_paths

    missing = []
    for doc in doc_paths():
        for number, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            for name in re.findall(r"`([^`\s]+)`", line):
                path = name.split("::")[0].rstrip(".,;:)")
                is_file_or_dir = "." in path.rsplit("/", 1)[-1] or path.endswith("/")  # not an MQTT topic
                placeholder = "<" in path or "..." in path
                if (path.split("/", 1)[0] in REPO_DIRS and "/" in path and is_file_or_dir and not placeholder
                        and not list(REPO.glob(path))):
                    missing.append(f"{doc.relative_to(REPO)}:{number}: {path}")
    assert not missing, "the docs name paths that do not exist:\n" + "\n".join(missing)
