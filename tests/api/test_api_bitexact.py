"""Fixes served over HTTP are the in-process pipeline's, bit for bit."""

from __future__ import annotations

from apihelp import NO_DOPPLER, batch_observations, open_session, scenario, wire
from edgepos.pipelines.base import InitialState, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline

BATCHES = [(0, 1), (1, 7), (8, 20), (28, 3)]  # (first epoch, epochs)
HELD_BACK = 29  # the last batch arrives without this epoch's gyro, which comes late with the next epoch
OPTIONS = {"filter": "ckf", "rsu_handling": "joint"}


def _expected_wire(fix):
    """What the wire should say for a pipeline Fix, with include_state (floats untouched)."""
    return {
        "t": fix.t,
        "status": fix.status,
        "revised": fix.revised,
        "divergence": fix.divergence,
        "x": fix.x,
        "y": fix.y,
        "vx": fix.vx,
        "vy": fix.vy,
        "speed": fix.speed,
        "heading": fix.heading,
        "yaw_rate": fix.yaw_rate,
        "latitude": None,
        "longitude": None,
        "height": None,
        "position_covariance": fix.position_cov,
        "state": {"components": list(fix.state_components), "mean": fix.state, "covariance": fix.state_cov},
        "model_probabilities": fix.model_probabilities,
        "nis": fix.nis,
        "nis_dof": fix.nis_dof,
        "constraints": None if fix.constraints is None else list(fix.constraints),
        "protection_level_m": fix.protection_level,
        "integrity": fix.integrity,
        "measurements": [
            {
                "index": u.index,
                "type": u.kind,
                "used": u.used,
                "reason": u.reason,
                "doppler_used": u.doppler_used,
                "doppler_reason": u.doppler_reason,
                "correction_applied": u.correction_applied,
                "correction_reason": u.correction_reason,
                "noise_std": u.noise_std,
                "noise_reason": u.noise_reason,
            }
            for u in fix.measurements
        ],
    }


def _assert_identical(actual, expected, path="fix"):
    """Equal with floats compared exactly (==, and the same type), recursively."""
    assert type(actual) is type(expected) or (isinstance(actual, float) and isinstance(expected, float)), path
    if isinstance(expected, dict):
        assert list(actual) == list(expected), path
        for key in expected:
            _assert_identical(actual[key], expected[key], f"{path}.{key}")
    elif isinstance(expected, list):
        assert len(actual) == len(expected), path
        for index, (a, e) in enumerate(zip(actual, expected, strict=True)):
            _assert_identical(a, e, f"{path}[{index}]")
    else:
        assert actual == expected, f"{path}: {actual!r} != {expected!r}"
        if isinstance(expected, float):
            assert actual.hex() == expected.hex(), path


def _check_session(client, initial_state):
    pipeline = get_pipeline("rsu_imu")
    environment = StaticEnvironment({rsu.id: rsu for rsu in scenario().rsus})
    initial = None if initial_state is None else InitialState(**initial_state)
    state = pipeline.create(pipeline.resolve_options(OPTIONS), initial)
    session_id, token = open_session(client, options=OPTIONS, initial_state=initial_state)
    late = next(o for o in batch_observations(HELD_BACK, 1) if o.kind == "gyro")
    last_first, last_count = BATCHES[-1]
    # in time order, then a late measurement: the lag window's revised fixes are served bit for bit too
    batches = [batch_observations(first, count) for first, count in BATCHES]
    batches[-1] = [o for o in batches[-1] if o != late]
    batches.append(batch_observations(last_first + last_count, 1) + [late])
    counts = [count for _, count in BATCHES] + [1 + (last_first + last_count - HELD_BACK)]  # fixes per batch
    for seq, (observations, count) in enumerate(zip(batches, counts, strict=True), start=1):
        expected_fixes, state = pipeline.process(state, observations, environment)
        body = {"seq": seq, "measurements": [wire(o) for o in observations], "include_state": True}
        response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
        assert response.status_code == 200, response.text
        served = response.json()["fixes"]
        assert len(served) == len(expected_fixes) == count
        for index, (got, fix) in enumerate(zip(served, expected_fixes, strict=True)):
            _assert_identical(got, _expected_wire(fix), f"batch{seq}.fix{index}")
    # the last batch: the held-back epoch and the one after it come back revised, then the new epoch
    assert [f["revised"] for f in served] == [True] * (count - 1) + [False]
    assert served[0]["t"] == late.t
    gyro = {"index": len(observations) - 1, "type": "gyro", "used": True, "reason": None, **NO_DOPPLER}
    assert served[0]["measurements"] == [gyro]
    stored = client.portal.call(client.app.state.context.store.get, session_id)
    assert stored.state == state  # the session's state is byte-identical too


def test_http_fixes_equal_the_pipeline_bit_for_bit(client):
    _check_session(client, initial_state=None)


def test_http_fixes_equal_the_pipeline_from_a_known_start(client):
    truth = scenario().truth
    start = {
        "x": float(truth.x[0]),
        "y": float(truth.y[0]),
        "vx": float(truth.vx[0]),
        "vy": float(truth.vy[0]),
        "position_std": 0.5,
        "velocity_std": 0.2,
    }
    _check_session(client, initial_state=start)
