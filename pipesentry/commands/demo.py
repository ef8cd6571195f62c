"""`pipesentry demo`: the README's main command — simulated nodes, the gateway, SQLite, the API, damage arising.

Starts the mock nodes on pseudo-terminals, the gateway daemon and the API (with a demo key)
as real processes, prints the dashboard URL, then follows the database and prints progress:
measurements, state changes, and the estimated defect coordinates against the scenario's
truth. Stops after ``--duration-s``, on Ctrl-C, on SIGTERM (``kill``) or SIGHUP (the terminal
closed): every child is stopped before it exits, none is left running as an orphan.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from pipesentry.errors import fail

if TYPE_CHECKING:
    from pipesentry.demo_progress import Progress

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
DEMO_SCENARIO = DATA_DIR / "demo_scenario.toml"


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


class Stopped(Exception):
    """A stop signal arrived; raised by the main loop so that the children are stopped on the way out."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopSignals:
    """SIGINT, SIGTERM and SIGHUP are noted, and :meth:`check` / :meth:`sleep` raise :class:`Stopped`.

    The handler only records the signal: one that raised could fire inside a garbage collector's
    callback, where Python prints the exception and drops it (the demo then ran on, deaf to the
    next signal). A second signal while stopping changes nothing; the clean-up runs to the end."""

    POLL_S = 0.2

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def __enter__(self) -> StopSignals:
        def note(signum: int, _frame: object) -> None:
            if self.signum is None:
                self.signum = signum

        self._previous = {sig: signal.signal(sig, note) for sig in STOP_SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]

    def check(self) -> None:
        if self.signum is not None:
            raise Stopped(self.signum)

    def sleep(self, seconds: float) -> None:
        """Wait, answering a stop signal within POLL_S."""
        deadline = time.monotonic() + seconds
        while True:
            self.check()
            left = deadline - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(self.POLL_S, left))


