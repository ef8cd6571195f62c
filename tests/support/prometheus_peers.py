"""The real Prometheus tools as test peers: promtool, amtool, and Alertmanager and Prometheus processes.

Debian's ``prometheus`` (2.42, with promtool) and ``prometheus-alertmanager`` (0.25, with amtool)
packages; ``make test`` installs them when missing (scripts/ensure-test-deps.sh). A test that
needs one skips with the reason where it is absent, and fails under CI (``CI=true``).

:class:`Alertmanager` and :class:`Prometheus` run their own processes on 127.0.0.1 ephemeral ports
with temporary data directories (never the system services), and stop them at the end.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import httpx
import yaml

from tests.support.peers import peer_missing
from tests.support.process_harness import Proc, wait_until

ENSURE = "scripts/ensure-test-deps.sh"
PACKAGES = {"promtool": "prometheus", "prometheus": "prometheus",
            "prometheus-alertmanager": "prometheus-alertmanager", "amtool": "prometheus-alertmanager"}
LISTENING = re.compile(r'msg="Listening on" address=127\.0\.0\.1:(\d+)')


def require_binary(name: str) -> str:
    """The path of ``name``; skips (fails under CI=true) when it is not installed."""
    path = shutil.which(name)
    if path is None:
        peer_missing(f"{name} is not installed (Debian package {PACKAGES.get(name, name)!r}; `bash {ENSURE}` installs it)")
    return path


def run_tool(name: str, *args: str, cwd: Path | None = None, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([require_binary(name), *args], capture_output=True, text=True, cwd=cwd, timeout=timeout_s)


def alertmanager_config(webhook_url: str, *, resolve_timeout: str = "5m") -> dict[str, Any]:
    """A route that notifies ``webhook_url`` at once, firing and resolved, grouped per alert."""
    return {
        "global": {"resolve_timeout": resolve_timeout},
        "route": {
            "receiver": "test", "group_by": ["..."],  # every label set its own group: one notification each
            "group_wait": "0s", "group_interval": "1s", "repeat_interval": "1h",
        },
        "receivers": [{"name": "test", "webhook_configs": [{"url": webhook_url, "send_resolved": True}]}],
    }


class _Served:
    """A real Prometheus-project server on 127.0.0.1:<ephemeral> with its own data directory."""

    def __init__(self, binary: str, args: list[str], work_dir: Path, name: str) -> None:
        self.proc = Proc([require_binary(binary), *args, "--web.listen-address=127.0.0.1:0"], work_dir, name)
        try:
            port = wait_until(self._port, 30, what=f"{name} to listen")
            self.url = f"http://127.0.0.1:{port}"
            wait_until(self._ready, 30, what=f"{name} to be ready")
        except BaseException:
            self.close()
            raise

    def _port(self) -> int | None:
        if not self.proc.alive():
            raise AssertionError(f"{self.proc.name} exited: {self.proc.stderr[-2000:]}")
        found = LISTENING.search(self.proc.stderr)
        return int(found.group(1)) if found else None

    def _ready(self) -> bool:
        return httpx.get(f"{self.url}/-/ready", timeout=2).status_code == 200

    def close(self) -> None:
        self.proc.terminate(timeout_s=10)
        self.proc.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _config_file(work_dir: Path, name: str, config: dict[str, Any]) -> Path:
    work_dir.mkdir(parents=True, exist_ok=True)
    path = work_dir / f"{name}.yml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


class Alertmanager(_Served):
    """A real Alertmanager (clustering off, never the system service)."""

    def __init__(self, work_dir: Path, config: dict[str, Any], name: str = "alertmanager") -> None:
        path = _config_file(work_dir, name, config)
        super().__init__("prometheus-alertmanager", [
            f"--config.file={path}", f"--storage.path={work_dir / (name + '-data')}", "--cluster.listen-address=",
            "--log.level=info"], work_dir, name)

    def alerts(self, **labels: str) -> list[dict[str, Any]]:
        """The active alerts (``GET /api/v2/alerts``; resolved ones are not listed) matching ``labels``."""
        params = [("filter", f'{k}="{v}"') for k, v in labels.items()]
        response = httpx.get(f"{self.url}/api/v2/alerts", params=params, timeout=5)
        response.raise_for_status()
        return response.json()

    def amtool_query(self, *matchers: str) -> list[dict[str, Any]]:
        """``amtool alert query -o json``: what an operator's terminal says is active."""
        result = run_tool("amtool", f"--alertmanager.url={self.url}", "alert", "query", "-o", "json", *matchers)
        assert result.returncode == 0, result.stderr
        return json.loads(result.stdout or "[]")


class Prometheus(_Served):
    """A real Prometheus server on ``config_path`` (which may name rule files next to it)."""

    def __init__(self, work_dir: Path, config_path: Path, name: str = "prometheus") -> None:
        super().__init__("prometheus", [
            f"--config.file={config_path}", f"--storage.tsdb.path={work_dir / (name + '-data')}",
            "--log.level=info"], work_dir, name)

    def api(self, path: str, **params: str) -> Any:
        response = httpx.get(f"{self.url}/api/v1/{path}", params=params, timeout=10)
        response.raise_for_status()
        body = response.json()
        assert body["status"] == "success", body
        return body["data"]

    def query(self, expr: str) -> list[dict[str, Any]]:
        return self.api("query", query=expr)["result"]
