"""Filter-based solution separation: a bank of cheap sub-filters, one per RSU-excluded hypothesis.

An epoch-wise test on the posterior (``core.integrity.protect``) takes the prior as fault-free, so a
fault that grows into the estimate over several epochs below its threshold escapes it. Here the
hypotheses run over time (Brenner, "Integrated GPS/inertial fault detection availability",
Navigation 43(2), 1996; Joerger and Pervan, "Kalman filter-based integrity monitoring against sensor
faults", JGCD 36(2), 2013; ARAIM's multiple hypothesis solution separation, Blanch et al., ION GNSS
2012): a reference filter uses every RSU the pipeline uses, and sub-filter i the same measurements
except RSU i's, from the epoch RSU i was first heard. Under hypothesis i (RSU i faulty, all else
sound) sub-filter i never saw the fault, however slowly it grew.

* Each filter is a linear constant-acceleration (white-jerk) model on (x, vx, ax, y, vy, ay) in the
  site frame, with range and bearing linearised at its own prediction (an EKF): one batched numpy
  update for the whole bank, the RSU a sub-filter leaves out entering with zero rows (no gain, exact).
* Detection: the separation d_i = x_i - x_0 of sub-filter i from the reference has covariance
  P_i - P_0 without a fault (the reference is the efficient estimate of a superset of the data), so
  q_i = d_i^T (P_i - P_0)^-1 d_i is chi-square with 2 degrees of freedom; a fault in RSU i is
  detected when q_i exceeds the (1 - P_FA / N) quantile.
* Protection level of the reported fix x (any estimator, here the pipeline's IMM): under hypothesis
  i, |x - x_true| <= |x - x_i| + |x_i - x_true| and x_i is fault-free, so
  PL_i = |x - x_i| + R(P_i, p_i) with p_i = (risk / 2 / N) / P_fault, and
  PL = max(R(P, risk / 2), |x - x_0| + R(P_0, risk / 2), max_i PL_i), R(C, p) the exact radial bound
  of ``core.integrity`` (the first two: fault-free, through the fix's and through the reference's
  covariance, both taken so that neither needs to be trusted alone).
  The union bound gives P(error > PL) <= risk / 2 + sum_i P_fault p_i = risk.

A failed test excludes the RSU for a while (from the pipeline's filter and the whole bank). No
sub-filter is dropped for it: under any single fault the sub-filter that never saw it is still there,
so the bound holds even when the test pointed at the wrong RSU (with three RSUs a fault in one also
moves the others' sub-filters), and the fix is in alarm only for a protection level above the alert
limit or a failed test that could not be acted on. A sub-filter is dropped once RSU i is no longer used and its data no longer weigh on the reference
(its position covariance within ``CONVERGED`` of the reference's): what RSU i contributed to the
estimate then is below a percent of its own error. Plain arrays, so a session stores the bank as
bytes and reads it back bit for bit (``to_bytes`` / ``from_bytes``).
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import ModuleType

import numpy as np

from edgepos.core.integrity import (
    ALARM,
    OK,
    UNAVAILABLE,
    IntegrityBudget,
    Protection,
    new_protection,
    radial_bound,
    radial_factor_table,
    test_threshold,
)

#: State order of every filter: x, vx, ax, y, vy, ay (site frame, m, m/s, m/s^2).
DIM = 6
_POS = [0, 3]
#: A sub-filter whose position covariance exceeds the reference's by less than this fraction (trace)
#: carries no weight any more and is dropped when its RSU is not in use.
CONVERGED = 0.01
#: Indices into the epoch's scalars the compiled kernels read and write (``kernels_integrity.bank_epoch``,
#: ``bank_protect``): the jerk density of the prediction, the test threshold, the fix's x, y and
#: covariance xx, xy, yy; then what the kernels write: the protection level, the worst failed sub-filter
#: (-1: none) and its statistic, and how many sub-filters ``prune`` would drop; ``bank_epoch`` also reads
#: the length of a radial factor table (what follows the scalars in its ``work`` vector). One array:
#: numba's dispatch costs per argument.
JERK, THRESHOLD, FIX_X, FIX_Y, FIX_XX, FIX_XY, FIX_YY, LEVEL, WORST, STATISTIC, DROPPABLE, TABLE = range(12)
SCALARS = TABLE + 1
#: What ``kernels_integrity.bank_epoch`` returns instead of the protection level when a test failed (the
#: outcome is in the scalars) or the update did (the bank is predicted only); levels are never negative.
TEST_FAILED, UPDATE_FAILED = -2.0, -1.0
_HEADER = struct.Struct("<4sBHdH")  # magic, version, K, t, the exclusions' count
_LENGTH = struct.Struct("<H")
_EXCLUSION = struct.Struct("<Hd")
_FLOAT = np.dtype("<f8")
_MAGIC = b"EPIB"
_VERSION = 1


@dataclass(frozen=True)
class RangeBearing:
    """One RSU's measurement of an epoch: range (m) and bearing from the RSU to the vehicle (rad, from
    the site x axis), with their standard deviations."""

    rsu_id: str
    rsu_x: float
    rsu_y: float
    range: float
    bearing: float
    range_std: float
    bearing_std: float


@dataclass
class SeparationBank:
    """The reference filter (row 0) and one sub-filter per excluded RSU (rows 1..), in plain arrays."""

    ids: list[str]  # ids[0] == "" (the reference); ids[i]: the RSU sub-filter i leaves out
    means: np.ndarray  # (K, 6)
    covs: np.ndarray  # (K, 6, 6)
    t: float
    excluded: dict[str, float] = field(default_factory=dict)  # RSU id -> time (s) its exclusion ends
    # what the last epoch's kernel call needed (not state: rebuilt after decoding, or when it no longer fits)
    _plan: _Plan | None = field(default=None, init=False, repr=False, compare=False)

    @staticmethod
    def start(mean: np.ndarray, cov: np.ndarray, t: float) -> SeparationBank:
        """A bank with only the reference, from an estimate (x, vx, ax, y, vy, ay) and its covariance."""
        return SeparationBank(
            [""], np.array(mean, dtype=float)[None, :], np.array(cov, dtype=float)[None, :, :], t
        )

    def predict(self, t: float, jerk_density: float) -> None:
        """Every filter to time ``t`` with white jerk of spectral density ``jerk_density`` (m^2/s^5) per axis."""
        dt = t - self.t
        if dt <= 0.0:
            return
        if _compiled():
            bank_predict = _kernels().bank_predict

            self.means = np.ascontiguousarray(self.means)
            self.covs = np.ascontiguousarray(self.covs)
            bank_predict(self.means, self.covs, dt, jerk_density)
            self.t = t
            return
        self.predict_reference(dt, jerk_density)
        self.t = t

    def predict_reference(self, dt: float, jerk_density: float) -> None:
        """The numpy form of :meth:`predict`, over ``dt`` s (the reference the compiled kernel is tested
        against)."""
        transition, noise = _transition(dt, jerk_density)
        self.means = self.means @ transition.T
        self.covs = transition @ self.covs @ transition.T + noise

    def spawn(self, rsu_ids: Sequence[str]) -> None:
        """A sub-filter for every RSU in ``rsu_ids`` without one: a copy of the reference, which has not
        used that RSU yet (call before the update that first uses it)."""
        if len(self.ids) > len(rsu_ids) and set(rsu_ids).issubset(self.ids):
            return
        new = [rsu for rsu in dict.fromkeys(rsu_ids) if rsu not in self.ids]
        if not new:
            return
        count = len(self.ids)
        self.ids = self.ids + new
        # filled in place (fewer numpy calls than concatenating copies: this runs at a batch's first epochs)
        means = np.empty((count + len(new), DIM))
        covs = np.empty((count + len(new), DIM, DIM))
        means[:count], covs[:count] = self.means, self.covs
        means[count:], covs[count:] = self.means[0], self.covs[0]
        self.means, self.covs = means, covs

    def update(self, measurements: Sequence[RangeBearing]) -> None:
        """One joint EKF update of every filter; sub-filter i skips RSU ids[i]'s rows (on the compiled
        kernel when the kernels are enabled, ``core.kernels_integrity``; else, or if it fails, numpy)."""
        self.update_arrays(*_arrays(measurements))

    def update_arrays(
        self,
        rsu_ids: Sequence[str],
        positions: np.ndarray,
        observed: np.ndarray,
        range_std: np.ndarray,
        bearing_std: np.ndarray,
    ) -> None:
        """:meth:`update` with the measurements as arrays (what the pipeline has built for its own filter
        already): the RSUs' ids and positions (n, 2), the observed range and bearing (n, 2) and their
        standard deviations (n,) each."""
        if not rsu_ids:
            return
        if _compiled():
            bank_update = _kernels().bank_update

            means, covs = np.ascontiguousarray(self.means), np.ascontiguousarray(self.covs)
            if (
                bank_update(means, covs, self._owners(rsu_ids), positions, observed, range_std, bearing_std)
                == 0
            ):
                self.means, self.covs = means, covs
                return
        self._update_reference(rsu_ids, _data(positions, observed, range_std, bearing_std))

    def update_reference(self, measurements: Sequence[RangeBearing]) -> None:
        """The numpy form of :meth:`update` (the reference the compiled kernel is tested against)."""
        if measurements:
            ids, *arrays = _arrays(measurements)
            self._update_reference(ids, _data(*arrays))

    def _update_reference(self, rsu_ids: Sequence[str], data: np.ndarray) -> None:
        rows = 2 * len(rsu_ids)
        # every filter linearised at the reference's prediction: the bank is then one linear system, in
        # which the separations' covariances P_i - P_0 hold exactly. H acts on x and y only.
        dx = self.means[0, 0] - data[:, 0]
        dy = self.means[0, 3] - data[:, 1]
        distance = np.maximum(np.hypot(dx, dy), 1e-3)
        r2 = distance * distance
        h_xy = np.empty((rows, 2))  # rows: range, bearing of each RSU; columns: x, y
        h_xy[0::2, 0], h_xy[0::2, 1] = dx / distance, dy / distance
        h_xy[1::2, 0], h_xy[1::2, 1] = -dy / r2, dx / r2
        residual = np.empty(rows)  # z - h(x_0)
        residual[0::2] = data[:, 2] - distance
        residual[1::2] = np.remainder(data[:, 3] - np.arctan2(dy, dx) + math.pi, math.tau) - math.pi
        # sub-filter i leaves RSU ids[i]'s rows out: zero rows of H and of the innovation add nothing
        keep = np.repeat(np.array([[m != rsu for m in rsu_ids] for rsu in self.ids]), 2, axis=1)
        offsets = self.means[:, _POS] - self.means[0, _POS]  # (K, 2)
        z = (residual[None, :] - offsets @ h_xy.T) * keep  # z - h(x_0) - H (x_i - x_0)
        h = h_xy[None, :, :] * keep[:, :, None]  # (K, rows, 2)
        pht = self.covs[:, :, _POS] @ h.transpose(0, 2, 1)  # P H^T (K, 6, rows)
        s = h @ pht[:, _POS, :]
        s[:, range(rows), range(rows)] += np.square(data[:, 4:6]).reshape(rows)
        gain = np.linalg.solve(s, pht.transpose(0, 2, 1)).transpose(0, 2, 1)  # P H^T S^-1 (S symmetric)
        self.means = self.means + np.einsum("kij,kj->ki", gain, z)
        covs = self.covs - gain @ pht.transpose(0, 2, 1)
        self.covs = 0.5 * (covs + covs.transpose(0, 2, 1))

    def prune(self, in_use: Sequence[str]) -> None:
        """Drop the sub-filters whose RSU is not in ``in_use`` and no longer weighs on the reference."""
        if _covered(self.ids, in_use):
            return
        # on Python floats: a handful of sub-filters, every epoch while an RSU out of view still weighs
        # (numpy's per-call overhead was most of this method's time); the same double arithmetic
        xx, yy = self.covs[:, 0, 0].tolist(), self.covs[:, 3, 3].tolist()
        reference = xx[0] + yy[0]
        bound = CONVERGED * reference
        keep = [
            i
            for i, rsu in enumerate(self.ids)
            if i == 0 or rsu in in_use or (xx[i] + yy[i]) - reference > bound
        ]
        if len(keep) < len(self.ids):
            self.ids = [self.ids[i] for i in keep]
            rows = np.array(keep, dtype=np.intp)  # take(): far cheaper than fancy indexing with a list
            self.means, self.covs = self.means.take(rows, 0), self.covs.take(rows, 0)

    def exclude(self, rsu_id: str, until: float) -> None:
        """RSU ``rsu_id`` failed its test: the pipeline and the bank leave it out until ``until`` (s). Every
        sub-filter stays, its own too (it never saw the fault), so the protection level keeps bounding what
        the fault left in the estimate until that has faded, even if the test pointed at the wrong RSU."""
        self.excluded[rsu_id] = until

    def excluded_now(self, t: float) -> set[str]:
        """The RSUs left out at time ``t``; forgets the exclusions that have ended."""
        for rsu in [rsu for rsu, until in self.excluded.items() if until <= t]:
            del self.excluded[rsu]
        return set(self.excluded)

    def separations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per sub-filter: sqrt(q_i) (chi with 2 dof without a fault; 0 while P_i - P_0 is singular, as right
        after it starts), its position (K-1, 2) and position covariance as (K-1, 3) rows (xx, xy, yy)."""
        if _compiled():
            bank_separations = _kernels().bank_separations

            out = np.empty((len(self.ids) - 1, 6))
            bank_separations(np.ascontiguousarray(self.means), np.ascontiguousarray(self.covs), out)
            return out[:, 0], out[:, 1:3], out[:, 3:6]
        return self.separations_reference()

    def separations_reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The numpy form of :meth:`separations`."""
        px, py = self.means[:, 0], self.means[:, 3]
        xx, xy, yy = self.covs[:, 0, 0], self.covs[:, 0, 3], self.covs[:, 3, 3]
        dx, dy = px[1:] - px[0], py[1:] - py[0]
        a, b, c = xx[1:] - xx[0], xy[1:] - xy[0], yy[1:] - yy[0]
        det = a * c - b * b
        regular = (a > 0.0) & (c > 0.0) & (det > 1e-12 * a * c)
        q = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / np.where(regular, det, 1.0)
        statistic = np.sqrt(np.maximum(np.where(regular, q, 0.0), 0.0))
        return statistic, np.column_stack([px[1:], py[1:]]), np.column_stack([xx[1:], xy[1:], yy[1:]])

    def _owners(self, rsu_ids: Sequence[str]) -> np.ndarray:
        """Per measurement, the sub-filter that leaves it out (-1: none), for the compiled kernels."""
        return _flags(tuple(self.ids), tuple(rsu_ids))[: len(rsu_ids)]

    def _flags(self, rsu_ids: Sequence[str]) -> np.ndarray:
        """The compiled ``bank_epoch``'s flags: the measurements' owners, then per filter 1 if its RSU is
        excluded already."""
        flags = _flags(tuple(self.ids), tuple(rsu_ids))
        if not self.excluded:
            return flags
        flags = flags.copy()
        flags[len(rsu_ids) :] = [rsu in self.excluded for rsu in self.ids]
        return flags

    def step(
        self,
        t: float,
        jerk_density: float,
        rsu_ids: Sequence[str],
        arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        fix: Sequence[float],
        budget: IntegrityBudget,
    ) -> tuple[Protection, str | None]:
        """One epoch: :meth:`predict` to ``t``, :meth:`spawn` and :meth:`update_arrays` with the epoch's RSUs
        (``arrays``: their positions, observed range and bearing, range and bearing standard deviations),
        then :meth:`protect_fix` for the fix (x, y, and its covariance's xx, xy, yy); :meth:`epoch` with the
        fix as a 2-vector and its 2x2 covariance."""
        mean = np.array([fix[0], fix[1]], dtype=float)
        cov = np.array([[fix[2], fix[3]], [fix[3], fix[4]]], dtype=float)
        return self.epoch(t, jerk_density, rsu_ids, arrays, mean, cov, (0, 1), budget)

    def epoch(
        self,
        t: float,
        jerk_density: float,
        rsu_ids: Sequence[str],
        arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        mean: np.ndarray,
        cov: np.ndarray,
        position: tuple[int, int],
        budget: IntegrityBudget,
        prune: bool = False,
    ) -> tuple[Protection, str | None]:
        """:meth:`step` for the fix of an estimate whose x and y are ``mean[position]`` with covariance
        ``cov`` (what the pipeline has: its output Gaussian, read in place). On one compiled kernel call when
        the kernels are enabled (``kernels_integrity.bank_epoch``), with what only changes with the RSUs in
        use, the sub-filters, the exclusions or the options kept from the epoch before (``_Plan``); else
        the numpy steps. ``prune``: when no test failed (no RSU to exclude), :meth:`prune` for ``rsu_ids``
        too, after the outcome (the kernel counts what it would drop, so the usual epoch skips it)."""
        plan = self.plan_for(rsu_ids, jerk_density, budget, position)
        if plan is None:
            if not _compiled():  # (a plan exists only when the kernels are enabled)
                x, y = position
                fix = (float(mean[x]), float(mean[y]), float(cov[x, x]), float(cov[x, y]), float(cov[y, y]))
                self.spawn(rsu_ids)
                self.predict(t, jerk_density)
                self.update_arrays(rsu_ids, *arrays)
                return self._pruned(self.protect_fix(fix, budget), rsu_ids, prune)
            self.spawn(rsu_ids)
            plan = self._plan = _Plan.make(self, rsu_ids, jerk_density, budget, position)
        scalars = plan.scalars
        dt = t - self.t
        if not self.t > t:  # self.t = max(t, self.t), NaN alike, without the builtin's call (every epoch)
            self.t = t
        # the bank's arrays are C-contiguous float64 as every method leaves them; the estimate's are read as
        # they come (the pipeline's are fresh C-contiguous float64 arrays; another layout compiles once)
        level = plan.kernel(self.means, self.covs, scalars, dt, *arrays, mean, cov)
        if 0.0 <= level <= budget.alert_limit:  # the usual outcome: every test passed, within the limit
            # prune drops nothing when every sub-filter's RSU is in use or the kernel found none converged
            if prune and not plan.covered and scalars[DROPPABLE]:
                self.prune(rsu_ids)
            return new_protection(level, OK), None
        if level == UPDATE_FAILED:
            self._update_reference(rsu_ids, _data(*arrays))  # predicted already: the numpy update, the bound
            x, y = position
            fix = (float(mean[x]), float(mean[y]), float(cov[x, x]), float(cov[x, y]), float(cov[y, y]))
            return self._pruned(self.protect_fix(fix, budget), rsu_ids, prune)
        return self._pruned(self._protection(scalars, budget), rsu_ids, prune)

    def plan_for(
        self, rsu_ids: Sequence[str], jerk_density: float, budget: IntegrityBudget, position: tuple[int, int]
    ) -> _Plan | None:
        """The plan of the epoch before when it serves an epoch with these RSUs in use and options (the same
        sub-filters, exclusions, budget, jerk density and fix layout), else None (:meth:`epoch` makes one)."""
        plan = self._plan
        if (
            plan is None
            or plan.ids is not self.ids
            or plan.rsu_ids != rsu_ids
            or plan.budget is not budget
            or plan.jerk_density != jerk_density
            or plan.position != position
            or ((plan.excluded or self.excluded) and plan.excluded != self.excluded.keys())
        ):
            return None
        return plan

    def _pruned(
        self, outcome: tuple[Protection, str | None], rsu_ids: Sequence[str], prune: bool
    ) -> tuple[Protection, str | None]:
        """``outcome``, after :meth:`prune` for ``rsu_ids`` when asked to and no test failed."""
        if prune and outcome[1] is None:
            self.prune(rsu_ids)
        return outcome

    def _protection(self, scalars: np.ndarray, budget: IntegrityBudget) -> tuple[Protection, str | None]:
        """The outcome the compiled ``bank_protect`` wrote into ``scalars`` (level, worst failed sub-filter,
        statistic)."""
        values = scalars[:SCALARS].tolist()
        level = values[LEVEL]
        if not math.isfinite(level):
            return Protection(None, UNAVAILABLE), None
        state = ALARM if level > budget.alert_limit else OK
        worst = int(values[WORST])
        if worst > 0:
            protection = Protection(
                level, state, faulty=worst - 1, statistic=values[STATISTIC], threshold=values[THRESHOLD]
            )
            return protection, self.ids[worst]
        return Protection(level, state), None

    def protect(
        self, position: Sequence[float] | np.ndarray, position_cov: np.ndarray, budget: IntegrityBudget
    ) -> tuple[Protection, str | None]:
        """``protect_with_bank`` for this bank, on one compiled kernel when the kernels are enabled (the
        module function is the numpy reference it is tested against)."""
        fix = (
            float(position[0]),
            float(position[1]),
            float(position_cov[0, 0]),
            float(position_cov[0, 1]),
            float(position_cov[1, 1]),
        )
        return self.protect_fix(fix, budget)

    def protect_fix(self, fix: Sequence[float], budget: IntegrityBudget) -> tuple[Protection, str | None]:
        """:meth:`protect` for a fix given as x, y and its covariance's xx, xy, yy (on the compiled kernel)."""
        if not _compiled():
            position = np.array(fix[:2], dtype=float)
            position_cov = np.array([[fix[2], fix[3]], [fix[3], fix[4]]], dtype=float)
            return protect_with_bank(position, position_cov, self, budget)
        if not _proper(fix):
            return Protection(None, UNAVAILABLE), None
        bank_protect = _kernels().bank_protect

        tables, threshold = budget_tables(budget, len(self.ids) - 1)
        # JERK, THRESHOLD, the fix (FIX_X .. FIX_YY), LEVEL, WORST, STATISTIC, DROPPABLE, TABLE
        scalars = np.array([0.0, threshold, *fix, 0.0, 0.0, 0.0, 0.0, tables.shape[1]])
        excluded = np.array(self._flags([]))  # writable, as the tables: the kernel signature warm-up compiles
        bank_protect(
            np.ascontiguousarray(self.means),
            np.ascontiguousarray(self.covs),
            scalars,
            tables.copy(),
            excluded,
        )
        return self._protection(scalars, budget)

    def to_bytes(self) -> bytes:
        """Little-endian: magic, version, K, t; the exclusions (count, then uint16 length, end time, UTF-8 id);
        then K ids (uint16 length + UTF-8), means and covariances."""
        parts = [_HEADER.pack(_MAGIC, _VERSION, len(self.ids), self.t, len(self.excluded))]
        for rsu, until in self.excluded.items():
            raw = rsu.encode()
            parts.append(_EXCLUSION.pack(len(raw), until) + raw)
        for rsu in self.ids:
            raw = rsu.encode()
            parts.append(_LENGTH.pack(len(raw)) + raw)
        parts.append(np.asarray(self.means, dtype=_FLOAT).tobytes())
        parts.append(np.asarray(self.covs, dtype=_FLOAT).tobytes())
        return b"".join(parts)

    @staticmethod
    def from_bytes(blob: bytes) -> SeparationBank:
        """The bank ``to_bytes`` wrote; ValueError when ``blob`` is not one."""
        try:
            magic, version, count, t, excluded_count = _HEADER.unpack_from(blob)
            if magic != _MAGIC or version != _VERSION or count < 1:
                raise ValueError("not an integrity bank")
            offset = _HEADER.size
            excluded = {}
            for _ in range(excluded_count):
                length, until = _EXCLUSION.unpack_from(blob, offset)
                excluded[blob[offset + 10 : offset + 10 + length].decode()] = until
                offset += 10 + length
            ids = []
            for _ in range(count):
                (length,) = _LENGTH.unpack_from(blob, offset)
                ids.append(blob[offset + 2 : offset + 2 + length].decode())
                offset += 2 + length
            floats = count * (DIM + DIM * DIM)
            if len(blob) != offset + 8 * floats:
                raise ValueError("integrity bank is truncated")
            values = np.frombuffer(blob, dtype=_FLOAT, count=floats, offset=offset).astype(float)
        except (struct.error, UnicodeDecodeError) as error:
            raise ValueError(f"integrity bank is corrupt: {error!r}") from None
        # on the compiled kernel when the kernels are enabled: every batch decodes the bank, and numpy's
        # isfinite and reduction cost several microseconds there
        finite = _kernels().all_finite(values) if _compiled() else bool(np.isfinite(values).all())
        if not finite or not math.isfinite(t):
            raise ValueError("integrity bank is not finite")
        means = values[: count * DIM].reshape(count, DIM)
        return SeparationBank(ids, means, values[count * DIM :].reshape(count, DIM, DIM), t, excluded)


def _covered(ids: Sequence[str], rsu_ids: Sequence[str]) -> bool:
    """Whether every sub-filter's RSU (``ids[1:]``) is among ``rsu_ids`` (then ``prune`` drops none)."""
    return len(ids) - 1 <= len(rsu_ids) and set(ids[1:]).issubset(rsu_ids)


@dataclass(slots=True)
class _Plan:
    """What ``SeparationBank.epoch`` hands the compiled kernel besides the filters and the epoch's data: one
    vector (``kernels_integrity.bank_epoch``'s ``work``) with the jerk density, the test threshold, the
    radial factor tables, the per-measurement owners, the exclusions and the fix's indices filled in, and
    room for the kernel's outcome and scratch. It changes only with the RSUs in use, the sub-filters, the
    exclusions, the options or the fix's layout, so one serves epoch after epoch; what was an allocation
    of id tuples, flags and scalars per epoch is a few comparisons."""

    ids: list[str]  # the bank's ids list it was made for (spawn and prune replace the list, never mutate it)
    rsu_ids: list[str]
    excluded: frozenset[str]
    budget: IntegrityBudget
    jerk_density: float
    position: tuple[int, int]
    covered: bool  # every sub-filter's RSU is in use: prune has nothing to drop
    scalars: np.ndarray  # the kernel's work vector, the scalars at its head
    kernel: Callable[..., float]  # kernels_integrity.bank_epoch

    @staticmethod
    def make(
        bank: SeparationBank,
        rsu_ids: Sequence[str],
        jerk_density: float,
        budget: IntegrityBudget,
        position: tuple[int, int],
    ) -> _Plan:
        """The plan for ``bank`` (its sub-filters spawned for ``rsu_ids`` already). The kernel writes the
        bank's arrays in place, as they are: C-contiguous float64 as every method and ``from_bytes`` leave
        them (arrays of another layout, given to the constructor, compile another signature once)."""
        excluded = frozenset(bank.excluded)
        work, covered = _plan_work(tuple(bank.ids), tuple(rsu_ids), excluded, budget, position, jerk_density)
        kernel = _kernels().bank_epoch
        return _Plan(
            bank.ids, list(rsu_ids), excluded, budget, jerk_density, position, covered, work.copy(), kernel
        )


@functools.lru_cache(maxsize=1024)
def _plan_work(
    ids: tuple[str, ...],
    rsu_ids: tuple[str, ...],
    excluded: frozenset[str],
    budget: IntegrityBudget,
    position: tuple[int, int],
    jerk_density: float,
) -> tuple[np.ndarray, bool]:
    """A plan's work vector as it starts (read only: each plan writes its own copy) and ``covered``, shared by
    the banks with the same sub-filters, RSUs in use, exclusions, options and fix layout (sessions rebuild
    their plan every batch, the bank decoded anew)."""
    index = {rsu: k for k, rsu in enumerate(ids) if k}
    flags = [index.get(rsu, -1) for rsu in rsu_ids] + [rsu in excluded for rsu in ids] + list(position)
    tables, threshold = budget_tables(budget, len(ids) - 1)
    table = tables.shape[1]
    work = np.zeros(_kernels().work_size(len(rsu_ids), len(ids), table))
    work[JERK], work[THRESHOLD], work[TABLE] = jerk_density, threshold, table
    work[SCALARS : SCALARS + 2 * table] = tables.ravel()
    work[SCALARS + 2 * table : SCALARS + 2 * table + len(flags)] = flags
    work.flags.writeable = False
    return work, _covered(ids, rsu_ids)


@functools.lru_cache(maxsize=1024)
def _flags(ids: tuple[str, ...], rsu_ids: tuple[str, ...]) -> np.ndarray:
    """Per measurement the sub-filter that leaves it out (-1: none), then a zero per filter (no RSU
    excluded), read only."""
    index = {rsu: k for k, rsu in enumerate(ids) if k}
    flags = np.array([index.get(rsu, -1) for rsu in rsu_ids] + [0] * len(ids), dtype=np.int64)
    flags.flags.writeable = False
    return flags


def _proper(fix: Sequence[float]) -> bool:
    """Whether a fix's position covariance (xx, xy, yy at fix[2:5]) is positive definite."""
    return bool(fix[2] > 0.0 and fix[4] > 0.0 and fix[2] * fix[4] > fix[3] ** 2)


@functools.lru_cache(maxsize=256)
def budget_tables(budget: IntegrityBudget, hypotheses: int) -> tuple[np.ndarray, float]:
    """The fault-free and per-hypothesis radial factor tables (rows 0 and 1) and the test threshold of a
    budget with ``hypotheses`` sub-filters (the split of the risk in the module docstring)."""
    threshold = test_threshold(budget.false_alarm_probability, hypotheses) if hypotheses else 0.0
    missed = 0.5 * budget.integrity_risk / max(hypotheses, 1) / budget.fault_probability
    tables = np.array([radial_factor_table(0.5 * budget.integrity_risk), radial_factor_table(missed)])
    tables.flags.writeable = False
    return tables, threshold


def _arrays(
    measurements: Sequence[RangeBearing],
) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ids and arrays of ``update_arrays`` for a list of measurements."""
    count = len(measurements)
    return (
        [m.rsu_id for m in measurements],
        np.array([(m.rsu_x, m.rsu_y) for m in measurements], dtype=float).reshape(count, 2),
        np.array([(m.range, m.bearing) for m in measurements], dtype=float).reshape(count, 2),
        np.array([m.range_std for m in measurements], dtype=float),
        np.array([m.bearing_std for m in measurements], dtype=float),
    )


def _data(
    positions: np.ndarray, observed: np.ndarray, range_std: np.ndarray, bearing_std: np.ndarray
) -> np.ndarray:
    """Rows of rsu_x, rsu_y, range, bearing, range_std, bearing_std, as the numpy reference reads them."""
    return np.column_stack([positions, observed, range_std, bearing_std])


@functools.lru_cache(maxsize=1)
def _kernels() -> ModuleType:
    """The bank's compiled kernels (imported on first use: numba loads only when they are enabled)."""
    from edgepos.core import kernels_integrity

    return kernels_integrity


@functools.lru_cache(maxsize=1)
def _compiled() -> bool:
    from edgepos.core.compiled import compiled_enabled

    return compiled_enabled()


@functools.lru_cache(maxsize=64)
def _transition(dt: float, jerk_density: float) -> tuple[np.ndarray, np.ndarray]:
    """F and Q of the constant-acceleration model over ``dt`` on (x, vx, ax, y, vy, ay) (read only)."""
    f = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    q = jerk_density * np.array(
        [
            [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
            [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
            [dt**3 / 6.0, dt**2 / 2.0, dt],
        ]
    )
    transition = np.zeros((DIM, DIM))
    noise = np.zeros((DIM, DIM))
    transition[:3, :3] = transition[3:, 3:] = f
    noise[:3, :3] = noise[3:, 3:] = q
    transition.flags.writeable = noise.flags.writeable = False
    return transition, noise


def protect_with_bank(
    position: Sequence[float] | np.ndarray,
    position_cov: np.ndarray,
    bank: SeparationBank,
    budget: IntegrityBudget,
) -> tuple[Protection, str | None]:
    """Protection level of the fix at ``position`` (x, y) with covariance ``position_cov`` (2x2) from the
    bank's hypotheses (see the module docstring), its state by the alert limit, and the RSU not excluded
    already whose test failed worst (None if none: the caller excludes it or raises the alarm)."""
    covariance = (float(position_cov[0, 0]), float(position_cov[0, 1]), float(position_cov[1, 1]))
    if covariance[0] <= 0.0 or covariance[2] <= 0.0 or covariance[0] * covariance[2] <= covariance[1] ** 2:
        return Protection(None, UNAVAILABLE), None
    x, y = float(position[0]), float(position[1])
    fault_free = 0.5 * budget.integrity_risk
    reference = bank.covs[0]
    reference_cov = (float(reference[0, 0]), float(reference[0, 3]), float(reference[3, 3]))
    offset = math.hypot(x - float(bank.means[0, 0]), y - float(bank.means[0, 3]))
    # the fault-free bound of the fix's own covariance, and through the reference (the fix within
    # |x - x_0| of an estimate whose covariance is known to be the linear filter's)
    level = max(radial_bound(covariance, fault_free), offset + radial_bound(reference_cov, fault_free))
    hypotheses = bank.separations()
    count = len(bank.ids) - 1
    threshold = test_threshold(budget.false_alarm_probability, count) if count else 0.0
    missed = 0.5 * budget.integrity_risk / max(count, 1) / budget.fault_probability
    worst: tuple[float, int] | None = None
    statistics, positions, covariances = hypotheses
    offsets = np.hypot(positions[:, 0] - x, positions[:, 1] - y).tolist()
    for index, (statistic, subset) in enumerate(zip(statistics.tolist(), covariances.tolist(), strict=True)):
        failed = statistic > threshold and bank.ids[index + 1] not in bank.excluded
        if failed and (worst is None or statistic > worst[0]):
            worst = (statistic, index)
        level = max(level, offsets[index] + radial_bound(tuple(subset), missed))
    if not math.isfinite(level):
        return Protection(None, UNAVAILABLE), None
    state = ALARM if level > budget.alert_limit else OK
    if worst is not None:
        protection = Protection(level, state, faulty=worst[1], statistic=worst[0], threshold=threshold)
        return protection, bank.ids[worst[1] + 1]
    return Protection(level, state), None
