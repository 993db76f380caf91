"""Heavy vehicles beside light ones on a real server: nobody's batch is lost, refused or wrong.

Two ``gnss_tight`` vehicles (UPF, real pseudoranges) send the heaviest batches the server admits back
to back while three ``rsu_imu`` vehicles stream theirs. Every light batch must be answered 200 with
the fix the in-process pipeline computes from the same measurements (bit for bit), every heavy batch
200 or, when the server's cost model says it is over the budget, a 422 that names the budget; and the
heavy batches must have run in the heavy lane (worker processes) and the light ones on the filter
thread, as the scheduler's metrics show. How fast the light vehicles were served is the fairness
benchmark's question (bench/fairness.py), not this test's: nothing here depends on timing.
"""

from __future__ import annotations

import asyncio
import json
import re
import sys
from pathlib import Path

import httpx
import pytest
from edgepos.api.convert import fix_to_json
from edgepos.api.measurement_schemas import BatchIn
from edgepos.api.schemas import FixOut
from edgepos.api.settings import Settings
from edgepos.loadgen import common
from edgepos.pipelines import cost
from edgepos.pipelines.base import InitialState, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from faulthelp import ADMIN_KEY, scenario, serve, start_state, stream_batches

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "api"))
from gnsswire import QUICK, measurements, nav_text

pytestmark = pytest.mark.slow
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
LIGHT_VEHICLES = 3
LIGHT_BATCHES = 40
HEAVY_OPTIONS = {**QUICK, "filter": "upf", "particles": 200}
SLICE_S = Settings.model_fields["scheduler_slice_ms"].default / 1000.0


def _light_reference(stream: int) -> list[list[dict]]:
    """The wire fixes the pipeline gives stream ``stream``'s one-epoch batches, in process."""
    pipeline = get_pipeline("rsu_imu")
    environment = StaticEnvironment({rsu.id: rsu for rsu in scenario().rsus})
    state = pipeline.create(pipeline.resolve_options({}), InitialState(**start_state().model_dump()))
    out = []
    for epoch in common.vehicle_epochs(scenario(), 0, stream)[:LIGHT_BATCHES]:
        fixes, state = pipeline.process(state, list(epoch), environment)
        out.append(
            [
                json.loads(FixOut.model_validate(fix_to_json(fix, False, None)).model_dump_json())
                for fix in fixes
            ]
        )
    return out


def _predicted_heavy_batch_s() -> float:
    """What the server's cost model predicts for one of the heavy vehicles' batches."""
    batch = BatchIn.model_validate({"seq": 1, "measurements": measurements(0, 3)})
    return cost.batch_cost_s("gnss_tight", HEAVY_OPTIONS, [m.to_observation() for m in batch.measurements])


async def _light(url: str, stream: int, answers: list[tuple[int, list[dict]]]) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=120.0) as client:
        body = {"vehicle_id": f"light-{stream}", "initial_state": start_state().model_dump(mode="json")}
        created = (await client.post("/v1/sessions", json=body, headers=ADMIN)).json()
        token = {"Authorization": f"Bearer {created['token']}"}
        for seq, batch in enumerate(stream_batches(stream, 1)[:LIGHT_BATCHES], start=1):
            items = [item.model_dump(mode="json", exclude_none=True) for item in batch]
            response = await client.post(
                f"/v1/sessions/{created['session_id']}/batches",
                json={"seq": seq, "measurements": items},
                headers=token,
            )
            answers.append((response.status_code, response.json().get("fixes", [])))


async def _heavy(url: str, index: int, statuses: list[tuple[int, str]]) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=120.0) as client:
        body = {"vehicle_id": f"heavy-{index}", "pipeline": "gnss_tight", "options": HEAVY_OPTIONS}
        created = (await client.post("/v1/sessions", json=body, headers=ADMIN)).json()
        token = {"Authorization": f"Bearer {created['token']}"}
        seq, first = 1, 0
        while first < 9:  # three batches, sent while the light vehicles stream theirs
            response = await client.post(
                f"/v1/sessions/{created['session_id']}/batches",
                json={"seq": seq, "measurements": measurements(first, 3)},
                headers=token,
            )
            statuses.append((response.status_code, response.text))
            if response.status_code == 200:
                seq, first = seq + 1, first + 3
            else:
                break


def test_heavy_vehicles_do_not_cost_light_ones_a_batch(tmp_path):
    references = [_light_reference(stream) for stream in range(LIGHT_VEHICLES)]

    async def scenario_run(url: str) -> tuple[list[list[tuple[int, list[dict]]]], list[tuple[int, str]]]:
        async with httpx.AsyncClient(base_url=url, timeout=60.0) as client:
            uploaded = await client.put(
                "/v1/ephemerides", content=nav_text(), headers={**ADMIN, "Content-Type": "text/plain"}
            )
            assert uploaded.status_code == 200, uploaded.text
        light_answers: list[list[tuple[int, list[dict]]]] = [[] for _ in range(LIGHT_VEHICLES)]
        heavy_statuses: list[tuple[int, str]] = []
        await asyncio.gather(
            *(_heavy(url, index, heavy_statuses) for index in range(2)),
            *(_light(url, stream, light_answers[stream]) for stream in range(LIGHT_VEHICLES)),
        )
        return light_answers, heavy_statuses

    with serve(tmp_path, 1, EDGEPOS_RATE_LIMIT_PER_S="0", EDGEPOS_DEMO_RSUS="true") as server:
        light_answers, heavy_statuses = asyncio.run(scenario_run(server.url))
        metrics = httpx.get(f"{server.url}/metrics").text

    for stream, answers in enumerate(light_answers):
        assert [status for status, _ in answers] == [200] * LIGHT_BATCHES, answers[:3]
        assert [fixes for _, fixes in answers] == references[stream]
    assert heavy_statuses, "no heavy batch was sent"
    for status, text in heavy_statuses:
        assert status == 200 or (status == 422 and "EDGEPOS_BATCH_CPU_BUDGET_MS" in text), (status, text)
    lanes = dict(re.findall(r'edgepos_scheduler_wait_seconds_count\{lane="(\w+)"\} ([0-9.]+)', metrics))
    assert float(lanes.get("light", 0)) >= LIGHT_VEHICLES * LIGHT_BATCHES
    applied = sum(status == 200 for status, _ in heavy_statuses)
    if _predicted_heavy_batch_s() > SLICE_S:  # they are heavy by the server's own reckoning
        assert float(lanes.get("heavy", 0)) >= applied >= 1, metrics
