"""Building the ``pipesentry`` command line is cheap and complete: every command listed, no physics imported."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.e2e  # runs the installed command as a process

COMMANDS = ("analyze", "demo", "gateway", "api", "apikey", "alerts", "mock-node")
# What ``--help`` must not import: the physics, numerics, storage, the API, the daemons.
HEAVY = ("numpy", "scipy", "sqlalchemy", "matplotlib", "fastapi", "numba",
         "mocknode.physics", "mocknode.server", "imaging", "db", "gateway", "service", "alerts", "fullwave")
PROBE = """
import json, runpy, sys
args, watched = json.loads(sys.argv[1]), json.loads(sys.argv[2])
sys.argv = ["pipesentry", *args]
code = None
try:
    runpy.run_module("pipesentry", run_name="__main__")
except SystemExit as exit:
    code = exit.code
heavy = sorted(m for m in watched if m in sys.modules)
print(json.dumps({"code": code, "heavy": heavy}), file=sys.stderr)
"""


def probe(*args: str) -> tuple[str, dict]:
    result = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args), json.dumps(HEAVY)],
                            capture_output=True, text=True, timeout=60)
    return result.stdout, json.loads(result.stderr.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [("--help",), ("analyze", "--help"), ("mock-node", "--help"), ("alerts", "--help")])
def test_help_imports_none_of_the_physics_numerics_storage_or_api(args):
    _output, seen = probe(*args)
    assert seen == {"code": 0, "heavy": []}


def test_help_lists_every_command_including_the_mock_node():
    output, _seen = probe("--help")
    assert all(name in output for name in COMMANDS), output
