"""``read_batch``'s one-pass reading of a clean batch against ``_checked_batch``'s reading observation by
observation: the same arrays for a clean batch, and for a batch with any one bad value the same problems."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.pipelines.base import PipelineInputError, Rsu, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu_batch import Batch, _checked_batch, read_batch

ENV = StaticEnvironment(
    {
        "A": Rsu("A", 0.0, -4.0),
        "B": Rsu("B", 50.0, 15.0, range_std=0.3, bearing_std=0.01, radius=80.0),
        "C": Rsu("C", 100.0, -4.0),
    }
)
OPTIONS = get_pipeline("rsu_imu").resolve_options({})


def clean_batch() -> list[Observation]:
    rng = np.random.default_rng(5)
    batch: list[Observation] = []
    for k in range(4):
        t = 10.0 + 0.1 * k
        for rsu_id in ("A", "B", "C"):
            batch.append(RsuObservation(t, rsu_id, float(rng.uniform(0, 90)), float(rng.uniform(-3, 3))))
        batch.append(GyroObservation(t, float(rng.normal(0, 0.1))))
    batch.append(RsuObservation(10.5, "A", 0.0, math.pi))  # the edges: range 0, bearing pi
    return batch


def same_batch(a: Batch, b: Batch) -> bool:
    arrays = ("positions", "observed", "range_std", "bearing_std", "range_variances", "bearing_variances")
    return (
        a.rsus == b.rsus
        and a.times == b.times
        and a.ranges == b.ranges
        and a.radii == b.radii
        and all(np.array_equal(getattr(a, name), getattr(b, name)) for name in (*arrays, "yaw_rates"))
    )


def problems_of(reader, observations, last_t) -> list[tuple[int | None, str, str]] | None:
    try:
        reader(OPTIONS, last_t, observations, ENV)
    except PipelineInputError as error:
        return [(p.index, p.field, p.reason) for p in error.problems]
    return None


@pytest.mark.parametrize("last_t", [None, 9.0, 10.0])
def test_a_clean_batch_reads_as_the_checked_reading_does(last_t) -> None:
    batch = clean_batch()
    assert same_batch(read_batch(OPTIONS, last_t, batch, ENV), _checked_batch(OPTIONS, last_t, batch, ENV))


BAD = [
    ("t", math.nan),
    ("t", math.inf),
    ("t", -math.inf),
    ("t", 9.5),  # older than the session's last epoch (10.0)
    ("range", math.nan),
    ("range", math.inf),
    ("range", -0.5),
    ("bearing", math.nan),
    ("bearing", -math.inf),
    ("bearing", math.pi + 1e-6),
    ("bearing", -math.pi - 1e-6),
    ("rsu_id", "nowhere"),
    ("yaw_rate", math.nan),
    ("yaw_rate", math.inf),
]


@pytest.mark.parametrize("position", [0, 3, 7, 16])
@pytest.mark.parametrize(("field", "value"), BAD)
def test_a_bad_value_anywhere_gives_the_checked_readings_problems(position, field, value) -> None:
    batch = clean_batch()
    # the first observation at or after ``position`` (cyclically) that has the field
    position = next(
        k % len(batch)
        for k in range(position, position + len(batch))
        if hasattr(batch[k % len(batch)], field)
    )
    batch[position] = dataclasses.replace(batch[position], **{field: value})
    expected = problems_of(_checked_batch, batch, 10.0)
    assert expected, f"{field}={value!r} should be refused"
    assert problems_of(read_batch, batch, 10.0) == expected
    assert any(index == position and name == field for index, name, _ in expected)


def test_an_observation_of_another_type_is_refused_by_name() -> None:
    @dataclasses.dataclass(frozen=True)
    class Stranger:
        t: float
        kind: str = "gnss_fix"

    batch: list = [*clean_batch(), Stranger(10.2)]
    assert problems_of(read_batch, batch, None) == [
        (len(batch) - 1, "type", "'gnss_fix' is not used by the rsu_imu pipeline")
    ]
