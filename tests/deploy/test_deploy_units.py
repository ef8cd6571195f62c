"""The systemd units in deploy/systemd: systemd itself accepts them, they run commands the
installed package has, and the gateway yields the CPU to the API under contention."""
from __future__ import annotations

import configparser
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e  # runs the system's real processes

REPO = Path(__file__).resolve().parents[2]
UNITS = REPO / "deploy" / "systemd"
INSTALLED_EXE = "/opt/pipesentry/.venv/bin/pipesentry"
VENV_EXE = Path(sys.executable).with_name("pipesentry")


def unit(name: str) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # systemd keys are case-sensitive
    parser.read_string((UNITS / name).read_text())
    return parser


def exec_start(name: str) -> list[str]:
    argv = shlex.split(unit(name)["Service"]["ExecStart"])
    assert argv[0] == INSTALLED_EXE, argv
    return [str(VENV_EXE), *argv[1:]]


@pytest.mark.parametrize("name", ["pipesentry-gateway.service", "pipesentry-api.service"])
def test_systemd_accepts_the_unit_without_a_warning(name, tmp_path):
    verify = shutil.which("systemd-analyze")
    if verify is None:
        reason = "systemd-analyze is not installed (Debian package 'systemd')"
        if os.environ.get("CI") == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    local = tmp_path / name  # the same unit, pointing at this checkout's installed command
    local.write_text((UNITS / name).read_text().replace(INSTALLED_EXE, str(VENV_EXE)))
    result = subprocess.run([verify, "verify", str(local)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr


@pytest.mark.parametrize("name", ["pipesentry-gateway.service", "pipesentry-api.service"])
def test_the_unit_runs_a_command_the_package_has(name):
    argv = exec_start(name)
    result = subprocess.run([*argv, "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    for option in (a for a in argv[2:] if a.startswith("--")):
        assert option in result.stdout, f"{option} is not an option of {argv[1]}"


def test_the_gateway_yields_the_cpu_to_the_api():
    gateway, api = unit("pipesentry-gateway.service")["Service"], unit("pipesentry-api.service")["Service"]
    assert int(gateway.get("Nice", "0")) > int(api.get("Nice", "0"))
    assert int(gateway.get("CPUWeight", "100")) < int(api.get("CPUWeight", "100"))


def test_both_units_reach_the_database_directory():
    gateway, api = unit("pipesentry-gateway.service")["Service"], unit("pipesentry-api.service")["Service"]
    assert gateway["User"] == api["User"]  # the gateway's SQLite file and its -wal/-shm are the user's
    assert "/var/lib/pipesentry" in api["ReadWritePaths"].split()
    assert gateway["StateDirectory"] == "pipesentry"
