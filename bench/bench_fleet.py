"""The central site under load: sustained ingest of measurements with traces, fleet-query latency meanwhile, and
the uplink's catch-up after an outage.

Run: ``.venv/bin/python bench/bench_fleet.py [all|central|catch-up] [--workers 1 4] [--duration-s 20] [--senders 8]
[--nodes 100] [--outage-min 60]``
(needs the PostgreSQL server on 127.0.0.1:5432; the benchmark creates its own database and drops it).

For each worker count: a fresh database (migrated as ``python -m db upgrade`` does) with 1,000 nodes
reported by 10 gateways of 5 sites, ``pipesentry api --workers N`` in its own processes, then for
``--duration-s`` seconds ``--senders`` concurrent gateways-like clients POST ready-made batches
(20 measurements of 8 x 6,000 ADC codes each with its traces, ``shuffle-zlib-v1`` as a gateway
stores them, and its detection; gzip) while one client asks the fleet questions an operator's
dashboard asks (``/fleet/sites``, ``/fleet/nodes?state=damage``, a page of ``/fleet/nodes``) one after
the other. The batches are built and compressed before the clock starts, so the clients' cost is
sending only; everything (PostgreSQL, the API workers, the clients) shares this machine's cores.

Prints, per worker count: measurements stored per second (and MB/s of request bodies), batches
refused busy (429) if any, and the p50/p99/max of the fleet queries while ingest runs.

Catch-up: one gateway's queue after a one-hour outage of 100 nodes at a 60 s cadence (6,000 monitor
measurements, each with its traces from the mock node's physics, 16 x 6000 samples, ~76 kB stored, a
100 x 72 gateway DI map and its detection: 12,100 records with the nodes) is written into a real SQLite
file the way the gateway writes it (``store_cycle`` on a queueing handle), then drained by the gateway's
own sender (``gateway/uplink/sender.py``, default ``[uplink]`` settings, in this process) into
``pipesentry api`` (one worker) against PostgreSQL in a database of its own. Prints how long the drain
takes, its rates, and where the time goes (the edge reading and encoding batches vs the centre answering).
"""
from __future__ import annotations

import argparse
import asyncio
import contextlib
import gzip
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import numpy as np
import psycopg

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from db.api_keys import create_api_key  # noqa: E402
from db.blobs import TRACE_DTYPE, encode_array  # noqa: E402
from db.cycles import store_cycle  # noqa: E402
from db.database import open_database  # noqa: E402
from db.models import (  # noqa: E402
    MapSource,
    MeasurementKind,
    NodeState,
    Role,
)
from db.nodes import upsert_node  # noqa: E402
from db.records import (  # noqa: E402
    AcquisitionInput,
    CycleRecord,
    DetectionInput,
    DiMapInput,
    MapGrid,
    NodeGeometry,
    NodeInfo,
)
from db.uplink_queue import QueuePolicy, queue_stats  # noqa: E402
from gateway.config import UplinkSettings  # noqa: E402
from gateway.uplink.batches import Batch, Outcome  # noqa: E402
from gateway.uplink.sender import UplinkSender  # noqa: E402
from mocknode.physics import acquire  # noqa: E402
from mocknode.scenario import load_scenario  # noqa: E402
from tests.support.api_fixtures import free_port  # noqa: E402
from tests.support.db_fixtures import sample_codes  # noqa: E402
from tests.support.ingest_batches import blob, detection_record, measurement_record, node_record  # noqa: E402
from tests.support.process_harness import Proc, wait_until  # noqa: E402
from uplink.contract import INGEST_PATH, IngestBatch, MeasurementRecord, Record  # noqa: E402

PG_ADMIN = "host=127.0.0.1 port=5432 user=postgres dbname=test connect_timeout=3"
PG_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
SITES = 5
GATEWAYS_PER_SITE = 2
NODES_PER_GATEWAY = 100  # 1,000 nodes
N_CHANNELS, N_SAMPLES = 8, 6_000  # the gateway's default record length (gateway/config.py)
MEASUREMENTS_PER_BATCH = 20  # with their detections: 40 records, about 1.1 MB of JSON
BIN = Path(sys.executable).parent


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


