"""The import graph keeps the layers of docs/architecture.md (import-linter contracts in pyproject.toml)."""
from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import grimp
import pytest
from importlinter import configuration
from importlinter.application.use_cases import SUCCESS, lint_imports, read_user_options
from importlinter.contracts.forbidden import ForbiddenContract
from importlinter.contracts.layers import LayersContract

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = ROOT / "pyproject.toml"
CONTRACT_TYPES = {"layers": LayersContract, "forbidden": ForbiddenContract}


@pytest.fixture(scope="module")
def options():
    configuration.configure()  # what lint-imports does first: the config readers and contract types
    return read_user_options(str(PYPROJECT))


@pytest.fixture(scope="module")
def graph(options):
    return grimp.build_graph(*options.session_options["root_packages"], include_external_packages=False)


def contracts_of(options) -> dict[str, object]:
    return {c["id"]: c for c in options.contracts_options}


def kept(options, graph, contract_id: str) -> bool:
    spec = contracts_of(options)[contract_id]
    contract = CONTRACT_TYPES[spec["type"]](
        name=spec["name"], session_options=options.session_options, contract_options=spec
    )
    return contract.check(graph, verbose=False).kept


def test_every_contract_is_kept(options, capsys):
    assert lint_imports(config_filename=str(PYPROJECT), no_logo=True, cache_dir=None) is SUCCESS  # as make lint runs it
    assert f"{len(options.contracts_options)} kept, 0 broken" in capsys.readouterr().out


def test_every_package_the_project_installs_is_in_the_contracts(options):
    installed = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = {pattern.rstrip("*") for pattern in installed}
    assert set(options.session_options["root_packages"]) == packages
    layered = set()
    for spec in options.contracts_options:
        for key in ("layers", "source_modules", "forbidden_modules"):
            for entry in spec.get(key, ()):
                layered |= {name.strip() for name in entry.split("|")}
    assert layered == packages  # a new package has to be given its place


@pytest.mark.parametrize(
    "importer, imported, contract_id",
    [
        ("alerts.__main__", "gateway.config", "layers"),  # the alerts <-> gateway cycle issue 14 found
        ("service.traces", "gateway.measurement_build", "layers"),  # the API reaching into the gateway
        ("service.traces", "gateway.geometry", "layers"),  # daemons are independent of each other
        ("db.queries", "alerts.events", "layers"),
        ("imaging.pipeline", "db.records", "layers"),
        ("protocol.messages", "imaging.grid", "layers"),  # the two pure layers are independent
        ("gateway.worker", "mocknode.node", "no-simulator-in-the-system"),
        ("mocknode.node", "db.records", "no-system-in-a-simulator"),
        ("fullwave.cli", "mocknode.scenario", "simulators-layers"),  # the independent check stays independent
    ],
)
def test_an_import_from_a_layer_above_breaks_a_contract(options, graph, importer, imported, contract_id):
    assert kept(options, graph, contract_id)
    broken = copy.deepcopy(graph)
    broken.add_import(importer=importer, imported=imported, line_number=1, line_contents=f"import {imported}")
    assert not kept(options, broken, contract_id)
