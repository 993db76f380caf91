"""Simulated RSU and gyro observations of the RSU + IMU paper's scenario."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.sim.scenarios import Scenario, rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return rsu_imu_paper_scenario()


@pytest.fixture(scope="module")
def epochs(scenario: Scenario) -> list[list[Observation]]:
    return rsu_imu_epochs(scenario, np.random.default_rng(2024))


def true_geometry(scenario: Scenario, k: int, rsu_id: str) -> tuple[float, float]:
    """True range and bearing from RSU ``rsu_id`` to the vehicle at sample k."""
    rsu = environment(scenario).rsu(rsu_id)
    assert rsu is not None
    dx, dy = scenario.truth.x[k] - rsu.x, scenario.truth.y[k] - rsu.y
    return math.hypot(dx, dy), math.atan2(dy, dx)


def test_rsu_layout_is_staggered_and_uniquely_named(scenario: Scenario) -> None:
    south = sorted(rsu.x for rsu in scenario.rsus if rsu.id.startswith("S"))
    north = sorted(rsu.x for rsu in scenario.rsus if rsu.id.startswith("N"))
    assert south == [float(x) for x in range(-300, 601, 100)]
    assert north == [float(x) for x in range(-250, 651, 100)]
    assert {rsu.y for rsu in scenario.rsus} == {-3.875, 15.125}
    assert len({rsu.id for rsu in scenario.rsus}) == len(scenario.rsus) == 20
    assert environment(scenario).rsu("N+050") == next(rsu for rsu in scenario.rsus if rsu.id == "N+050")


def test_one_epoch_per_sample_after_the_initial_state(
    scenario: Scenario, epochs: list[list[Observation]]
) -> None:
    assert len(epochs) == 800
    for k, epoch in enumerate(epochs, start=1):
        assert {obs.t for obs in epoch} == {scenario.truth.t[k]}
        assert [type(obs) for obs in epoch] == [RsuObservation] * 4 + [GyroObservation]


def test_the_four_nearest_rsus_in_range_report(scenario: Scenario, epochs: list[list[Observation]]) -> None:
    ids = [rsu.id for rsu in scenario.rsus]
    for k, epoch in enumerate(epochs, start=1):
        distances = {rsu_id: true_geometry(scenario, k, rsu_id)[0] for rsu_id in ids}
        in_range = sorted((d, rsu_id) for rsu_id, d in distances.items() if d <= scenario.comm_radius)
        assert len(in_range) >= 4
        assert [obs.rsu_id for obs in epoch[:4]] == [rsu_id for _, rsu_id in in_range[:4]]


def test_fewer_rsus_when_out_of_range(scenario: Scenario) -> None:
    short_range = dataclasses.replace(scenario, comm_radius=30.0, max_rsus=2)
    epochs = rsu_imu_epochs(short_range, np.random.default_rng(5))
    counts = [sum(isinstance(obs, RsuObservation) for obs in epoch) for epoch in epochs]
    assert set(counts) == {1, 2}
    for k, epoch in enumerate(epochs, start=1):
        for obs in epoch:
            if isinstance(obs, RsuObservation):
                assert true_geometry(scenario, k, obs.rsu_id)[0] <= 30.0


def test_same_seed_same_epochs_other_seed_differs(scenario: Scenario) -> None:
    first = rsu_imu_epochs(scenario, np.random.default_rng(7))
    again = rsu_imu_epochs(scenario, np.random.default_rng(7))
    other = rsu_imu_epochs(scenario, np.random.default_rng(8))
    assert first == again
    assert first != other
    assert [len(epoch) for epoch in first] == [len(epoch) for epoch in other]


def test_noise_matches_the_configured_levels(scenario: Scenario, epochs: list[list[Observation]]) -> None:
    range_errors, bearing_errors, gyro_errors = [], [], []
    for k, epoch in enumerate(epochs, start=1):
        for obs in epoch:
            if isinstance(obs, RsuObservation):
                true_range, true_bearing = true_geometry(scenario, k, obs.rsu_id)
                assert -math.pi <= obs.bearing < math.pi
                range_errors.append(obs.range - true_range)
                bearing_errors.append(math.remainder(obs.bearing - true_bearing, 2 * math.pi))
            else:
                gyro_errors.append(obs.yaw_rate - scenario.truth.yaw_rate[k])
    for errors, configured in (
        (range_errors, scenario.range_std),
        (bearing_errors, scenario.bearing_std),
        (gyro_errors, scenario.gyro_std),
    ):
        assert np.std(errors) == pytest.approx(configured, rel=0.10)
        assert abs(np.mean(errors)) < 4 * configured / math.sqrt(len(errors))
    assert scenario.range_std == 0.6
    assert scenario.bearing_std == pytest.approx(math.radians(0.5))
    assert scenario.gyro_std == pytest.approx(math.radians(0.3))
