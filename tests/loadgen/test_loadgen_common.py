"""The shared pieces of simulate and loadtest: loopback check, wire batches, seeds, RMSE."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.observations import GyroObservation, RsuObservation
from edgepos.loadgen import common
from edgepos.loadgen.simulate import rmse
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos_client import Fix, GyroMeasurement, RsuMeasurement


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:8000",
        "http://127.9.8.7",
        "https://localhost:1/",
        "http://LOCALHOST",
        "http://[::1]:8000",
    ],
)
def test_loopback_urls_are_accepted(url: str) -> None:
    assert common.loopback_problem(url) is None


@pytest.mark.parametrize(
    "url",
    [
        "http://10.0.0.1:8000",
        "http://example.com",
        "http://128.0.0.1",
        "http://0.0.0.0:8000",
        "ftp://127.0.0.1",
        "http://[::2]:80",
        "127.0.0.1:8000",
        "http://127.0.0.1:99999",
        "http://localhost.example.com",
    ],
)
def test_other_urls_are_refused(url: str) -> None:
    assert common.loopback_problem(url) is not None


def test_wire_batches_keep_values_and_group_epochs() -> None:
    epochs = [
        [
            RsuObservation(t=0.05, rsu_id="S+000", range=4.25, bearing=1.0),
            GyroObservation(t=0.05, yaw_rate=0.1),
        ],
        [GyroObservation(t=0.1, yaw_rate=0.2)],
        [GyroObservation(t=0.15, yaw_rate=0.3)],
    ]
    batches = common.wire_batches(epochs, 2)
    assert batches == [
        [
            RsuMeasurement(t=0.05, rsu_id="S+000", range=4.25, bearing=1.0),
            GyroMeasurement(t=0.05, yaw_rate=0.1),
            GyroMeasurement(t=0.1, yaw_rate=0.2),
        ],
        [GyroMeasurement(t=0.15, yaw_rate=0.3)],
    ]
    with pytest.raises(ValueError):
        common.wire_batches(epochs, 0)


def test_each_vehicle_has_its_own_reproducible_noise() -> None:
    scenario = rsu_imu_paper_scenario()
    first, again, second = (common.vehicle_epochs(scenario, 5, v)[:3] for v in (0, 0, 1))
    assert first == again and first != second


def test_initial_state_is_the_truth_at_zero() -> None:
    scenario = rsu_imu_paper_scenario()
    start = common.initial_state(scenario)
    assert (start.x, start.y, start.vx, start.vy) == (
        scenario.truth.x[0],
        scenario.truth.y[0],
        scenario.truth.vx[0],
        scenario.truth.vy[0],
    )
    assert (start.position_std, start.velocity_std) == (1.0, 1.0)


def test_rmse_against_the_truth() -> None:
    scenario = rsu_imu_paper_scenario()
    truth = scenario.truth

    def fix(k: int, dx: float, dvy: float) -> Fix:
        return Fix(
            t=float(truth.t[k]),
            status="tracking",
            x=float(truth.x[k]) + dx,
            y=float(truth.y[k]),
            vx=float(truth.vx[k]),
            vy=float(truth.vy[k]) + dvy,
        )

    position, velocity = rmse(
        [fix(1, 3.0, 0.0), fix(2, 4.0, 1.0), Fix(t=0.15, status="uninitialised")], scenario
    )
    assert position == pytest.approx(math.sqrt((9.0 + 16.0) / 2))
    assert velocity == pytest.approx(math.sqrt(0.5))
    assert rmse([], scenario) == (None, None)
    assert np.isclose(rmse([fix(1, 0.0, 0.0)], scenario)[0], 0.0)