def _die_with_parent() -> None:
    """In the child, before exec: the kernel sends it SIGTERM if the demo dies without cleaning up (kill -9)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


class Child:
    """A child process with its output in a log file, in its own session (Ctrl-C reaches only us)."""

    def __init__(self, name: str, args: list[str], log_dir: Path) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        self._log = self.log_path.open("wb")
        self.popen = subprocess.Popen(
            args, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
            preexec_fn=_die_with_parent if sys.platform == "linux" else None,  # noqa: PLW1509 (no threads yet)
        )

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout_s: float = 10.0) -> None:
        if self.alive():
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(timeout_s)
        self._log.close()


def gateway_toml(db_path: Path, link_dir: Path, nodes, interval_s: float) -> str:
    """The demo's gateway config; the pipe facts a node does not report (length, Tx ring position,
    wall) come from the scenario, as an installer would write them into a real config."""
    lines = [f'[database]\nurl = "sqlite:///{db_path}"\n', "[logging]\njson = false\n"]
    for node in nodes:
        lines.append(
            f'[[nodes]]\nid = "{node.node_id}"\nurl = "{link_dir / node.node_id}"\ninterval_s = {interval_s}\n'
            f"[nodes.geometry]\npipe_length_mm = {node.pipe.length_mm}\ntx_axial_mm = {node.rings.tx_axial_mm}\n"
            f"wall_mm = {node.pipe.wall_mm}\n"
            "[nodes.threshold]\ncalibration_count = 8\nhysteresis_count = 2\nfalse_alarm_rate = 0.001\n"
        )
    return "\n".join(lines)


def _wait_for(predicate, timeout_s: float, what: str, children: list[Child], signals: StopSignals) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        for child in children:
            if not child.alive():
                fail(f"{child.name} exited while waiting for {what}; see {child.log_path}")
        signals.sleep(0.1)
    fail(f"timed out waiting for {what}")


def _free_port(preferred: int) -> int:
    """``preferred`` if it is free on 127.0.0.1, else one the kernel picks."""
    for candidate in (preferred, 0):
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", candidate))
            except OSError:
                continue
            return sock.getsockname()[1]
    fail("no free TCP port on 127.0.0.1")


def _http_ok(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=1) as response:
            return response.status == 200
    except OSError:
        return False


def _schema_ready(db_url: str) -> bool:
    from db.database import open_database
    from db.errors import SchemaOutOfDate, StorageError

    try:
        open_database(db_url, upgrade=False).dispose()
    except (SchemaOutOfDate, StorageError):
        return False
    return True


def demo(
    duration_s: Annotated[float, typer.Option(help="stop after this many seconds")] = 150.0,
    interval_s: Annotated[float, typer.Option(help="seconds between a node's measurements")] = 2.0,
    out_dir: Annotated[Path, typer.Option(help="where the database, config and logs go")] = Path("out/demo"),
    scenario: Annotated[Path, typer.Option(help="mock-node scenario (TOML)")] = DEMO_SCENARIO,
    port: Annotated[int, typer.Option(help="API and dashboard port on 127.0.0.1 (another if taken)")] = 8000,
) -> None:
    """Run simulated nodes and the gateway on SQLite, and show damage being flagged as it arises."""
    from mocknode.scenario import ScenarioError, load_scenario
    from pipesentry.demo_progress import Progress

    try:
        scn = load_scenario(scenario)
    except ScenarioError as exc:
        fail(str(exc))
    node_ids = [n.node_id for n in scn.nodes]
    truths = {n.node_id: [(d.axial_mm, d.angle_deg, d.appears_at_s) for d in n.defects] for n in scn.nodes}
    out_dir = out_dir.resolve()
    link_dir = out_dir / "ports"
    db_path = out_dir / "pipesentry.db"
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for stale in (db_path, db_path.with_name(db_path.name + "-wal"), db_path.with_name(db_path.name + "-shm")):
            stale.unlink(missing_ok=True)
        config = out_dir / "gateway.toml"
        config.write_text(gateway_toml(db_path, link_dir, scn.nodes, interval_s))
    except OSError as exc:
        fail(f"cannot prepare {out_dir}: {exc.strerror or exc}")

    exe = [sys.executable, "-m", "pipesentry"]
    children: list[Child] = []
    started = time.monotonic()
    progress: Progress | None = None
    with StopSignals() as signals:
        try:
            children.append(Child("mock-node", [*exe, "mock-node", "--scenario", str(scenario),
                                                "--link-dir", str(link_dir)], out_dir))
            _wait_for(lambda: all((link_dir / n).exists() for n in node_ids), 30, "the mock nodes' ports", children,
                      signals)
            typer.echo(f"mock nodes up: {', '.join(f'{n} -> {os.path.realpath(link_dir / n)}' for n in node_ids)}")
            children.append(Child("gateway", [*exe, "gateway", "--config", str(config)], out_dir))
            db_url = f"sqlite:///{db_path}"
            _wait_for(lambda: _schema_ready(db_url), 60, "the gateway's database", children, signals)
            typer.echo(f"gateway polling every {interval_s:g} s; database {db_path}; logs in {out_dir}")
            key = subprocess.run(
                [*exe, "apikey", "create", "--name", "demo", "--role", "operator", "--database-url", db_url],
                capture_output=True, text=True, timeout=60, check=False,
            )
            signals.check()  # a signal during the key's creation: that child got it too
            if key.returncode != 0:
                fail(f"cannot create the demo API key: {key.stderr.strip()}")
            token = key.stdout.strip().splitlines()[-1]
            api_port = _free_port(port)
            if api_port != port:
                typer.echo(f"port {port} is taken on 127.0.0.1: the API and dashboard use port {api_port} instead "
                           "(--port chooses another)")
            children.append(Child("api", [*exe, "api", "--database-url", db_url, "--port", str(api_port)], out_dir))
            _wait_for(lambda: _http_ok(f"http://127.0.0.1:{api_port}/healthz"), 60, "the API", children, signals)
            typer.echo(f"dashboard: http://127.0.0.1:{api_port}/#key={token}")
            typer.echo(f"API:       http://127.0.0.1:{api_port}/api/v1/nodes  (Authorization: Bearer {token})")
            typer.echo(f"running for {duration_s:g} s (Ctrl-C stops earlier)\n")
            progress = Progress(db_url, truths, echo=typer.echo)
            while time.monotonic() - started < duration_s:
                for child in children:
                    if not child.alive():
                        fail(f"{child.name} exited unexpectedly; see {child.log_path}")
                progress.poll(elapsed_s=time.monotonic() - started)
                signals.sleep(1.0)
        except Stopped as stop:
            _say(f"\n{'interrupted' if stop.signum == signal.SIGINT else f'stopping on {stop}'}")
        finally:
            for child in reversed(children):
                child.stop()
        _say("stopped cleanly")
        if progress is not None:
            progress.summary(elapsed_s=time.monotonic() - started)


def _say(line: str) -> None:
    """Echo, unless the terminal is gone (SIGHUP): stopping must not depend on being able to print."""
    with contextlib.suppress(OSError):
        typer.echo(line)
