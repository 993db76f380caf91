"""Ready-made simulation scenarios: a truth trajectory, the RSUs along it and the sensor noise.

:func:`rsu_imu_paper_scenario` rebuilds sec. 5 of the RSU + IMU 2IMM-CKF paper. The paper gives a
two-way road of four 3.75 m lanes, RSUs every 100 m staggered on both sides 2 m off the road,
a 160 m communication radius, the noise levels and the motion table (Table 1); where it is vague
this module chooses, so that every manoeuvre lands in a lane centre:

* Lanes run along x. Eastbound lanes are centred at y = 0 (the start lane, so the vehicle starts
  at the origin as the paper says) and y = 3.75; westbound lanes at y = 7.5 and y = 11.25. Road
  edges are at y = -1.875 and y = 13.125.
* RSUs stand 2 m beyond each edge (y = -3.875 south, y = 15.125 north), every 100 m, the north row
  shifted by 50 m: south at x = -300, -200, ..., 600, north at x = -250, -150, ..., 650. Ids name
  the side and the x position: "S+000", "N-250".
* Lane changes shift by exactly one lane width (3.75 m) with a sin^2 heading profile; the U-turn
  goes from the inner eastbound lane (y = 3.75) to the outer westbound lane (y = 11.25), a 7.5 m
  shift, with a bell-shaped turn rate (see :mod:`edgepos.sim.trajectory`).
* Table 1's westbound accelerations are read as speed changes: "-4 m/s^2" at 22.7 s and "-5 m/s^2"
  at 30 s are written in world x, i.e. speeding up westbound (+4 and +5 along the heading), and the
  "3 m/s^2 deceleration" at 35.6 s is -3 along the heading. "Left lane" westbound is towards -y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from edgepos.pipelines.base import Rsu
from edgepos.sim.trajectory import Accelerate, Cruise, LaneChange, Segment, Truth, UTurn, build_trajectory

LANE_WIDTH = 3.75
#: Lane centres (m): eastbound start lane, eastbound inner, westbound inner, westbound outer.
LANE_CENTRES = (0.0, 3.75, 7.5, 11.25)
#: Southern and northern road edges (m).
ROAD_EDGES = (-1.875, 13.125)
RSU_SETBACK = 2.0
RSU_SPACING = 100.0
#: Along-road shift (m) of the northern RSU row against the southern one.
RSU_STAGGER = 50.0

#: Table 1 of the paper as segments, starting eastbound at 10 m/s (end time in the comments).
PAPER_SEGMENTS: tuple[Segment, ...] = (
    Cruise(4.0),  # 4.0 s, 10 m/s
    Accelerate(4.0, 2.5),  # 8.0 s, 20 m/s
    LaneChange(4.0, LANE_WIDTH),  # 12.0 s, to the inner eastbound lane (y = 3.75)
    Accelerate(2.5, 2.0),  # 14.5 s, 25 m/s
    Accelerate(4.0, -5.0),  # 18.5 s, 5 m/s
    UTurn(4.2, 2.0 * LANE_WIDTH),  # 22.7 s, left U-turn into the outer westbound lane (y = 11.25)
    Accelerate(2.5, 4.0),  # 25.2 s, 15 m/s
    LaneChange(4.8, LANE_WIDTH),  # 30.0 s, left = -y when westbound: to y = 7.5
    Accelerate(2.0, 5.0),  # 32.0 s, 25 m/s
    LaneChange(3.6, -LANE_WIDTH),  # 35.6 s, right: back to y = 11.25
    Accelerate(3.0, -3.0),  # 38.6 s, 16 m/s
    Cruise(1.4),  # 40.0 s
)


@dataclass(frozen=True)
class Scenario:
    """A simulation run's inputs: ground truth, RSU sites and sensor noise (1-sigma, SI units).

    Each epoch the vehicle hears at most ``max_rsus`` RSUs, the nearest within ``comm_radius``.
    """

    name: str
    truth: Truth
    rsus: tuple[Rsu, ...]
    period: float
    range_std: float
    bearing_std: float
    gyro_std: float
    comm_radius: float = 160.0
    max_rsus: int = 4

    def __post_init__(self) -> None:
        sampled = float(self.truth.t[1] - self.truth.t[0])
        if not math.isclose(sampled, self.period, rel_tol=1e-9):
            raise ValueError(
                f"Scenario {self.name!r}: period {self.period} s but truth sampled every {sampled} s"
            )

    @property
    def initial_state(self) -> tuple[float, ...]:
        """The truth at t = 0 as the 8-state [xp, xv, xa, yp, yv, ya, phi, omega]."""
        truth = self.truth
        return tuple(
            float(value[0])
            for value in (
                truth.x,
                truth.vx,
                truth.ax,
                truth.y,
                truth.vy,
                truth.ay,
                truth.heading,
                truth.yaw_rate,
            )
        )


def staggered_rsus(x_start: float, x_end: float) -> tuple[Rsu, ...]:
    """RSUs of the paper's road: every RSU_SPACING m on the south side from ``x_start`` to ``x_end``
    and on the north side RSU_STAGGER m further along."""
    count = math.floor((x_end - x_start) / RSU_SPACING + 1e-9) + 1
    south_y = ROAD_EDGES[0] - RSU_SETBACK
    north_y = ROAD_EDGES[1] + RSU_SETBACK
    rsus = []
    for index in range(count):
        south_x = x_start + index * RSU_SPACING
        north_x = south_x + RSU_STAGGER
        rsus.append(Rsu(id=f"S{round(south_x):+04d}", x=south_x, y=south_y))
        rsus.append(Rsu(id=f"N{round(north_x):+04d}", x=north_x, y=north_y))
    return tuple(rsus)


def rsu_imu_paper_scenario() -> Scenario:
    """The RSU + IMU paper's sec. 5 scenario: 40 s at T = 0.05 s, Table 1's motion, 20 RSUs."""
    period = 0.05
    truth = build_trajectory(
        PAPER_SEGMENTS, start=(0.0, LANE_CENTRES[0]), heading0=0.0, speed0=10.0, period=period
    )
    return Scenario(
        name="rsu-imu-paper",
        truth=truth,
        rsus=staggered_rsus(-300.0, 600.0),
        period=period,
        range_std=0.6,
        bearing_std=math.radians(0.5),
        gyro_std=math.radians(0.3),
        comm_radius=160.0,
        max_rsus=4,
    )
