"""The Galileo group-delay check on the recording: the vehicle's receiver measures as if the satellites had no
BGD, the station's as the ICD says, and the check says so (docs/gnss.md, "The receivers' Galileo group delay")."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.gnss.differential import base_position
from edgepos.gnss.group_delay_check import GALILEO_CODES, check, main
from edgepos.gnss.measurements import Atmosphere
from edgepos.gnss.orbits import BroadcastOrbits
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import read_epochs, read_header
from edgepos.gnss.spp import epochs_at_reference, read_reference

DATA = "tests/data/gnss-rover/"


@pytest.fixture(scope="module")
def navigation():
    nav = read_navigation(DATA + "broadcast-nav.rnx")
    return BroadcastOrbits(nav.ephemerides), Atmosphere.from_navigation(nav)


def _rover(first: int, stop: int):
    ref_time, ref_ecef = read_reference(DATA + "reference-0-5min.csv")
    for epoch, row in epochs_at_reference(DATA + "rover-0-5min.rnx", GALILEO_CODES, ref_time, first, stop):
        yield epoch, ref_ecef[row]


def test_the_vehicle_carries_no_bgd_and_the_station_does(navigation) -> None:
    """Measured: the rover's slope -0.11 +- 0.17 on the first half, -0.07 +- 0.37 on the second; the
    station's 0.56 +- 0.36 over the five minutes (its other errors are as large as its BGDs, so alone it
    is the weaker evidence; the two receivers' difference is what the differential fixes show)."""
    orbits, atmosphere = navigation
    first = check(_rover(0, 150), orbits, atmosphere)
    assert first.setting == "none" and abs(first.slope) < 0.3 and first.slope_std < 0.3
    assert len(first.sats) >= 6 and np.all(first.epochs >= 30)
    assert "E12" in first.sats and first.bgd_m[first.sats.index("E12")] == pytest.approx(-3.14, abs=0.01)
    assert check(_rover(150, 300), orbits, atmosphere).setting == "none"
    position = base_position(read_header(DATA + "base-0-5min.rnx"))
    station = check(
        ((e, position) for e in read_epochs(DATA + "base-0-5min.rnx", GALILEO_CODES)), orbits, atmosphere
    )
    assert station.setting == "broadcast" and station.slope > first.slope + 0.5


def test_too_few_satellites_is_an_error(navigation) -> None:
    orbits, atmosphere = navigation
    with pytest.raises(ValueError, match="3 are needed"):
        check(_rover(0, 10), orbits, atmosphere)


def test_the_command_line(capsys) -> None:
    args = ["--obs", DATA + "rover-0-5min.rnx", "--nav", DATA + "broadcast-nav.rnx"]
    assert main([*args, "--reference", DATA + "reference-0-5min.csv", "--epochs", "0:150"]) == 0
    assert "galileo_group_delay none" in capsys.readouterr().out
    assert main([*args, "--reference", DATA + "reference-0-5min.csv", "--epochs", "0:10"]) == 2
    assert "3 are needed" in capsys.readouterr().err
