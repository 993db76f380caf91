"""Benchmark: what the service adds to a gnss_tight epoch (real recording; GPS + BeiDou: 15 pseudoranges,
``--systems GCE`` adds Galileo: 22).

For each filter, one-epoch batches of tests/data/gnss-rover are sent through the app in-process
(``POST /v1/sessions/{id}/batches``: JSON validation, the satellite check, the ephemerides digest read
and the cached parsed file, the store's compare-and-set) and, interleaved epoch by epoch on the same
data, straight into ``GnssTightPipeline.process``; the difference is the service's share. Also the
time to parse the navigation file, which a worker pays once per uploaded file. Stores: memory, and
Redis when redis-server is installed (one extra HGET per batch for the digest).

    python bench/gnss_api.py [--epochs N] [--filters ukf,upf] [--systems GC|GCE]
"""

from __future__ import annotations

import argparse
import math
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from edgepos.api.app import create_app
from edgepos.api.ephemerides import parse, satellite_problems
from edgepos.api.settings import Settings
from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_nav import parse_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.loadgen.localredis import RedisServer
from edgepos.pipelines.base import StaticEnvironment
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from fastapi.testclient import TestClient

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "gnss-rover"
KEY = "bench-admin-key-0123456789abcdef"
ADMIN = {"Authorization": f"Bearer {KEY}"}


def load_epochs(count: int, systems: str = "GC") -> list[list[dict]]:
    codes = {system: DEFAULT_CODES[system] for system in systems}
    out = []
    for number, epoch in enumerate(read_epochs(str(DATA / "rover-0-5min.rnx"), codes)):
        if number >= count:
            break
        out.append(
            [
                {
                    "type": "pseudorange",
                    "t": epoch.gpst % 604800.0,
                    "system": system,
                    "prn": int(prn),
                    "pseudorange_m": float(pr),
                    "cn0_dbhz": float(cn0) if math.isfinite(cn0) else 0.0,
                }
                for system, prn, pr, cn0 in zip(
                    epoch.systems, epoch.prns, epoch.pseudorange_m, epoch.cn0_dbhz
                )
                if math.isfinite(pr) and 1.0e6 <= pr <= 1.0e8
            ]
        )
    return out


def observations(items: list[dict]) -> list[PseudorangeObservation]:
    return [
        PseudorangeObservation(m["t"], m["system"], m["prn"], m["pseudorange_m"], m["cn0_dbhz"])
        for m in items
    ]


def run(
    store: str, options: dict, epochs: list[list[dict]], text: str, workdir: Path
) -> tuple[float, float, float]:
    """Median ms per epoch: (through the API, straight into the pipeline), and of GET /healthz through the
    same in-process client (the floor of any request: the test client's thread hop and the middleware)."""
    settings = Settings(admin_key=KEY, admin_key_file=workdir / "admin.key", store=store, rate_limit_per_s=0)
    pipeline = GnssTightPipeline()
    navigation = Ephemerides.from_navigation(parse_navigation(text.splitlines()))
    environment = StaticEnvironment(navigation=navigation)
    state = pipeline.create(pipeline.resolve_options(options), None)
    api_ms: list[float] = []
    direct_ms: list[float] = []
    floor_ms: list[float] = []
    with TestClient(create_app(settings)) as client:
        headers = {**ADMIN, "Content-Type": "text/plain"}
        assert client.put("/v1/ephemerides", content=text, headers=headers).is_success
        body = {"vehicle_id": "bench", "pipeline": "gnss_tight", "options": options}
        created = client.post("/v1/sessions", json=body, headers=ADMIN).json()
        session_id, token = created["session_id"], {"Authorization": f"Bearer {created['token']}"}
        for seq, items in enumerate(epochs, start=1):
            started = time.perf_counter()
            response = client.post(
                f"/v1/sessions/{session_id}/batches", json={"seq": seq, "measurements": items}, headers=token
            )
            api_ms.append(1e3 * (time.perf_counter() - started))
            assert response.status_code == 200, response.text
            batch = observations(items)
            started = time.perf_counter()
            _, state = pipeline.process(state, batch, environment)
            direct_ms.append(1e3 * (time.perf_counter() - started))
            started = time.perf_counter()
            assert client.get("/healthz").status_code == 200
            floor_ms.append(1e3 * (time.perf_counter() - started))
    skip = min(3, len(epochs) - 1)  # the first epochs initialise (least squares), not representative
    return statistics.median(api_ms[skip:]), statistics.median(direct_ms[skip:]), statistics.median(floor_ms)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--filters", default="ukf,upf")
    parser.add_argument("--systems", default="GC", help="constellations (GCE adds Galileo: 22 pseudoranges)")
    args = parser.parse_args()
    text = (DATA / "broadcast-nav.rnx").read_text(encoding="ascii")
    epochs = load_epochs(args.epochs, args.systems)
    print(
        f"python {platform.python_version()} on {platform.machine()}; {len(epochs)} epochs of "
        f"{statistics.median(len(e) for e in epochs):.0f} pseudoranges"
    )

    parses = []
    for _ in range(20):
        started = time.perf_counter()
        Ephemerides.from_navigation(parse_navigation(text.splitlines()))
        parses.append(1e3 * (time.perf_counter() - started))
    print(
        f"parse the navigation file ({len(text.encode())} bytes), once per worker and file: "
        f"{statistics.median(parses):.1f} ms median"
    )
    loaded = parse(text, "bench", 0.0)
    first = observations(epochs[0])
    checks = []
    for _ in range(2000):
        started = time.perf_counter()
        assert not satellite_problems(first, loaded, list(args.systems))
        checks.append(1e6 * (time.perf_counter() - started))
    print(
        f"per batch: the check that each of {len(first)} pseudoranges has a satellite state: "
        f"{statistics.median(checks):.0f} us median"
    )

    print(
        f"{'store':<8} {'filter':<10} {'API ms/epoch':>13} {'pipeline ms':>12} {'service share ms':>17} "
        f"{'GET /healthz ms':>16}"
    )
    with tempfile.TemporaryDirectory() as directory:
        workdir = Path(directory)
        stores = {"memory": "memory"}
        redis = None
        binary = shutil.which("redis-server")
        if binary is not None:
            redis = RedisServer(binary, workdir / "redis", "--save", "", "--appendonly", "no")
            redis.start()
            stores["redis"] = redis.url("bench:")
        try:
            for name, url in stores.items():
                for filter_name in args.filters.split(","):
                    options = {"filter": filter_name, "seed": 1, "systems": list(args.systems)}
                    label = filter_name if filter_name == "ukf" else f"{filter_name} 200"
                    api, direct, floor = run(url, options, epochs, text, workdir)
                    print(
                        f"{name:<8} {label:<10} {api:>13.2f} {direct:>12.2f} {api - direct:>17.2f} "
                        f"{floor:>16.2f}"
                    )
        finally:
            if redis is not None:
                redis.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
