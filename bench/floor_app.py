"""The benchmark's floor: the service's web layer without the filter.

A minimal FastAPI app with the same routes the load test uses, parsing the same request schemas
as the service (imported from ``edgepos.api.schemas``: strict types, the measurement union, bounds)
and answering every batch with fixed fixes of the same shape and size (one per epoch, each listing
its measurements), written to JSON by the service's own code (``edgepos.api.convert``). Comparing
the service's epochs/s with this app's shows what the filter costs beside the HTTP, validation and
JSON work every request pays anyway. It keeps no state, so seq
and tokens are not checked.

Run: ``python bench/floor_app.py --port 8001`` (loopback only).
"""

from __future__ import annotations

import argparse
import secrets
import time
from pathlib import Path

import uvicorn
from edgepos.api.convert import fix_to_json, joined_batch_body, to_json
from edgepos.api.measurement_schemas import BatchIn
from edgepos.api.schemas import Health, Ready, RsuBulk, SessionCreate, SessionCreated, Upserted
from edgepos.pipelines.base import Fix, MeasurementUse
from fastapi import FastAPI, Response

_COVARIANCE = [[0.04, 0.0], [0.0, 0.04]]
_PROBABILITIES = {"ca": 0.4, "at": 0.3, "singer": 0.3}


def _fixed_fix(t: float, uses: list[MeasurementUse]) -> Fix:
    return Fix(
        t=t,
        status="tracking",
        x=10.0,
        y=0.0,
        vx=10.0,
        vy=0.0,
        speed=10.0,
        heading=0.0,
        yaw_rate=0.0,
        position_cov=_COVARIANCE,
        model_probabilities=_PROBABILITIES,
        nis=2.0,
        nis_dof=len(uses) * 2,
        measurements=uses,
    )


def create_app() -> FastAPI:
    app = FastAPI(title="edgepos floor", docs_url=None, redoc_url=None, openapi_url=None)

    @app.get("/healthz")
    async def healthz() -> Health:
        return Health(status="ok")

    @app.get("/readyz")
    async def readyz() -> Ready:
        return Ready(status="ready")

    @app.put("/v1/rsus")
    async def put_rsus(body: RsuBulk) -> Upserted:
        return Upserted(upserted=len(body.rsus))

    @app.post("/v1/sessions", status_code=201)
    async def create_session(body: SessionCreate) -> SessionCreated:
        session_id = secrets.token_hex(16)
        return SessionCreated(
            session_id=session_id,
            token=f"{session_id}.{secrets.token_urlsafe(32)}",
            vehicle_id=body.vehicle_id,
            pipeline=body.pipeline,
            options={},
            created_at=time.time(),
        )

    @app.delete("/v1/sessions/{session_id}", status_code=204)
    async def delete_session(session_id: str) -> Response:
        return Response(status_code=204)

    @app.post("/v1/sessions/{session_id}/batches")
    async def post_batch(session_id: str, body: BatchIn) -> Response:
        epochs: dict[float, list[MeasurementUse]] = {}
        for index, measurement in enumerate(body.measurements):
            epochs.setdefault(measurement.t, []).append(MeasurementUse(index, measurement.type, True))
        fixes = [
            fix_to_json(_fixed_fix(t, uses), body.include_state, None) for t, uses in sorted(epochs.items())
        ]
        body_bytes = joined_batch_body(body.seq, [to_json(fix) for fix in fixes])  # as the service writes it
        return Response(body_bytes, media_type="application/json")

    return app


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()
    uvicorn.run(
        "floor_app:create_app",
        factory=True,
        host="127.0.0.1",
        port=args.port,
        workers=args.workers,
        log_level="warning",
        access_log=False,
        app_dir=str(Path(__file__).parent),
    )


if __name__ == "__main__":
    main()
