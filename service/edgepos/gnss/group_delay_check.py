"""Which Galileo group delay a receiver's code carries, measured at known positions.

A Galileo E1 user subtracts the broadcast group delay (BGD) of the navigation record's clock pair from the
satellite clock (the ICD's model, ``galileo_group_delay`` broadcast); some receivers' Galileo code measures
as if the satellites had none (none). At a known position (a reference trajectory, or a station's surveyed
point) each Galileo pseudorange's residual with the clock *without* the BGD is BGD + the rest when the
receiver follows the ICD, and the rest alone when it does not. Each epoch's Galileo median is removed (the
receiver clock), each satellite's residuals are averaged over the epochs, and the satellites' means are
regressed on their BGDs: the slope is the fraction of the BGD the receiver's code carries, near 1 for
broadcast and near 0 for none. The satellites' other errors (orbit, clock, ionosphere, multipath) are the
regression's noise: a few minutes and five or more satellites with BGDs a metre or more apart give a slope
that separates the two (docs/gnss.md, "The receivers' Galileo group delay").

``python -m edgepos.gnss.group_delay_check --obs OBS --nav NAV (--reference CSV | --header-position)
[--epochs A:B]`` prints each satellite's mean residual and BGD, the slope with its standard error, and the
setting it points to.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.differential import base_position
from edgepos.gnss.measurements import Atmosphere, prepare_epoch, without_group_delay
from edgepos.gnss.orbits import SPEED_OF_LIGHT, BroadcastOrbits, group_delay_factors, sagnac_range
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, ObservationEpoch, read_epochs, read_header
from edgepos.gnss.spp import epoch_range, epochs_at_reference, read_reference

GALILEO_CODES = {"E": DEFAULT_CODES["E"]}
_E1 = np.array([group_delay_factors("E", DEFAULT_CODES["E"][0])])


@dataclass(frozen=True)
class GroupDelayCheck:
    """Per Galileo satellite its mean residual without the BGD (m, the epochs' Galileo median removed),
    its BGD (m, the records' own clock pairs', averaged over the epochs) and epochs; the slope of the means
    on the BGDs with its standard error."""

    sats: tuple[str, ...]
    mean_residual_m: np.ndarray
    bgd_m: np.ndarray
    epochs: np.ndarray
    slope: float
    slope_std: float

    @property
    def setting(self) -> str:
        """The ``galileo_group_delay`` the slope is nearer to."""
        return "broadcast" if self.slope >= 0.5 else "none"


def check(
    epochs: Iterable[tuple[ObservationEpoch, np.ndarray]],
    orbits: BroadcastOrbits,
    atmosphere: Atmosphere,
    mask_rad: float = math.radians(10.0),
    min_epochs: int = 30,
) -> GroupDelayCheck:
    """The check over ``epochs`` (each with the receiver's ECEF position, m). Satellites seen in fewer than
    ``min_epochs`` epochs are left out; ValueError when fewer than three remain."""
    sums: dict[str, list[float]] = {}
    no_delay = without_group_delay("none")
    for epoch, position in epochs:
        prs, _ = prepare_epoch(epoch, orbits, GALILEO_CODES, no_delay)
        if len(prs) < 2:
            continue
        iono, tropo, elevation, _ = atmosphere.delays(position, prs)
        residual = (
            prs.pseudorange_m
            - sagnac_range(prs.sat_position, position)
            - iono
            - tropo
            + SPEED_OF_LIGHT * prs.sat_clock_s
        )
        keep = elevation > mask_rad
        if np.count_nonzero(keep) < 2:
            continue
        residual = residual - np.median(residual[keep])
        index = orbits.select(prs.systems, prs.prns, prs.gpst)
        bgd = orbits.group_delay(index, np.repeat(_E1, len(index), axis=0)) * SPEED_OF_LIGHT
        for sat, value, delay, used in zip(prs.sats, residual, bgd, keep, strict=True):
            if used:
                total = sums.setdefault(sat, [0.0, 0.0, 0.0])
                total[0] += float(value)
                total[1] += float(delay)
                total[2] += 1.0
    rows = sorted((sat, t) for sat, t in sums.items() if t[2] >= min_epochs)
    if len(rows) < 3:
        raise ValueError(f"{len(rows)} Galileo satellites seen in {min_epochs} epochs or more: 3 are needed")
    counts = np.array([t[2] for _, t in rows])
    means = np.array([t[0] for _, t in rows]) / counts
    bgds = np.array([t[1] for _, t in rows]) / counts
    design = np.column_stack([np.ones(len(rows)), bgds])
    coefficients, _, rank, _ = np.linalg.lstsq(design, means, rcond=None)
    if rank < 2:
        raise ValueError("the satellites' BGDs are all the same: the slope is undetermined")
    variance = float(np.sum((means - design @ coefficients) ** 2)) / (len(rows) - 2)
    slope_std = math.sqrt(variance * np.linalg.inv(design.T @ design)[1, 1])
    sats = tuple(sat for sat, _ in rows)
    return GroupDelayCheck(sats, means, bgds, counts, float(coefficients[1]), slope_std)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m edgepos.gnss.group_delay_check", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--obs", required=True, help="RINEX 3 observation file")
    parser.add_argument("--nav", required=True, help="RINEX 3 navigation file")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--reference", help="reference CSV: week, seconds of week, lat, lon, height")
    where.add_argument(
        "--header-position",
        action="store_true",
        help="a static receiver at its header's position (APPROX POSITION XYZ + antenna delta)",
    )
    parser.add_argument("--epochs", default="0:1000000", help="epochs A:B (0-based, B excluded)")
    args = parser.parse_args(argv)
    first, stop = epoch_range(args.epochs)
    navigation = read_navigation(args.nav)
    orbits = BroadcastOrbits(navigation.ephemerides)
    atmosphere = Atmosphere.from_navigation(navigation)
    if args.header_position:
        position = base_position(read_header(args.obs))
        epochs = (
            (epoch, position)
            for number, epoch in enumerate(read_epochs(args.obs, GALILEO_CODES))
            if first <= number < stop
        )
    else:
        ref_time, ref_ecef = read_reference(args.reference)
        epochs = (
            (epoch, ref_ecef[row])
            for epoch, row in epochs_at_reference(args.obs, GALILEO_CODES, ref_time, first, stop)
        )
    try:
        result = check(epochs, orbits, atmosphere)
    except ValueError as error:
        print(f"group delay check: {error}", file=sys.stderr)
        return 2
    print("sat   epochs  mean residual m   BGD m")
    for sat, count, mean, bgd in zip(result.sats, result.epochs, result.mean_residual_m, result.bgd_m):
        print(f"{sat}  {int(count):6d}  {mean:15.2f}  {bgd:6.2f}")
    print(
        f"slope {result.slope:.2f} +- {result.slope_std:.2f} (1: the ICD's BGD in the code, 0: none): "
        f"galileo_group_delay {result.setting}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
