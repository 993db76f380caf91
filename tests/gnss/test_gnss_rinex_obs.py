"""RINEX 3 observation reader on the real recording and on malformed snippets."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.rinex_nav import RinexError
from edgepos.gnss.rinex_obs import ALL_SYSTEMS, ObservationEpoch, iter_epochs, parse_systems, read_header
from edgepos.gnss.timesys import calendar_to_seconds, week_seconds
from gnsshelp import OBS

HEADER = [
    "     3.04           OBSERVATION DATA    M (MIXED)           RINEX VERSION / TYPE",
    "G    4 C1C L1C D1C S1C                                      SYS / # / OBS TYPES ",
    "C    2 C2I S2I                                              SYS / # / OBS TYPES ",
    "  2020    11    29    12    40    0.0000000     GPS         TIME OF FIRST OBS   ",
    "                                                            END OF HEADER       ",
]
EPOCH = [
    "> 2020 11 29 12 40 00.0000000  0  3",
    "G05  20741344.067 7 108998394.123 7      1427.440 7        46.250",
    "G07                 114695434.700 7     -1942.590 7        47.406",
    "C21  21805890.851 7        47.969",
]


def test_real_recording_epochs(epochs: list[ObservationEpoch]) -> None:
    assert len(epochs) == 300
    week, sow = week_seconds(epochs[0].gpst)
    assert (week, sow) == (2134, 45600.0)
    assert np.allclose(np.diff([e.gpst for e in epochs]), 1.0)
    first = epochs[0]
    # The first epoch's GPS satellites with C1C and BeiDou satellites with C2I (read off the file by eye).
    gps_bds = [s for s in first.sats if s[0] in "GC"]
    assert gps_bds == [
        "C07",
        "C10",
        "C14",
        "C21",
        "C22",
        "C26",
        "C36",
        "G02",
        "G05",
        "G06",
        "G07",
        "G09",
        "G13",
        "G28",
        "G30",
    ]
    assert first.pseudorange_m[first.sats.index("G05")] == pytest.approx(20741344.067)
    assert first.cn0_dbhz[first.sats.index("G05")] == pytest.approx(46.250)
    assert first.pseudorange_m[first.sats.index("C07")] == pytest.approx(40656230.413)
    # The Doppler of the chosen signal: D1C beside C1C (GPS), D2I beside C2I (BeiDou), not D1P or D5P.
    assert first.doppler_hz[first.sats.index("G05")] == pytest.approx(1427.440)
    assert first.doppler_hz[first.sats.index("C21")] == pytest.approx(2.619)
    assert all(np.isfinite(e.doppler_hz).all() for e in epochs)
    counts = [sum(s[0] in "GC" for s in e.sats) for e in epochs]
    assert (min(counts), max(counts), sum(counts)) == (9, 17, 4126)


def test_header_fields() -> None:
    header = read_header(OBS)
    assert header.obs_types["G"][:5] == ("C1C", "C1W", "C2L", "C2W", "C5Q")
    assert len(header.obs_types["G"]) == 18 and len(header.obs_types["C"]) == 16
    assert header.approx_position == pytest.approx((4769615.6688, 195962.0732, 4216207.5526))
    assert header.interval_s == 1.0 and header.time_system == "GPS"


def test_blank_fields_truncated_lines_and_codes() -> None:
    ((_, epoch),) = list(iter_epochs(HEADER + EPOCH, {"G": ("C1C", "S1C"), "C": ("C2I", "S2I")}))
    assert epoch.gpst == calendar_to_seconds(2020, 11, 29, 12, 40, 0)
    assert epoch.sats == ("G05", "C21")  # G07 has a blank C1C field
    assert epoch.cn0_dbhz == pytest.approx([46.25, 47.969])
    assert epoch.doppler_hz[0] == pytest.approx(1427.44) and math.isnan(epoch.doppler_hz[1])  # no D2I listed
    ((_, only_gps),) = list(iter_epochs(HEADER + EPOCH, {"G": ("C1C", "S9X")}))
    assert only_gps.sats == ("G05",) and math.isnan(only_gps.cn0_dbhz[0])


def test_event_records_are_skipped_and_bdt_files_converted() -> None:
    event = [
        "> 2020 11 29 12 40 00.5000000  4  1",
        "                                                            COMMENT",
    ]
    bdt = [line.replace("     GPS     ", "     BDT     ") for line in HEADER]
    parsed = [e for _, e in iter_epochs(bdt + event + EPOCH)]
    assert len(parsed) == 1
    assert parsed[0].gpst == calendar_to_seconds(2020, 11, 29, 12, 40, 14)


def test_malformed_input_names_the_line() -> None:
    with pytest.raises(RinexError, match=r"line 9: epoch of line 6 announced 3 satellites, found fewer"):
        list(iter_epochs(HEADER + EPOCH[:3] + EPOCH))
    with pytest.raises(RinexError, match=r"line 6: expected an epoch line"):
        list(iter_epochs(HEADER + EPOCH[1:]))
    with pytest.raises(RinexError, match=r"line 6: bad epoch time"):
        list(iter_epochs(HEADER + ["> 2020 1x 29 12 40 00.0000000  0  0"]))
    with pytest.raises(RinexError, match=r"line 9: file ends inside the epoch of line 6"):
        list(iter_epochs(HEADER + EPOCH[:3]))
    with pytest.raises(RinexError, match=r"system G has no observation 'C5Q'"):
        list(iter_epochs(HEADER + EPOCH, {"G": ("C5Q", "S5Q")}))
    with pytest.raises(RinexError, match=r"line 1: .*not 'O'"):
        list(iter_epochs([HEADER[0][:20] + "N" + HEADER[0][21:]] + HEADER[1:]))
    with pytest.raises(RinexError, match="line 3: system C: 1 observation types, header said 2"):
        list(iter_epochs([HEADER[0], HEADER[1], HEADER[2].replace("C2I S2I", "C2I    "), HEADER[4]]))


def test_systems_are_every_supported_constellation_by_default_and_unknown_letters_are_refused() -> None:
    assert ALL_SYSTEMS == "GCE"
    assert parse_systems("GCE") == "GCE" and parse_systems("CGC") == "CG"  # each once, in the order given
    for bad, named in (("GR", "R not supported"), ("x", "x not supported"), ("", "got ''")):
        with pytest.raises(ValueError, match=named):
            parse_systems(bad)
