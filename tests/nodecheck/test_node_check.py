"""`pipesentry node-check` against the mock node on a real pty and TCP: a conformant node passes
every requirement, and each violation the mock can inject is caught by exactly the line it breaks."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from mocknode.faults import FaultSpec, Violation
from mocknode.scenario import FirmwareSpec, NodeScenario, default_scenario
from mocknode.server import MockNodeServer
from nodecheck.outcomes import Outcome, Status, all_passed
from nodecheck.requirements import REQUIREMENTS
from nodecheck.runner import CHECKS, run_checks
from nodecheck.session import Timing

pytestmark = pytest.mark.timeout(60)
REPO = Path(__file__).resolve().parents[2]
QUICK = Timing(timeout_s=0.3, backoff_s=0.01)

BROKEN_BY = {
    Violation.ANSWERS_CORRUPT_FRAMES: "R-FRAME-2",
    Violation.ACCEPTS_OVERSIZED: "R-FRAME-3",
    Violation.INFO_NEEDS_VERSION: "R-VER-1",
    Violation.VERSION_IGNORED: "R-VER-2",
    Violation.REQUEST_ID_ZERO_RUNS: "R-REQ-1",
    Violation.LENIENT_LENGTHS: "R-REQ-3",
    Violation.CLAMPS_SETTINGS: "R-CONF-2",
    Violation.ACQUIRES_TWICE: "R-CACHE-1",
    Violation.CACHED_CRC_STALE: "R-CACHE-2",
    Violation.CACHES_ERRORS: "R-CACHE-3",
    Violation.MISSTATES_CHUNK_COUNT: "R-TRACE-1",
    Violation.IGNORES_CHUNK_LIST: "R-BULK-1",
    Violation.DI_BOXCAR_DECIMATION: "R-DI-2",
    Violation.BUSY_FOREVER: "R-BUSY-1",
    Violation.BOOT_ID_STICKY: "R-BOOT-2",
}


def node(faults: dict | None = None, firmware: dict | None = None) -> NodeScenario:
    return default_scenario(1).nodes[0].model_copy(
        update={"faults": FaultSpec(**(faults or {})), "firmware": FirmwareSpec(**(firmware or {}))})


def check(scenario: NodeScenario, kind: str = "pty") -> dict[str, Outcome]:
    with MockNodeServer([scenario], kind=kind) as server:
        outcomes = run_checks(server.urls[scenario.node_id], QUICK, reboot=server.power_cycle, reboot_wait_s=5.0,
                              seed=7)
    assert [o.requirement.id for o in outcomes] == [r.id for r in REQUIREMENTS]
    return {o.requirement.id: o for o in outcomes}


def by_status(outcomes: dict[str, Outcome], status: Status) -> set[str]:
    return {rid for rid, o in outcomes.items() if o.status == status}


@pytest.mark.parametrize("kind", ["pty", "tcp"])
def test_the_mock_node_passes_every_requirement(kind):
    outcomes = check(node(), kind)
    assert by_status(outcomes, Status.FAILED) == set(), [o.line() for o in outcomes.values()]
    assert by_status(outcomes, Status.NOT_APPLICABLE) == {"R-CAP-1"}  # it has every capability
    assert all_passed(list(outcomes.values()))


def test_a_node_that_answers_busy_while_acquiring_passes_and_is_seen_busy():
    outcomes = check(node(firmware={"busy_while_acquiring": True}))
    assert by_status(outcomes, Status.FAILED) == set(), [o.line() for o in outcomes.values()]
    assert "BUSY during an acquisition, served when resent" in outcomes["R-BUSY-1"].note


def test_a_version_1_node_passes_what_version_1_requires():
    outcomes = check(node({"protocol_version": 1}))
    assert by_status(outcomes, Status.FAILED) == set(), [o.line() for o in outcomes.values()]
    assert by_status(outcomes, Status.NOT_APPLICABLE) == {"R-VER-1", "R-REQ-1", "R-CAP-1"}


def test_a_node_without_capabilities_is_checked_for_its_refusals_and_spared_the_rest():
    outcomes = check(node(firmware={"capabilities": []}))
    assert by_status(outcomes, Status.FAILED) == set(), [o.line() for o in outcomes.values()]
    assert by_status(outcomes, Status.NOT_APPLICABLE) == {"R-BULK-1", "R-DI-1", "R-DI-2"}
    assert "ON_BOARD_DI, BASELINE_SLOT, CHUNK_RETRANSMIT" in outcomes["R-CAP-1"].note


@pytest.mark.parametrize("violation", list(Violation))
def test_each_violation_is_caught_by_exactly_the_line_it_breaks(violation):
    firmware = {"busy_while_acquiring": True} if violation == Violation.BUSY_FOREVER else {}
    outcomes = check(node({"violations": [violation]}, firmware))
    assert by_status(outcomes, Status.FAILED) == {BROKEN_BY[violation]}, [o.line() for o in outcomes.values()]
    failed = outcomes[BROKEN_BY[violation]]
    assert failed.note and failed.line().startswith(f"{BROKEN_BY[violation]:<10} FAILED ")


def test_every_violation_names_a_requirement_the_checker_has():
    assert set(BROKEN_BY) == set(Violation)
    assert set(BROKEN_BY.values()) <= set(CHECKS)


def test_a_failed_line_shows_the_bytes_that_failed():
    outcomes = check(node({"violations": [Violation.CACHED_CRC_STALE]}))
    line = outcomes["R-CACHE-2"].line()
    assert re.search(r"\[bytes: 02 83 07 00( [0-9a-f]{2})+\]", line), line  # version 2, CONFIGURE_REPLY, REPLY|LAST|CACHED


def test_every_requirement_is_a_numbered_clause_of_the_protocol_document_and_back():
    text = (REPO / "docs" / "protocol.md").read_text()
    documented = re.findall(r"\*\*(R-[A-Z]+-\d+)\*\*", text)
    assert len(documented) == len(set(documented)), "a requirement id is defined twice"
    assert set(documented) == {r.id for r in REQUIREMENTS} == set(CHECKS)
