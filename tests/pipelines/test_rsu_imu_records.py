"""The lag window's records written from an ``rsu_imu`` batch's table (``rsu_imu_batch.batch_records``,
``core.kernels_grouping.write_records``) against ``core.observation_codec``'s encoders
(``lag_state.encode_epochs``): the same bytes for every batch of RSU and gyro observations, and the same
window states through the registry's pipeline for batches in time order, late and out of order."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from edgepos.core.compiled import compiled_enabled
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.pipelines import rsu_imu
from edgepos.pipelines.base import InitialState, PipelineInputError, Rsu, StaticEnvironment
from edgepos.pipelines.lag_state import encode_epochs
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu_batch import _checked_batch, batch_records, read_batch
from edgepos.sim.delivery import arrival_batches
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs
from hypothesis import given, settings
from hypothesis import strategies as st

IDS = ("A", "north-gantry-17", "Ωmega", "x" * 40)
ENV = StaticEnvironment({rsu_id: Rsu(rsu_id, 10.0 * k, -4.0) for k, rsu_id in enumerate(IDS)})
OPTIONS = get_pipeline("rsu_imu").inner.inner.resolve_options({})  # type: ignore[attr-defined]  # the wrappers'
compiled = pytest.mark.skipif(not compiled_enabled(), reason="the compiled writer is off (EDGEPOS_NUMBA=0)")

number = st.one_of(st.floats(-1e6, 1e6), st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1.5]))
observation = st.one_of(
    st.builds(
        RsuObservation,
        st.floats(0.0, 1e9),
        st.sampled_from(IDS),
        st.one_of(st.floats(0.0, 1e7), st.sampled_from([0.0, 5e-324])),
        st.floats(-math.pi, math.pi),
    ),
    st.builds(GyroObservation, st.one_of(st.floats(0.0, 1e9), st.sampled_from([0.0, 7.0])), number),
)


@compiled
@settings(max_examples=300, deadline=None)
@given(st.lists(observation, max_size=40))
def test_the_written_records_are_the_encoders_bytes(observations: list[Observation]) -> None:
    written = batch_records(read_batch(OPTIONS, None, observations, ENV))
    assert written is not None
    data, ends = written
    each = encode_epochs(observations, [1] * len(observations))
    assert data.tobytes() == b"".join(each)
    assert ends == list(itertools.accumulate(map(len, each)))


def test_a_batch_read_observation_by_observation_is_left_to_the_encoders() -> None:
    batch = [RsuObservation(1.0, "A", 5.0, 0.1), GyroObservation(0.5, 0.0)]  # older than t=0.8: refused
    with pytest.raises(PipelineInputError, match="older"):
        read_batch(OPTIONS, 0.8, batch, ENV)
    assert batch_records(_checked_batch(OPTIONS, 0.1, batch, ENV)) is None


def test_written_records_answer_only_for_the_batch_just_read() -> None:
    pipeline = rsu_imu.RsuImuPipeline()
    state = pipeline.create(OPTIONS, InitialState(0.0, 0.0, 5.0, 0.0))
    batch = [RsuObservation(1.0, "A", 5.0, 0.1), GyroObservation(1.0, 0.01)]
    pipeline.process(state, batch, ENV)
    assert pipeline.written_records(list(batch)) is None  # an equal list, not the one read
    assert (pipeline.written_records(batch) is not None) == compiled_enabled()


SCENARIO = rsu_imu_paper_scenario()
EPOCHS = rsu_imu_epochs(SCENARIO, np.random.default_rng(3))[:120]


def states(batches: list[list[Observation]], written: bool, monkeypatch: pytest.MonkeyPatch) -> list[bytes]:
    """The registry pipeline's state after each batch, records written from the table or by the encoders."""
    with monkeypatch.context() as patch:
        if not written:
            patch.setattr(rsu_imu.RsuImuPipeline, "written_records", lambda self, observations: None)
        pipeline = get_pipeline("rsu_imu")
        x0 = SCENARIO.initial_state
        state = pipeline.create(pipeline.resolve_options({}), InitialState(x0[0], x0[3], x0[1], x0[4]))
        out = []
        for batch in batches:
            _, state = pipeline.process(state, batch, environment(SCENARIO))
            out.append(state)
        return out


@compiled
@pytest.mark.parametrize("late", [False, True])
def test_the_window_states_are_the_encoders(monkeypatch: pytest.MonkeyPatch, late: bool) -> None:
    observations = [o for epoch in EPOCHS for o in epoch]
    arrivals = np.array([o.t for o in observations])
    if late:  # every seventh measurement 0.3 s late, every eleventh 0.12 s: late and out of order batches
        arrivals[::7] += 0.3
        arrivals[::11] += 0.12
    batches = arrival_batches(observations, arrivals, 5)
    assert late == any(b != sorted(b, key=lambda o: o.t) for b in batches)
    assert states(batches, True, monkeypatch) == states(batches, False, monkeypatch)
