"""Paths of the project's copy of the Rokubun recording (tests/data/gnss-rover), shared by the GNSS tests."""

from __future__ import annotations

from pathlib import Path

DATA = Path(__file__).resolve().parent.parent / "data" / "gnss-rover"
OBS = DATA / "rover-0-5min.rnx"
NAV = DATA / "broadcast-nav.rnx"
REFERENCE = DATA / "reference-0-5min.csv"
