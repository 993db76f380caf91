"""Benchmark and check: the reference-station resource on the real recording of tests/data/gnss-rover.

In-process app, memory store: load the navigation file, register MARE (its header's marker and antenna
delta), upload base-0-5min.rnx (timed: parse + corrections + store), then run gnss_tight over the rover's
epochs in one-epoch batches without and with ``base_station`` (timed per batch). Prints the horizontal
RMS / p95 scored as ``edgepos eval gnss-rinex`` scores them, beside that command's own figures with and
without ``--base`` on the same epochs and options: the two must agree.

    python bench/base_station_api.py [--epochs N] [--filter ukf|upf]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time
from pathlib import Path

from edgepos.api.app import create_app
from edgepos.api.base_stations import batch_corrections
from edgepos.api.measurement_schemas import PseudorangeMeasurement
from edgepos.api.settings import Settings
from edgepos.eval.gnss_rinex import _score, evaluate
from edgepos.gnss.geodesy import geodetic_to_ecef
from edgepos.gnss.spp import read_reference
from fastapi.testclient import TestClient
from gnss_api import load_epochs

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "gnss-rover"
KEY = "bench-admin-key-0123456789abcdef"
ADMIN = {"Authorization": f"Bearer {KEY}"}
TEXT = {**ADMIN, "Content-Type": "text/plain"}
MARE = {
    "station_id": "MARE",
    "position_ecef": [4777633.8950, 203108.9850, 4206595.1490],
    "antenna_delta": {"up": 0.0770, "east": 0.0, "north": 0.0},
}


def run(
    client: TestClient, vehicle: str, options: dict, batches: list[list[dict]]
) -> tuple[list[dict], list[float]]:
    created = client.post(
        "/v1/sessions",
        json={"vehicle_id": vehicle, "pipeline": "gnss_tight", "options": options},
        headers=ADMIN,
    )
    created.raise_for_status()
    session = created.json()
    token = {"Authorization": f"Bearer {session['token']}"}
    fixes, seconds = [], []
    for seq, items in enumerate(batches, start=1):
        started = time.perf_counter()
        response = client.post(
            f"/v1/sessions/{session['session_id']}/batches",
            json={"seq": seq, "measurements": items},
            headers=token,
        )
        seconds.append(time.perf_counter() - started)
        response.raise_for_status()
        fixes.extend(response.json()["fixes"])
    return fixes, seconds


def lookup_ms(client: TestClient, repeats: int = 200) -> float:
    """The web layer's per-batch cost of corrections alone: ``batch_corrections`` for epoch 150's pseudoranges."""
    context = client.app.state.context
    loaded = asyncio.run(context.ephemerides.current(context.store, lambda fn, *a: _now(fn(*a))))
    observations = [PseudorangeMeasurement(**m).to_observation() for m in load_epochs(151, "GC")[150]]
    options = {"base_station": "MARE", "max_correction_age_s": 30.0}

    async def repeat() -> float:
        started = time.perf_counter()
        for _ in range(repeats):
            await batch_corrections(
                context.store, context.base_epochs, options, observations, loaded.ephemerides, None, None
            )
        return (time.perf_counter() - started) / repeats * 1e3

    return asyncio.run(repeat())


async def _now(value):
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=300)
    parser.add_argument("--filter", default="ukf", choices=("ukf", "upf"))
    args = parser.parse_args()
    options = {"filter": args.filter, "seed": 1, "systems": ["G", "C"], "use_doppler": False}
    batches = load_epochs(args.epochs, "GC")
    client = TestClient(
        create_app(Settings(admin_key=KEY, admin_key_file=Path("/nonexistent/never.key"), rate_limit_per_s=0))
    )
    with client:
        client.put(
            "/v1/ephemerides", content=(DATA / "broadcast-nav.rnx").read_text(), headers=TEXT
        ).raise_for_status()
        client.post("/v1/base-stations", json=MARE, headers=ADMIN).raise_for_status()
        started = time.perf_counter()
        upload = client.post(
            "/v1/base-stations/MARE/observations",
            content=(DATA / "base-0-5min.rnx").read_bytes(),
            headers=TEXT,
        )
        upload_s = time.perf_counter() - started
        upload.raise_for_status()
        plain, plain_s = run(client, "plain", options, batches)
        based, based_s = run(client, "based", {**options, "base_station": "MARE"}, batches)
    info = upload.json()
    print(
        f"upload of base-0-5min.rnx (2.0 MB, {info['epochs_read']} epochs): {upload_s:.2f} s, "
        f"{info['epochs_stored']} epochs / {info['corrections']} corrections stored"
    )
    reference = read_reference(str(DATA / "reference-0-5min.csv"))
    times = [items[0]["t"] for items in batches]
    gps_week_s = float(reference[0][0] // 604800.0) * 604800.0  # the recording's week, from the reference

    def score(fixes: list[dict]) -> dict:
        ecef = [geodetic_to_ecef(f["latitude"], f["longitude"], f["height"]) for f in fixes]
        return _score([gps_week_s + t for t in times], ecef, reference, len(times))

    applied = [u["correction_applied"] for f in based for u in f["measurements"]]
    for label, fixes, seconds in (("API", plain, plain_s), ("API + base_station", based, based_s)):
        s = score(fixes)
        print(
            f"{label:22s} horizontal RMS {s['horizontal_rms_m']:.3f} m, p95 {s['horizontal_p95_m']:.3f} m; "
            f"batch median {statistics.median(seconds) * 1e3:.2f} ms"
        )
    print(f"pseudoranges corrected: {sum(applied)} of {len(applied)}")
    print(
        f"correction read + table per one-epoch batch (memory store, warm cache): {lookup_ms(client):.3f} ms"
    )
    obs, nav, ref = (str(DATA / n) for n in ("rover-0-5min.rnx", "broadcast-nav.rnx", "reference-0-5min.csv"))
    for label, base in (("eval gnss-rinex", None), ("eval gnss-rinex --base", str(DATA / "base-0-5min.rnx"))):
        s = evaluate(obs, nav, ref, "GC", options, args.epochs, base_path=base)
        print(f"{label:22s} horizontal RMS {s['horizontal_rms_m']:.3f} m, p95 {s['horizontal_p95_m']:.3f} m")


if __name__ == "__main__":
    main()
