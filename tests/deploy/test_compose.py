"""docker/compose.yaml, the central site, checked without a container engine: it parses, every image is
pinned public or built from the repository's Dockerfile, every file it mounts and command it names
exists, and the configurations it mounts are accepted by their own tools. (The API command runs from
the installed wheel in tests/service/test_central_workers.py.)"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml

from gateway.config import DeliverySettings, load_delivery_settings
from tests.support.api_fixtures import in_ci
from tests.support.wheel_fixtures import REPO, run_in

COMPOSE = REPO / "docker" / "compose.yaml"
# A release's full version tag (PostgreSQL's are major.minor), never latest or a bare major.
PINNED = re.compile(r"^[a-z0-9./-]+:v?\d+\.\d+(\.\d+)?(-[a-z0-9.]+)?$")
WANTED = {"postgres", "migrate", "api", "alerts", "prometheus", "alertmanager", "grafana"}


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def ours(service: dict) -> bool:
    return "build" in service


def tool(name: str) -> str:
    found = shutil.which(name)
    if found is None:
        message = f"{name} not installed (scripts/ensure-test-deps.sh installs it)"
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)
    return found


def test_it_runs_the_whole_central_site(compose):
    assert set(compose["services"]) == WANTED
    api = compose["services"]["api"]
    assert api["command"][:2] == ["api", "--workers"] and int(api["command"][2]) > 1
    assert api["environment"]["PIPESENTRY_API_DATABASE_URL"].startswith("postgresql+psycopg://")
    assert api["depends_on"] == {"migrate": {"condition": "service_completed_successfully"}}


def test_every_image_is_pinned_public_or_built_from_the_repositorys_dockerfile(compose):
    for name, service in compose["services"].items():
        if ours(service):
            build = service["build"]
            context = (COMPOSE.parent / build["context"]).resolve()
            assert context == REPO and (context / build["dockerfile"]).is_file(), name
        else:
            assert PINNED.match(service["image"]), f"{name}: {service['image']} is not a pinned version"


def test_every_file_it_mounts_exists_but_the_operators_secret(compose):
    named = set(compose.get("volumes", {}))
    for name, service in compose["services"].items():
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source in named:
                continue
            if source == "./secrets/prometheus.key":  # the operator writes it (docs/deploy.md)
                continue
            assert (COMPOSE.parent / source).exists(), f"{name}: {source} is not in the repository"


def test_the_commands_of_our_image_exist_in_the_installed_wheel(compose, installed_wheel):
    for name, service in compose["services"].items():
        if not ours(service):
            continue
        argv = service.get("entrypoint") or ["pipesentry", *service["command"]]
        if argv[:3] == ["python", "-m", "db"]:
            result = run_in(installed_wheel, "python", "-m", "db", "--help")
            assert result.returncode == 0 and argv[3] in result.stdout, (name, result.stderr[-500:])
            continue
        assert argv[0] == "pipesentry", name
        words = [a for a in argv[1:] if not a.startswith("-")]
        subcommand = words[:2] if words[:2] == ["alerts", "deliver"] else words[:1]
        result = run_in(installed_wheel, "pipesentry", *subcommand, "--help")
        assert result.returncode == 0, (name, result.stderr[-500:])
        for option in (a for a in argv if a.startswith("--")):
            assert option in result.stdout, f"{name}: {option} is not an option of pipesentry {' '.join(subcommand)}"


def test_the_central_alert_config_is_delivery_only_and_names_the_apis_central_sinks(compose):
    path = REPO / "docker" / "central" / "alerts.toml"
    settings = load_delivery_settings(path)
    assert isinstance(settings, DeliverySettings) and "nodes" not in tomllib.loads(path.read_text())
    sinks = json.loads(compose["services"]["api"]["environment"]["PIPESENTRY_API_CENTRAL_ALERT_SINKS"])
    assert sinks == [sink.name for sink in settings.alerting.sinks]
    assert "--no-watch" in compose["services"]["alerts"]["command"]  # the gateways watch their own nodes


def test_prometheus_and_alertmanager_accept_what_it_mounts(tmp_path):
    config = tmp_path / "prometheus.yml"
    config.write_text((REPO / "docker" / "central" / "prometheus.yml").read_text()
                      .replace("/etc/prometheus/pipesentry.key", str(tmp_path / "key")))
    (tmp_path / "key").write_text("psk_example\n")
    shutil.copy(REPO / "docker" / "prometheus" / "alerts.yml", tmp_path / "alerts.yml")
    checked = subprocess.run([tool("promtool"), "check", "config", str(config)], capture_output=True, text=True,
                             timeout=60)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    am = subprocess.run([tool("amtool"), "check-config", str(REPO / "docker" / "alertmanager" / "alertmanager.yml")],
                        capture_output=True, text=True, timeout=60)
    assert am.returncode == 0, am.stdout + am.stderr


def test_grafana_is_provisioned_with_the_prometheus_and_the_shipped_dashboard(compose):
    grafana = compose["services"]["grafana"]
    provisioning = REPO / "docker" / "grafana" / "provisioning"
    sources = yaml.safe_load((provisioning / "datasources" / "prometheus.yaml").read_text())["datasources"]
    assert [(s["type"], s["url"]) for s in sources] == [("prometheus", "http://prometheus:9090")]
    providers = yaml.safe_load((provisioning / "dashboards" / "pipesentry.yaml").read_text())["providers"]
    mounted = {Path(v.split(":")[1]).parent.as_posix() for v in grafana["volumes"] if "grafana-dashboard.json" in v}
    assert [p["options"]["path"] for p in providers] == sorted(mounted)
    json.loads((REPO / "docker" / "grafana-dashboard.json").read_text())
