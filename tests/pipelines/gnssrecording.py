"""The recording in tests/data/gnss-rover as the pipeline tests read it: its epochs as ``pseudorange``
measurements (``pipelines.gnss_recording.epoch_pseudoranges``, as the eval sends them) and an environment
holding its broadcast ephemerides, and a UKF session run over them epoch by epoch."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.pipelines.base import Fix, StaticEnvironment
from edgepos.pipelines.gnss_recording import epoch_pseudoranges
from edgepos.pipelines.gnss_tight import GnssTightPipeline

DATA = Path(__file__).resolve().parents[1] / "data" / "gnss-rover"


def recording_epochs(
    count: int | None = None, *, carrier: bool = True, systems: str = "GCE"
) -> tuple[list[list[PseudorangeObservation]], StaticEnvironment, np.ndarray]:
    """The first ``count`` epochs (all when None) of ``systems``, with or without their carrier phase, the
    environment with the ephemerides, and each epoch's GPS time (s)."""
    codes = {s: DEFAULT_CODES[s] for s in systems}
    environment = StaticEnvironment(
        navigation=Ephemerides.from_navigation(read_navigation(str(DATA / "broadcast-nav.rnx")))
    )
    epochs, times = [], []
    for number, epoch in enumerate(read_epochs(str(DATA / "rover-0-5min.rnx"), codes)):
        if count is not None and number >= count:
            break
        times.append(epoch.gpst)
        epochs.append(epoch_pseudoranges(epoch, carrier=carrier))
    return epochs, environment, np.array(times)


def run_ukf(
    epochs: list[list[PseudorangeObservation]],
    environment: StaticEnvironment,
    options: dict[str, Any],
    state: bytes | None = None,
) -> tuple[list[Fix], bytes]:
    """A UKF session (seed 1, ``options`` over it; or the stored ``state``) fed the ``epochs`` one batch
    each: every epoch's fix and the state after the last."""
    pipeline = GnssTightPipeline()
    if state is None:
        state = pipeline.create(pipeline.resolve_options({"filter": "ukf", "seed": 1, **options}), None)
    fixes = []
    for epoch in epochs:
        (fix,), state = pipeline.process(state, epoch, environment)
        fixes.append(fix)
    return fixes, state
