"""gnss_tight pipeline behaviour the filter defects hid: a vehicle starting eastbound is tracked (the RISS
azimuth used to start at north and never recover), a pseudorange with a large bias is excluded by the
snapshot test, and the state (with its new fields) survives bytes bit for bit."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation
from edgepos.eval.gnss_montecarlo import batches
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.pipelines.base import StaticEnvironment
from edgepos.pipelines.gnss_session import decode_session as _decode
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from edgepos.sim.gnss_scenario import open_sky_scenario
from edgepos.sim.gnss_sensors import simulate

DATA = "tests/data/gnss-rover/"


def run_scenario(heading0: float, options: dict) -> tuple[np.ndarray, bytes]:
    scenario = open_sky_scenario(short=True, heading0=heading0)
    run = simulate(scenario, np.random.default_rng([11, 0]))
    pipeline = GnssTightPipeline()
    resolved = pipeline.resolve_options({"gps_week": scenario.gps_week, "seed": 4, **options})
    state = pipeline.create(resolved, None)
    environment = StaticEnvironment(origin=scenario.site)
    epoch_of = {round(float(t), 6): k for k, t in enumerate(run.gnss_tow)}
    errors = np.full(run.gnss_tow.size, np.nan)
    for batch in batches(run, scenario.gnss_every):
        fixes, state = pipeline.process(state, batch, environment)
        for fix in fixes:
            k = epoch_of.get(round(fix.t, 6))
            if k is not None and fix.x is not None:
                errors[k] = math.hypot(fix.x - run.truth_east[k], fix.y - run.truth_north[k])
    return errors, state


@pytest.mark.parametrize(
    "options", [{"filter": "ukf"}, {"filter": "upf"}, {"filter": "pf"}], ids=["ukf", "upf", "pf"]
)
def test_an_eastbound_start_is_tracked(options: dict) -> None:
    """Starting east (90 degrees from the old fixed initial azimuth): every epoch has a fix and the error
    settles as on a northbound start (it used to be 7-10 m RMS and growing)."""
    errors, state = run_scenario(0.0, options)
    assert np.all(np.isfinite(errors))
    assert np.sqrt(np.mean(errors[10:] ** 2)) < 2.0, errors
    session = _decode(state)
    assert session.heading_known  # the RISS model took over
    assert _decode(state).to_bytes() == state


@pytest.fixture(scope="module")
def recording() -> tuple[list[list[PseudorangeObservation]], StaticEnvironment]:
    codes = {s: DEFAULT_CODES[s] for s in "GC"}
    navigation = Ephemerides.from_navigation(read_navigation(DATA + "broadcast-nav.rnx"))
    environment = StaticEnvironment(navigation=navigation)
    epochs = []
    for count, epoch in enumerate(read_epochs(DATA + "rover-0-5min.rnx", codes)):
        if count >= 12:
            break
        epochs.append(
            [
                PseudorangeObservation(epoch.gpst % 604800.0, system, int(prn), float(pr), float(cn0))
                for system, prn, pr, cn0 in zip(
                    epoch.systems, epoch.prns, epoch.pseudorange_m, epoch.cn0_dbhz
                )
                if math.isfinite(pr) and math.isfinite(cn0)
            ]
        )
    return epochs, environment


@pytest.mark.parametrize("filter_name", ["ukf", "upf", "pf"])
def test_a_biased_pseudorange_is_excluded_by_the_snapshot_test(recording, filter_name: str) -> None:
    """A 60 m bias on the strongest satellite (an NLOS-like error) in the last epoch: the snapshot test drops
    it; with both tests and the integrity monitor off it is used (so the exclusion is the snapshot test's);
    with the tests off and the monitor on, the monitor excludes it."""
    epochs, environment = recording
    pipeline = GnssTightPipeline()

    def last_use(fde: float, gate: float, integrity: bool = True) -> tuple[bool, str | None]:
        options = pipeline.resolve_options(
            {
                "filter": filter_name,
                "particles": 50,
                "seed": 2,
                "systems": ["C", "G"],
                "fde_probability": fde,
                "gate_probability": gate,
                "integrity": integrity,
            }
        )
        state = pipeline.create(options, None)
        for batch in epochs[:-1]:
            _, state = pipeline.process(state, batch, environment)
        biased = list(epochs[-1])
        target = max(range(len(biased)), key=lambda i: biased[i].cn0)
        o = biased[target]
        biased[target] = PseudorangeObservation(o.t, o.system, o.prn, o.pseudorange + 60.0, o.cn0)
        fixes, _ = pipeline.process(state, biased, environment)
        use = next(u for u in fixes[-1].measurements if u.index == target)
        return use.used, use.reason

    used, reason = last_use(0.999, 0.0)
    assert not used and reason is not None and "snapshot" in reason
    used, _ = last_use(0.0, 0.0, integrity=False)
    assert used
    used, reason = last_use(0.0, 0.0)
    assert not used and reason is not None and reason.startswith("excluded by fault detection")


@pytest.mark.parametrize("filter_name", ["upf", "pf"])
def test_the_cloud_mean_averages_the_azimuth_on_the_circle(filter_name: str) -> None:
    """Particles heading south straddle +-pi: their mean azimuth is south, not the plain average (north)
    the prediction used to be linearised at. The covariance beside it is session_covariance's (the UPF's
    taken from the same moments)."""
    from edgepos.core.motion import riss as layout
    from edgepos.core.particles import Cloud
    from edgepos.pipelines.gnss_session import GnssSession, cloud_moments, session_covariance

    particles = np.zeros((4, layout.DIM))
    particles[:, layout.AZIMUTH] = [math.pi - 0.01, -math.pi + 0.01, math.pi - 0.02, -math.pi + 0.02]
    particles[:, layout.NORTH] = [1.0, 2.0, 3.0, 4.0]
    cloud = Cloud(particles, np.log([0.1, 0.2, 0.3, 0.4]), np.eye(layout.DIM) * 2.0)
    options = GnssTightPipeline().resolve_options({"filter": filter_name})
    session = GnssSession(options, 1, True, 0.0, 0.0, 1, None, None, {}, cloud)
    mean, cov = cloud_moments(session)
    assert abs(abs(mean[layout.AZIMUTH]) - math.pi) < 0.02  # south; the plain average is near 0 (north)
    assert mean[layout.NORTH] == pytest.approx(3.0)
    assert np.array_equal(cov, session_covariance(session))


def test_outlier_likelihood_options_have_documented_defaults_and_bounds() -> None:
    from edgepos.pipelines.base import PipelineInputError

    pipeline = GnssTightPipeline()
    resolved = pipeline.resolve_options({})
    assert resolved["outlier_probability"] == 0.1
    assert resolved["outlier_std"] == 30.0
    assert pipeline.resolve_options({"outlier_probability": 0.0})["outlier_probability"] == 0.0
    with pytest.raises(PipelineInputError):
        pipeline.resolve_options({"outlier_probability": 1.0})
    with pytest.raises(PipelineInputError):
        pipeline.resolve_options({"outlier_std": 0.0})


def test_upf_spread_fraction_option_reaches_the_filter_and_old_states_keep_their_behaviour() -> None:
    """The option is validated and passed to the UPF; a state stored before it existed (no spread_fraction
    in its options) keeps the behaviour it was created with: all of the uncertainty in the particles."""
    from edgepos.core import state as state_format
    from edgepos.pipelines.base import PipelineInputError
    from edgepos.pipelines.gnss_session import filter_for as _filter

    pipeline = GnssTightPipeline()
    assert pipeline.resolve_options({})["spread_fraction"] == 0.02
    with pytest.raises(PipelineInputError):
        pipeline.resolve_options({"spread_fraction": 1.5})
    options = pipeline.resolve_options({"filter": "upf", "spread_fraction": 0.3})
    assert _filter(options).spread_fraction == 0.3

    old_options = {
        k: v
        for k, v in pipeline.resolve_options({"filter": "upf", "seed": 1}).items()
        if k != "spread_fraction"
    }
    meta, arrays = state_format.unpack(pipeline.create({**old_options, "seed": 1}, None))
    stored = json.loads(meta["options_json"])  # the options as their JSON text (gnss_session)
    assert "spread_fraction" not in stored
    assert _filter(stored).spread_fraction == 1.0
    errors, _ = _replay_short_open_sky(state_format.pack(meta, arrays))
    assert np.all(np.isfinite(errors[1:]))


def _replay_short_open_sky(state: bytes) -> tuple[np.ndarray, bytes]:
    scenario = open_sky_scenario(short=True)
    run = simulate(scenario, np.random.default_rng([11, 1]))
    pipeline = GnssTightPipeline()
    environment = StaticEnvironment(origin=scenario.site)
    epoch_of = {round(float(t), 6): k for k, t in enumerate(run.gnss_tow)}
    errors = np.full(run.gnss_tow.size, np.nan)
    for batch in batches(run, scenario.gnss_every)[:20]:
        fixes, state = pipeline.process(state, batch, environment)
        for fix in fixes:
            k = epoch_of.get(round(fix.t, 6))
            if k is not None and fix.x is not None:
                errors[k] = math.hypot(fix.x - run.truth_east[k], fix.y - run.truth_north[k])
    return errors[:20], state
