"""Real processes for end-to-end tests: the mock node on pseudo-terminals, the gateway, the API.

Every wait is bounded; a process still running at the end of a test is killed.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

PYTHON = sys.executable


def wait_until(predicate: Callable[[], object], timeout_s: float, interval_s: float = 0.1, what: str = "condition"):
    """Poll ``predicate`` until it returns a truthy value; fail the test after ``timeout_s``, saying what the
    last poll gave (its error, or its value: an early error the later polls got past is not the story)."""
    deadline = time.monotonic() + timeout_s
    last = "never polled"
    while time.monotonic() < deadline:
        try:
            value = predicate()
        except Exception as exc:  # noqa: BLE001 (any error means not yet: e.g. the database file does not exist)
            last, value = f"error: {type(exc).__name__}: {exc}", None
        else:
            last = f"returned {value!r}"[:300]
        if value:
            return value
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what} (last poll {last})")


class Proc:
    """A child process whose output goes to files (no pipe can fill up and block it)."""

    def __init__(self, args: list[str], log_dir: Path, name: str, env: dict | None = None, nice: int = 0) -> None:
        self.name = name
        if nice:  # nice(1) execs the command: the pid stays the command's own
            args = ["nice", "-n", str(nice), *args]
        self.out_path = log_dir / f"{name}.out"
        self.err_path = log_dir / f"{name}.err"
        self._out = self.out_path.open("wb")
        self._err = self.err_path.open("wb")
        self.popen = subprocess.Popen(
            args, stdout=self._out, stderr=self._err, stdin=subprocess.DEVNULL, env={**os.environ, **(env or {})},
            start_new_session=True,
        )

    @property
    def stdout(self) -> str:
        return self.out_path.read_text(errors="replace")

    @property
    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.popen.poll() is None

    def terminate(self, timeout_s: float = 10.0) -> int:
        if self.alive():
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.popen.returncode

    def kill(self) -> None:
        if self.alive():
            self.popen.kill()
        self.popen.wait(10)

    def close(self) -> None:
        self.kill()
        self._out.close()
        self._err.close()


def start_mock_nodes(
    scenario: Path, link_dir: Path, log_dir: Path, *extra: str, name: str = "mock", nice: int = 0
) -> Proc:
    return Proc(
        [PYTHON, "-m", "pipesentry", "mock-node", "--scenario", str(scenario), "--link-dir", str(link_dir), *extra],
        log_dir,
        name,
        nice=nice,
    )


def wait_for_links(link_dir: Path, node_ids: list[str], proc: Proc, timeout_s: float = 30.0) -> None:
    def ready():
        if not proc.alive():
            raise AssertionError(f"mock node exited: {proc.stderr[-2000:]}")
        return all((link_dir / n).exists() for n in node_ids)

    wait_until(ready, timeout_s, what=f"mock node ports {node_ids}")


def start_gateway(
    config: Path, log_dir: Path, name: str = "gateway", env: dict | None = None, nice: int = 0
) -> Proc:
    return Proc([PYTHON, "-m", "pipesentry", "gateway", "--config", str(config)], log_dir, name, env=env, nice=nice)


GATEWAY_METRICS = re.compile(r"metrics on http://127\.0\.0\.1:(\d+)/metrics")


def gateway_metrics_port(gateway: Proc, timeout_s: float = 30.0) -> int:
    """The port a gateway started with ``[metrics] port = 0`` serves its metrics on (from its log)."""
    found = wait_until(lambda: GATEWAY_METRICS.search(gateway.stderr), timeout_s, what="the gateway's metrics port")
    return int(found.group(1))


def gateway_config(db_path: Path, nodes: list[dict], **top) -> str:
    """A gateway TOML with the given nodes (dicts of NodeSettings fields; nested dicts become tables).

    The gateway's metrics listen on any free port unless ``metrics`` says otherwise (tests run side by side)."""
    top = {"metrics": {"port": 0}, **top}
    lines = [f'[database]\nurl = "sqlite:///{db_path}"\n']
    for key, value in top.items():
        if isinstance(value, dict):
            lines.append(f"[{key}]")
            lines += [f"{k} = {_toml(v)}" for k, v in value.items()]
        else:
            lines.insert(0, f"{key} = {_toml(value)}")
    for node in nodes:
        lines.append("\n[[nodes]]")
        tables = {k: v for k, v in node.items() if isinstance(v, dict)}
        lines += [f"{k} = {_toml(v)}" for k, v in node.items() if not isinstance(v, dict)]
        for tname, table in tables.items():
            lines.append(f"[nodes.{tname}]")
            lines += [f"{k} = {_toml(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def scenario_node(
    node_id: str,
    seed: int,
    *,
    defect: tuple[float, float, float] | None = None,
    temperature: dict | None = None,
    strength: float | None = None,
) -> str:
    """One node of a mock-node scenario TOML on the paper's default pipe: ``defect`` is a notch
    (axial_mm, angle_deg, appears_at_s), of the paper's size or of ``strength`` (scattered / incident
    amplitude); ``temperature`` the node's TemperatureSpec fields."""
    temperature = temperature or {"mean_c": 21.0, "jitter_c": 0.02}
    text = f'\n[[nodes]]\nnode_id = "{node_id}"\nseed = {seed}\n[nodes.temperature]\n'
    text += "".join(f"{k} = {_toml(v)}\n" for k, v in temperature.items())
    if defect is not None:
        axial_mm, angle_deg, appears_at_s = defect
        text += (f'[[nodes.defects]]\nkind = "notch"\naxial_mm = {axial_mm!r}\nangle_deg = {angle_deg!r}\n'
                 f"appears_at_s = {appears_at_s!r}\n")
        if strength is not None:
            text += f"strength = {strength!r}\n"
    return text


def gateway_node(node_id: str, link_dir: Path, **overrides) -> dict:
    """Gateway settings of one mock node, as an installer would write them for the default pipe."""
    cfg = {
        "id": node_id,
        "url": str(link_dir / node_id),
        "interval_s": 0.3,
        "timeout_s": 1.0,
        # what the node does not report: the scenario's default pipe length, Tx ring position and wall
        "geometry": {"pipe_length_mm": 1000.0, "tx_axial_mm": 300.0, "wall_mm": 4.0},
        "threshold": {"calibration_count": 8, "hysteresis_count": 2, "false_alarm_rate": 1e-3},
    }
    cfg.update(overrides)
    return cfg
