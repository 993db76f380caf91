"""Admission control: a worker works on at most EDGEPOS_MAX_INFLIGHT requests at once; the rest
wait in line and are answered 503 with Retry-After only after EDGEPOS_QUEUE_TIMEOUT_S; probes skip
the line."""

from __future__ import annotations

import asyncio
import json

import httpx
import pytest
from edgepos.api.metrics import Metrics
from edgepos.api.middleware import Admission, AdmissionMiddleware
from edgepos.api.settings import Settings


class Gate:
    """An ASGI app whose requests to /slow hold until ``release`` is set; it counts how many run."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.running = 0
        self.most_running = 0

    async def __call__(self, scope, receive, send) -> None:
        self.running += 1
        self.most_running = max(self.most_running, self.running)
        try:
            if scope["path"] == "/slow":
                await self.release.wait()
            await send({"type": "http.response.start", "status": 200, "headers": []})
            await send({"type": "http.response.body", "body": b"ok"})
        finally:
            self.running -= 1


async def until(condition, timeout_s: float = 10.0) -> None:
    """Yield to the loop until ``condition()`` holds: a fixed sleep is outrun on a busy machine."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not condition():
        assert asyncio.get_running_loop().time() < deadline, "condition not reached"
        await asyncio.sleep(0.005)


def client_for(app) -> httpx.AsyncClient:
    return httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://edge")


def test_requests_beyond_the_slots_wait_then_all_succeed():
    async def scenario() -> tuple[list[int], int]:
        gate = Gate()
        metrics = Metrics()
        app = AdmissionMiddleware(gate, Admission(max_inflight=2, queue_timeout_s=10.0, metrics=metrics))
        async with client_for(app) as client:
            pending = [asyncio.create_task(client.get("/slow")) for _ in range(6)]
            await until(lambda: metrics.waiting._value.get() == 4)
            await asyncio.sleep(0.05)  # nothing more gets in while the slots are held
            assert gate.running == 2
            assert metrics.waiting._value.get() == 4
            gate.release.set()
            responses = await asyncio.gather(*pending)
        return [r.status_code for r in responses], gate.most_running

    statuses, most_running = asyncio.run(scenario())
    assert statuses == [200] * 6
    assert most_running == 2


def test_a_request_that_waits_too_long_gets_503_with_retry_after_and_probes_skip_the_line():
    async def scenario() -> tuple[httpx.Response, httpx.Response, httpx.Response]:
        gate = Gate()
        app = AdmissionMiddleware(gate, Admission(max_inflight=1, queue_timeout_s=0.1, metrics=Metrics()))
        async with client_for(app) as client:
            holder = asyncio.create_task(client.get("/slow"))
            await until(lambda: gate.running == 1)
            refused = await client.get("/v1/sessions/x")
            probe = await client.get("/readyz")
            gate.release.set()
            await holder
            after = await client.get("/v1/sessions/x")
        return refused, probe, after

    refused, probe, after = asyncio.run(scenario())
    assert refused.status_code == 503
    assert int(refused.headers["retry-after"]) >= 1
    body = json.loads(refused.content)
    assert body["error"]["code"] == "unavailable"
    assert "EDGEPOS_QUEUE_TIMEOUT_S" in body["error"]["message"]
    assert probe.status_code == 200
    assert after.status_code == 200


@pytest.mark.parametrize(
    "field,value", [("max_inflight", 0), ("queue_timeout_s", 0), ("queue_timeout_s", "nan")]
)
def test_admission_settings_are_bounded(field: str, value: object):
    with pytest.raises(ValueError, match=field):
        Settings(**{field: value})


def test_the_batch_admission_agrees_with_the_cost_model_function_by_function():
    """``cost.admit`` (one pass, each epoch shape weighed once) gives exactly what it gave as
    ``batch_cost_from_counts_s`` over ``epoch_counts`` and ``epoch_bound_violations`` (and
    ``batch_cost_s`` up to the order of its sum) on batches mixing kinds, their order within an epoch, epochs out of
    time order, Dopplers on some pseudoranges only, and epochs over their bounds."""
    import random

    from edgepos.core.observations import (
        GnssFixObservation,
        GyroObservation,
        OdometerObservation,
        PseudorangeObservation,
        RissObservation,
        RsuObservation,
        RsuRangeObservation,
        V2vRangeObservation,
    )
    from edgepos.pipelines import cost
    from edgepos.pipelines.registry import get_pipeline

    makers = {
        "rsu": lambda t: RsuObservation(t, "r1", 10.0, 0.1),
        "rsu_range": lambda t: RsuRangeObservation(t, "r1", 10.0),
        "gyro": lambda t: GyroObservation(t, 0.0),
        "gnss_fix": lambda t: GnssFixObservation(t, 1.0, 2.0),
        "odometer": lambda t: OdometerObservation(t, speed=3.0),
        "v2v_range": lambda t: V2vRangeObservation(t, "v2", 5.0),
        "riss": lambda t: RissObservation(t, 1.0, 0.0, 0.0, 0.0),
        "pseudorange": lambda t: PseudorangeObservation(t, "G", 3, 2.2e7, 45.0),
        "doppler": lambda t: PseudorangeObservation(t, "G", 4, 2.2e7, 45.0, doppler_hz=-120.0),
    }
    rng = random.Random(19)
    checked_over = 0
    for pipeline, bounds in cost.MAX_PER_EPOCH.items():
        options = get_pipeline(pipeline).resolve_options({})
        kinds = [k for k in makers if (k if k != "doppler" else "pseudorange") in bounds]
        for _ in range(40):
            times = [100.0 + rng.choice(range(12)) * 0.05 for _ in range(rng.randint(1, 25))]
            shapes = [[rng.choice(kinds) for _ in range(rng.randint(1, 4))] for _ in range(3)]
            batch = [makers[kind](t) for t in times for kind in shapes[int(t * 20) % 3]]
            if rng.random() < 0.3:  # one epoch over the bound of a kind
                over = rng.choice(kinds)
                kind = "pseudorange" if over == "doppler" else over
                batch += [makers[over](99.0) for _ in range(bounds[kind] + 1)]
            if rng.random() < 0.5:
                rng.shuffle(batch)
            predicted, violations = cost.admit(pipeline, options, batch)
            counts = cost.epoch_counts(batch)
            assert predicted == cost.batch_cost_from_counts_s(pipeline, options, counts)
            assert predicted == pytest.approx(cost.batch_cost_s(pipeline, options, batch))
            assert violations == cost.epoch_bound_violations(pipeline, batch)
            checked_over += bool(violations)
    assert checked_over > 10
