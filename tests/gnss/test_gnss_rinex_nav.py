"""RINEX 3 navigation reader on the real broadcast file and on malformed snippets."""

from __future__ import annotations

import math

import pytest
from edgepos.gnss.rinex_nav import NavigationData, RinexError, parse_navigation
from edgepos.gnss.timesys import calendar_to_seconds

HEADER = [
    "     3.04           NAVIGATION DATA     MIXED               RINEX VERSION / TYPE",
    "GPSA   1.4901D-08 -1.4901D-08 -5.9605D-08  1.1921D-07       IONOSPHERIC CORR    ",
    "GPSB   1.2083D+05 -2.2938D+05 -6.5536D+04  8.5197D+05       IONOSPHERIC CORR    ",
    "    18                                                      LEAP SECONDS        ",
    "                                                            END OF HEADER       ",
]
G02 = [
    "G02 2020 11 29 12 00 00-5.484190769494D-04-4.547473508865D-12 0.000000000000D+00",
    "     5.100000000000D+01-8.671875000000D+01 4.265177661770D-09-1.954935102391D+00",
    "    -4.250556230545D-06 2.012822777033D-02 1.017004251480D-05 5.153566459656D+03",
    "     4.320000000000D+04 3.036111593246D-07-3.849493243759D-01 2.980232238770D-07",
    "     9.615670989807D-01 1.772812500000D+02-1.581532751336D+00-7.564600810273D-09",
    "     8.464638300447D-11 1.000000000000D+00 2.134000000000D+03 0.000000000000D+00",
    "     2.000000000000D+00 0.000000000000D+00-1.769512891769D-08 5.100000000000D+01",
    "     4.111800000000D+04",
]


def test_header_of_real_file(nav: NavigationData) -> None:
    assert nav.version == pytest.approx(3.04)
    assert nav.leap_seconds == 18
    alpha, beta = nav.klobuchar_gps
    assert alpha == pytest.approx((1.4901e-08, -1.4901e-08, -5.9605e-08, 1.1921e-07))
    assert beta == pytest.approx((1.2083e05, -2.2938e05, -6.5536e04, 8.5197e05))


def test_records_of_real_file(nav: NavigationData) -> None:
    systems = [e.system for e in nav.ephemerides]
    assert systems.count("G") == 24 and systems.count("C") == 23 and systems.count("E") == 82
    assert nav.skipped == {"R": 44, "S": 71}
    g02 = next(e for e in nav.ephemerides if e.sat == "G02")
    assert g02.toe == pytest.approx(2134 * 604800 + 43200.0)
    assert g02.sqrt_a == pytest.approx(5153.566459656)
    assert g02.tgd1 == pytest.approx(-1.769512891769e-08)
    assert g02.fit_interval_s == 4 * 3600.0
    c05 = next(e for e in nav.ephemerides if e.sat == "C05")
    # BeiDou epochs are BDT: 2020-11-29 11:00:00 BDT is 11:00:14 GPST; BDT week 778 = GPS week 2134.
    assert c05.toc == calendar_to_seconds(2020, 11, 29, 11, 0, 14)
    assert c05.toe == pytest.approx(2134 * 604800 + 39600.0 + 14.0)
    assert c05.toe_sow == 39600.0 and c05.week == 778
    assert (c05.tgd1, c05.tgd2) == pytest.approx((-3e-10, -9e-09))


def test_d_exponent_and_blank_trailing_fields() -> None:
    nav = parse_navigation(HEADER + G02)
    (eph,) = nav.ephemerides
    assert eph.af0 == pytest.approx(-5.484190769494e-04)
    assert eph.e == pytest.approx(2.012822777033e-02)
    assert eph.fit_interval_s == 4 * 3600.0  # blank fit interval -> the 4 h default
    assert nav.leap_seconds == 18


def test_blank_required_field_names_line_and_field() -> None:
    broken = list(G02)
    broken[2] = "    -4.250556230545D-06                    1.017004251480D-05 5.153566459656D+03"
    with pytest.raises(RinexError, match=r"line 8: G02: field e is blank"):
        parse_navigation(HEADER + broken)


def test_garbage_number_names_line() -> None:
    broken = list(G02)
    broken[3] = "     4.32000000000XD+04 3.036111593246D-07-3.849493243759D-01 2.980232238770D-07"
    with pytest.raises(RinexError, match=r"line 9: orbit field 1: cannot read number"):
        parse_navigation(HEADER + broken)


def test_truncated_record_and_missing_header_end() -> None:
    with pytest.raises(RinexError, match=r"line 6: G02 record has 5 lines, expected 8"):
        parse_navigation(HEADER + G02[:5])
    with pytest.raises(RinexError, match="END OF HEADER"):
        parse_navigation(HEADER[:-1])
    with pytest.raises(RinexError, match=r"line 1: .*not 'N'"):
        parse_navigation([HEADER[0][:20] + "O" + HEADER[0][21:]] + HEADER[1:])


def test_unexpected_line_in_data_section() -> None:
    with pytest.raises(RinexError, match=r"line 14: expected a record start"):
        parse_navigation(HEADER + G02 + ["this is not a record"])


def test_glonass_record_is_skipped_not_misread() -> None:
    glonass = [
        "R04 2020 11 29 10 15 00 6.354972720146e-05 1.818989403546e-12 3.600000000000e+04",
        "     2.131593261719e+03-1.091775894165e-01 9.313225746155e-10 0.000000000000e+00",
        "     2.240136865234e+04 1.647252082825e+00-1.862645149231e-09 6.000000000000e+00",
        "     1.202249755859e+04-3.055185317993e+00-1.862645149231e-09 0.000000000000e+00",
    ]
    nav = parse_navigation(HEADER + glonass + G02)
    assert [e.sat for e in nav.ephemerides] == ["G02"]
    assert nav.skipped == {"R": 1}
    assert math.isfinite(nav.ephemerides[0].m0)