class Site:
    def __init__(self, index: int, key: str) -> None:
        self.name = f"site-{index}"
        self.key = key
        self.gateways = [f"gw-{index}-{g}" for g in range(GATEWAYS_PER_SITE)]


def prepare_database(name: str) -> tuple[str, list[Site], str]:
    with psycopg.connect(PG_ADMIN, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    url = PG_URL.format(name=name)
    database = open_database(url)
    try:
        with database.write() as session:
            sites = [Site(i, create_api_key(session, name=f"site-{i}", role=Role.GATEWAY, site=f"site-{i}")[1])
                     for i in range(SITES)]
            viewer = create_api_key(session, name="bench-viewer", role=Role.VIEWER)[1]
    finally:
        database.dispose()
    return url, sites, viewer


def drop_database(name: str) -> None:
    with psycopg.connect(PG_ADMIN, autocommit=True) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def post(base: str, key: str, batch: IngestBatch) -> None:
    answer = httpx.post(f"{base}{INGEST_PATH}", content=gzip.compress(batch.model_dump_json().encode()), timeout=120,
                        headers={"Authorization": f"Bearer {key}", "Content-Encoding": "gzip"})
    answer.raise_for_status()


def seed_nodes(base: str, sites: list[Site]) -> None:
    """1,000 nodes; every 50th one damaged (its node record says so)."""
    count = 0
    for site in sites:
        for gateway in site.gateways:
            records: list[Record] = []
            for n in range(NODES_PER_GATEWAY):
                records.append(node_record(gateway, f"{gateway}-n{n:03d}", state="damage" if count % 50 == 0 else "ok"))
                count += 1
            post(base, site.key, IngestBatch(gateway_id=gateway, site=site.name, batch_id=uuid.uuid4(), records=records))


def ready_batches(sites: list[Site], count: int) -> list[tuple[str, bytes, int]]:
    """(key, gzip body, measurements) per batch: each batch is one node's next 20 measurements with traces."""
    codes = [encode_array(sample_codes(seed, N_CHANNELS, N_SAMPLES), TRACE_DTYPE) for seed in range(4)]
    traces = [blob(c.data, TRACE_DTYPE) for c in codes]
    template = measurement_record("x", "x", 1, traces=False, n_samples=N_SAMPLES)
    out = []
    local_id = 0
    for b in range(count):
        site = sites[b % len(sites)]
        gateway = site.gateways[(b // len(sites)) % len(site.gateways)]
        node_id = f"{gateway}-n{(b // (len(sites) * len(site.gateways))) % NODES_PER_GATEWAY:03d}"
        records: list[Record] = []
        for _ in range(MEASUREMENTS_PER_BATCH):
            local_id += 1
            records.append(MeasurementRecord(**{**template.model_dump(), "uid": f"{gateway}/measurement/{local_id}",
                                                "node_id": node_id, "node_measurement_id": local_id,
                                                "traces": traces[local_id % len(traces)].model_dump()}))
            records.append(detection_record(gateway, node_id, local_id, local_id, state="ok"))
        batch = IngestBatch(gateway_id=gateway, site=site.name, batch_id=uuid.uuid4(), records=records)
        out.append((site.key, gzip.compress(batch.model_dump_json().encode(), compresslevel=1), MEASUREMENTS_PER_BATCH))
    return out


async def run_load(base: str, viewer: str, batches: list[tuple[str, bytes, int]], senders: int,
                   duration_s: float) -> dict[str, float]:
    stored = sent_bytes = busy = 0
    query_ms: list[float] = []
    deadline = time.monotonic() + duration_s
    queue = list(reversed(batches))

    async def sender(client: httpx.AsyncClient) -> None:
        nonlocal stored, sent_bytes, busy
        while queue and time.monotonic() < deadline:
            key, body, measurements = queue.pop()
            answer = await client.post(INGEST_PATH, content=body, headers={
                "Authorization": f"Bearer {key}", "Content-Encoding": "gzip", "Content-Type": "application/json"})
            if answer.status_code == 429:
                busy += 1
                queue.append((key, body, measurements))
                await asyncio.sleep(float(answer.headers.get("retry-after", "1")) / 10)
                continue
            answer.raise_for_status()
            stored += answer.json()["accepted"] // 2  # a measurement and its detection
            sent_bytes += len(body)

    async def asker(client: httpx.AsyncClient) -> None:
        paths = ["/api/v1/fleet/sites", "/api/v1/fleet/nodes?state=damage&limit=100", "/api/v1/fleet/nodes?limit=100"]
        i = 0
        while time.monotonic() < deadline:
            started = time.perf_counter()
            answer = await client.get(paths[i % len(paths)], headers={"Authorization": f"Bearer {viewer}"})
            answer.raise_for_status()
            query_ms.append((time.perf_counter() - started) * 1000)
            i += 1

    limits = httpx.Limits(max_connections=senders + 2)
    async with httpx.AsyncClient(base_url=base, timeout=120, limits=limits) as client:
        started = time.monotonic()
        await asyncio.gather(*(sender(client) for _ in range(senders)), asker(client))
        elapsed = time.monotonic() - started
    if not queue:
        print("  warning: every prepared batch was sent before the time ran out: raise --batches", flush=True)
    return {"elapsed_s": elapsed, "stored": stored, "rate": stored / elapsed, "mb_s": sent_bytes / elapsed / 1e6,
            "busy": busy, "queries": len(query_ms), "p50": statistics.median(query_ms) if query_ms else float("nan"),
            "p99": percentile(query_ms, 0.99) if query_ms else float("nan"),
            "max": max(query_ms) if query_ms else float("nan")}


def central(args: argparse.Namespace) -> None:
    print(f"central site: {SITES * GATEWAYS_PER_SITE * NODES_PER_GATEWAY} nodes, batches of "
          f"{MEASUREMENTS_PER_BATCH} measurements ({N_CHANNELS} x {N_SAMPLES} codes with traces) and their "
          f"detections, {args.senders} senders, {args.duration_s:g} s per run, {os.cpu_count()} CPUs", flush=True)
    for workers in args.workers:
        name = f"bench_fleet_{uuid.uuid4().hex[:12]}"
        url, sites, viewer = prepare_database(name)
        log_dir = Path(tempfile.mkdtemp(prefix="bench-fleet-"))
        port = free_port()
        server = Proc([str(BIN / "pipesentry"), "api", "--workers", str(workers), "--database-url", url, "--port",
                       str(port), "--log-level", "warning"], log_dir, "api")
        base = f"http://127.0.0.1:{port}"
        try:
            def ready(server: Proc = server, base: str = base) -> bool:
                assert server.alive(), server.stderr[-2000:]
                return httpx.get(f"{base}/readyz", timeout=2).status_code == 200

            wait_until(ready, 120, 0.2, what="the API")
            seed_nodes(base, sites)
            batches = ready_batches(sites, args.batches)
            result = asyncio.run(run_load(base, viewer, batches, args.senders, args.duration_s))
            print(f"workers={workers}: {result['rate']:.0f} measurements/s with traces "
                  f"({result['stored']} in {result['elapsed_s']:.1f} s, {result['mb_s']:.1f} MB/s of gzip bodies, "
                  f"{result['busy']} answered 429); fleet queries meanwhile: {result['queries']}, "
                  f"p50 {result['p50']:.1f} ms, p99 {result['p99']:.1f} ms, max {result['max']:.1f} ms", flush=True)
        finally:
            server.terminate()
            with contextlib.suppress(ProcessLookupError):
                os.killpg(server.popen.pid, signal.SIGKILL)  # its workers, if it left any
            server.close()
            drop_database(name)


# The catch-up part: one gateway's queue after an outage, drained by the gateway's own sender.
CATCH_UP_GRID = MapGrid(axial_start_mm=0.0, axial_step_mm=10.0, axial_count=100, angle_start_deg=0.0,
                        angle_step_deg=5.0, angle_count=72)
CATCH_UP_GEOMETRY = NodeGeometry(rx_angles_deg=[i * 22.5 for i in range(16)], tx_angles_deg=[0.0, 90.0, 180.0, 270.0],
                                 tx_rx_distance_mm=600.0, circumference_mm=1000.0)
OUTAGE_START = datetime(2026, 12, 1, 0, 0, tzinfo=UTC)
SCENARIO = ROOT / "examples" / "scenarios" / "paper_notch.toml"


def node_traces(count: int) -> list[np.ndarray]:
    """Records of the mock node's physics (the paper's pipe, 16 x 6000 int16): ~76 kB each stored."""
    scenario = load_scenario(SCENARIO).nodes[0].model_copy(update={"defects": []})
    rng = np.random.default_rng(1)
    return [acquire(scenario, 60.0 * k, rng).codes for k in range(count)]


def smooth_map(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axial, angle = np.meshgrid(np.arange(100), np.arange(72), indexing="ij")
    bump = np.exp(-((axial - rng.uniform(0, 100)) ** 2 + (angle - rng.uniform(0, 72)) ** 2) / 50.0)
    return (0.05 * bump + rng.normal(0, 0.002, bump.shape)).astype(np.float32)


def fill_outage(url: str, nodes: int, minutes: int) -> int:
    """The queue an outage leaves: per minute, one monitor cycle of every node (the gateway's order)."""
    db = open_database(url)
    db.queue_uplink(QueuePolicy("everything"))
    samples = node_traces(8)
    maps = [smooth_map(seed) for seed in range(8)]
    names = [f"site-node-{n:03d}" for n in range(nodes)]
    with db.write() as session:
        for name in names:
            upsert_node(session, NodeInfo(name, f"socket://10.0.0.{len(name)}:4001", "1.2.0", 2, 16, 10e6, CATCH_UP_GEOMETRY),
                        seen_at=OUTAGE_START)
    stored = 0
    for minute in range(minutes):
        with db.write() as session:
            for n, name in enumerate(names):
                k = (minute + n) % 8
                acquisition = AcquisitionInput(acquired_at=OUTAGE_START + timedelta(minutes=minute), node_measurement_id=minute,
                                               codes=samples[k], volts_per_code=1 / 32768, fs_hz=10e6, t0_s=0.0,
                                               averaging=10, excitation_hz=85e3, cycles=5, temperature_c=21.0)
                record = CycleRecord(
                    acquisition, MeasurementKind.MONITOR, {"cycles": minute},
                    di_maps=[DiMapInput(MapSource.GATEWAY, "multipath", CATCH_UP_GRID, maps[k], None)],
                    detection=DetectionInput(peak_di=float(maps[k].max()), threshold=0.2, state=NodeState.COMMISSIONING),
                )
                store_cycle(session, name, record)
                stored += 1
    db.dispose()
    return stored


class TimedSender(UplinkSender):
    """The gateway's sender, timing the centre's part (the POST) apart from its own."""

    post_s = 0.0
    body_bytes = 0

    def _post(self, batch: Batch) -> Outcome:
        self.body_bytes += len(batch.body)
        started = time.perf_counter()
        outcome = super()._post(batch)
        self.post_s += time.perf_counter() - started
        if outcome.kind != "stored":
            print(f"    a batch was not stored: {outcome.detail}", file=sys.stderr)
        return outcome


def catch_up_run(nodes: int, minutes: int, workdir: Path) -> None:
    name = f"bench_fleet_{uuid.uuid4().hex[:10]}"
    central = f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
    admin = psycopg.connect(PG_ADMIN, autocommit=True)
    admin.execute(f'CREATE DATABASE "{name}"')
    api = None
    try:
        open_database(central).dispose()
        from db.api_keys import create_api_key

        db = open_database(central, upgrade=False)
        with db.write() as session:
            _row, key = create_api_key(session, name="bench gateway", role=Role("gateway"), site="bench")
        db.dispose()
        port = free_port()
        log = (workdir / "api.log").open("wb")
        api = subprocess.Popen([sys.executable, "-m", "pipesentry", "api", "--database-url", central, "--host",
                                "127.0.0.1", "--port", str(port), "--log-level", "warning"], stdout=log, stderr=log)
        for _ in range(300):
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        else:
            raise SystemExit(f"the central service did not start; see {workdir / 'api.log'}")

        edge = f"sqlite:///{workdir / 'edge.db'}"
        started = time.perf_counter()
        measurements = fill_outage(edge, nodes, minutes)
        fill_s = time.perf_counter() - started
        db = open_database(edge, upgrade=False)
        with db.session() as session:
            records = queue_stats(session).depth
        print(f"  queue after a {minutes} min outage of {nodes} nodes at a 60 s cadence: {measurements} measurements "
              f"with traces, {records} records (written in {fill_s:.0f} s)")
        settings = UplinkSettings(url=f"http://127.0.0.1:{port}", key=key, gateway_id="gw-bench", site="bench")
        sender = TimedSender(settings, db, stop=threading.Event())
        cpu0, wall0 = time.process_time(), time.perf_counter()
        batches = 0
        while True:
            with db.session() as session:
                if queue_stats(session).depth == 0:
                    break
            sender.run_once()
            batches += 1
        wall = time.perf_counter() - wall0
        edge_cpu = time.process_time() - cpu0
        sender.client.close()
        db.dispose()
        print(f"  drained in {wall:.1f} s: {batches} batches of up to {settings.batch_records} records, "
              f"{records / wall:.0f} records/s, {measurements / wall:.1f} measurements/s, "
              f"{sender.body_bytes / wall / 1e6:.1f} MB/s of JSON before gzip")
        print(f"  time in the centre's answer (POST): {sender.post_s:.1f} s ({100 * sender.post_s / wall:.0f} %); "
              f"the edge's own CPU (read, encode, gzip): {edge_cpu:.1f} s")
        live = nodes / 60.0  # measurements/s the nodes keep adding while the backlog drains
        drain = measurements / wall
        behind = f"{wall / (1 - live / drain):.0f} s" if drain > live else "never (the link is slower than the nodes)"
        print(f"  catch-up of the {minutes} min outage: {wall:.0f} s for the backlog alone; caught up with the "
              f"{live:.2f} live measurements/s the nodes keep adding: {behind}")
    finally:
        if api is not None:
            api.terminate()
            api.wait(30)
        admin.execute(f'DROP DATABASE "{name}" WITH (FORCE)')
        admin.close()


def catch_up(args: argparse.Namespace) -> None:
    print(f"uplink catch-up: one gateway's queue after a {args.outage_min} min outage of {args.nodes} nodes, drained "
          "by its sender into the central service (1 worker, PostgreSQL)", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        catch_up_run(args.nodes, args.outage_min, Path(tmp))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("part", nargs="?", default="all", choices=["all", "central", "catch-up"],
                        help="central: ingest rate with 1 and 4 workers, fleet-query p99 meanwhile; catch-up: the "
                        "uplink's drain after an outage; all (the default): both")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--duration-s", type=float, default=20.0)
    parser.add_argument("--senders", type=int, default=8)
    parser.add_argument("--batches", type=int, default=300, help="batches prepared before each run")
    parser.add_argument("--nodes", type=int, default=100, help="catch-up: simulated nodes behind the gateway")
    parser.add_argument("--outage-min", type=int, default=60, help="catch-up: outage in minutes (60 s cadence)")
    args = parser.parse_args()
    if args.part in ("all", "central"):
        central(args)
    if args.part in ("all", "catch-up"):
        catch_up(args)


if __name__ == "__main__":
    main()
