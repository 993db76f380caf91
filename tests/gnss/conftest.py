"""Shared fixtures of the GNSS tests: the project's copy of the Rokubun recording (tests/data/gnss-rover)."""

from __future__ import annotations

import pytest
from edgepos.gnss.orbits import BroadcastOrbits
from edgepos.gnss.rinex_nav import NavigationData, read_navigation
from edgepos.gnss.rinex_obs import ObservationEpoch, read_epochs
from gnsshelp import NAV, OBS


@pytest.fixture(scope="session")
def nav() -> NavigationData:
    return read_navigation(NAV)


@pytest.fixture(scope="session")
def orbits(nav: NavigationData) -> BroadcastOrbits:
    return BroadcastOrbits(nav.ephemerides)


@pytest.fixture(scope="session")
def epochs() -> list[ObservationEpoch]:
    return list(read_epochs(OBS))
