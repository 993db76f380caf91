"""Simulated measurements of a scenario's truth: RSU range/bearing and gyro yaw rate.

Noise is zero-mean Gaussian, independent between sensors and epochs. All of it is drawn up front
from the caller's generator in one fixed order, so the observations depend only on its seed:

1. range noise, shape (K, M): epoch-major, column j for the j-th nearest RSU heard that epoch;
2. bearing noise, shape (K, M), same layout;
3. gyro noise, shape (K,);

with K the number of epochs and M = min(max_rsus, number of RSUs). Slots of RSUs not heard are
drawn too and discarded, so how many RSUs are in range never shifts the stream.
"""

from __future__ import annotations

import numpy as np

from edgepos.core.numerics import wrap_angle
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.pipelines.base import StaticEnvironment
from edgepos.sim.scenarios import Scenario


def rsu_imu_epochs(scenario: Scenario, rng: np.random.Generator) -> list[list[Observation]]:
    """One epoch per t_k, k = 1..K (t_0 is the known initial state): RSU observations, nearest first,
    then the gyro.

    An RSU is heard if the true distance is within its radius (``Rsu.radius`` or the scenario's
    ``comm_radius``); the nearest ``max_rsus`` heard report range = distance + noise and bearing =
    atan2(y_vehicle - y_rsu, x_vehicle - x_rsu) + noise, wrapped to [-pi, pi). Per-RSU noise levels
    override the scenario's when set.
    """
    truth, rsus = scenario.truth, scenario.rsus
    times = truth.t[1:]
    dx = truth.x[1:, None] - np.array([rsu.x for rsu in rsus])[None, :]
    dy = truth.y[1:, None] - np.array([rsu.y for rsu in rsus])[None, :]
    distance = np.hypot(dx, dy)
    radius = np.array([scenario.comm_radius if rsu.radius is None else rsu.radius for rsu in rsus])
    range_std = np.array([scenario.range_std if rsu.range_std is None else rsu.range_std for rsu in rsus])
    bearing_std = np.array(
        [scenario.bearing_std if rsu.bearing_std is None else rsu.bearing_std for rsu in rsus]
    )

    slots = min(scenario.max_rsus, len(rsus))
    heard_distance = np.where(distance <= radius, distance, np.inf)
    nearest = np.argsort(heard_distance, axis=1, kind="stable")[:, :slots]
    heard = np.isfinite(np.take_along_axis(heard_distance, nearest, axis=1))

    epochs_count = times.size
    range_noise = rng.standard_normal((epochs_count, slots)) * range_std[nearest]
    bearing_noise = rng.standard_normal((epochs_count, slots)) * bearing_std[nearest]
    gyro_noise = rng.standard_normal(epochs_count) * scenario.gyro_std

    ranges = np.take_along_axis(distance, nearest, axis=1) + range_noise
    true_bearings = np.arctan2(
        np.take_along_axis(dy, nearest, axis=1), np.take_along_axis(dx, nearest, axis=1)
    )
    bearings = np.asarray(wrap_angle(true_bearings + bearing_noise))
    yaw_rates = truth.yaw_rate[1:] + gyro_noise

    ids = [rsu.id for rsu in rsus]
    epochs: list[list[Observation]] = []
    columns = (times, nearest, heard, ranges, bearings, yaw_rates)
    for t, rows, heard_row, range_row, bearing_row, yaw_rate in zip(*(column.tolist() for column in columns)):
        epoch: list[Observation] = [
            RsuObservation(t=t, rsu_id=ids[rsu], range=measured_range, bearing=bearing)
            for rsu, is_heard, measured_range, bearing in zip(rows, heard_row, range_row, bearing_row)
            if is_heard
        ]
        epoch.append(GyroObservation(t=t, yaw_rate=yaw_rate))
        epochs.append(epoch)
    return epochs


def environment(scenario: Scenario) -> StaticEnvironment:
    """The scenario's RSU registry, as pipelines look RSUs up by id."""
    return StaticEnvironment({rsu.id: rsu for rsu in scenario.rsus})
