"""``pipesentry mock-node``: serve simulated FPGA nodes on pseudo-terminals or TCP until SIGINT/SIGTERM.

The physics and the server are imported when the command runs, not when the ``pipesentry``
command line is built: ``pipesentry --help`` must not pay for scipy.
"""
from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from mocknode.scenario import NodeScenario


def _with_faults(node: NodeScenario, overrides: dict) -> NodeScenario:
    from mocknode.faults import FaultSpec

    if not overrides:
        return node
    faults = FaultSpec(**{**node.faults.model_dump(), **overrides})
    return node.model_copy(update={"faults": faults})


def _announce(node_id: str, url: str) -> None:
    print(f"{node_id} {url}", flush=True)


def mock_node(
    scenario: Annotated[Path | None, typer.Option(help="scenario TOML; default: built-in scenario")] = None,
    nodes: Annotated[int, typer.Option(min=1, max=256, help="nodes of the built-in scenario")] = 1,
    tcp: Annotated[bool, typer.Option(help="serve on TCP 127.0.0.1 (socket://) instead of pseudo-terminals")] = False,
    port: Annotated[int, typer.Option(min=0, max=65535, help="first TCP port (0: ephemeral)")] = 0,
    baud: Annotated[int, typer.Option(min=300, help="line rate for pacing, bit/s (8N1)")] = 230400,
    pace: Annotated[bool, typer.Option(help="send no faster than baud/10 bytes/s, like the real UART")] = False,
    link_dir: Annotated[Path | None, typer.Option(help="keep DIR/<node_id> symlinks to the current pty")] = None,
    corrupt_byte_rate: Annotated[float | None, typer.Option(help="fault: probability per sent byte of one flipped bit")] = None,
    drop_byte_rate: Annotated[float | None, typer.Option(help="fault: probability per sent byte of dropping it")] = None,
    stall_probability: Annotated[float | None, typer.Option(help="fault: probability per request of no answer for --stall-s")] = None,
    stall_s: Annotated[float | None, typer.Option(help="fault: how long a stall lasts, s")] = None,
    disconnect_every_s: Annotated[float | None, typer.Option(help="fault: close the port and open a new one every N s (0: never)")] = None,
    reconnect_after_s: Annotated[float | None, typer.Option(help="fault: how long the port stays gone, s (default 1)")] = None,
    reboot_probability: Annotated[float | None, typer.Option(help="fault: probability per bulk frame of a reboot mid-transfer (RAM lost)")] = None,
    garbage_on_power_up: Annotated[int | None, typer.Option(help="fault: random bytes sent at every (re)boot")] = None,
    reboot_every_s: Annotated[float | None, typer.Option(help="fault: power-cycle every N s, port kept")] = None,
    busy_probability: Annotated[float | None, typer.Option(help="fault: ERROR BUSY per command")] = None,
    protocol_version: Annotated[int | None, typer.Option(help="fault: speak only this protocol version")] = None,
    violation: Annotated[list[str] | None, typer.Option(
        help="break this requirement of docs/protocol.md on purpose (names: docs/simulator.md; repeatable)")] = None,
) -> None:
    """Serve simulated nodes; prints "<node_id> <port>" for every port it opens (again after a reconnect).

    SIGUSR1 power-cycles every node (ports stay open); SIGINT/SIGTERM stop.
    """
    from pydantic import ValidationError

    from mocknode.scenario import ScenarioError, default_scenario, load_scenario
    from mocknode.server import MockNodeServer, ServerError

    overrides = {
        key: value for key, value in {
            "corrupt_byte_rate": corrupt_byte_rate, "drop_byte_rate": drop_byte_rate,
            "stall_probability": stall_probability, "stall_s": stall_s,
            "disconnect_every_s": disconnect_every_s, "reconnect_after_s": reconnect_after_s,
            "reboot_probability": reboot_probability, "garbage_on_power_up": garbage_on_power_up,
            "reboot_every_s": reboot_every_s, "busy_probability": busy_probability,
            "protocol_version": protocol_version, "violations": violation or None,
        }.items() if value is not None
    }
    # The handlers go in before any port is announced: a supervisor may stop us the moment it
    # reads a port, and an unhandled SIGTERM would leave the ports' links behind.
    stopping = threading.Event()
    servers: list[MockNodeServer] = []

    def _stop(signum: int, _frame: object) -> None:
        stopping.set()
        for running in servers:
            running.stop_event.set()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    try:
        fleet = load_scenario(scenario) if scenario is not None else default_scenario(nodes)
        node_scenarios = [_with_faults(node, overrides) for node in fleet.nodes]
        server = MockNodeServer(node_scenarios, kind="tcp" if tcp else "pty", base_port=port, baud=baud,
                                pace=pace, link_dir=link_dir, on_port=_announce)
    except ValidationError as exc:
        where = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        print(f"mock-node: bad fault option: {where}", file=sys.stderr)
        raise typer.Exit(2) from None
    except (ScenarioError, ServerError, ValueError, OSError) as exc:
        print(f"mock-node: {exc}".splitlines()[0], file=sys.stderr)
        raise typer.Exit(2) from None

    servers.append(server)
    if stopping.is_set():
        server.stop_event.set()
    signal.signal(signal.SIGUSR1, lambda _signum, _frame: server.power_cycle())
    server.start()
    while not server.stop_event.wait(1.0):
        pass  # the signal handler sets the event; wait() wakes on it
    server.stop()
