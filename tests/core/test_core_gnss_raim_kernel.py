"""gnss_tight's compiled RAIM hypotheses (core/measurements/gnss_raim_kernel.py) against the numpy form of
gnss/raim.py ``separations`` they replace, and the kernel declining to the numpy form; the protection
level's compiled per-hypothesis bounds against ``raim._hypothesis_bound``'s numpy form, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core import compiled
from edgepos.core.measurements import gnss_raim_kernel
from edgepos.gnss import raim
from edgepos.gnss.raim import RaimBudget, protection, separations

pytestmark = pytest.mark.skipif(
    not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)"
)

BUDGET = RaimBudget(1e-5, 1e-4, 1e-4, 1e-4, 10.0, 5.0)


def _epoch(seed: int, count: int, systems: str, lone: bool):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(0, 2 * np.pi, count)
    elevation = rng.uniform(np.radians(10), np.radians(85), count)
    names = [systems[k % len(systems)] for k in range(count)]
    if lone:
        names[-1] = "J"
    groups = sorted(set(names))
    h = np.zeros((count, 3 + len(groups)))
    h[:, 0] = -np.cos(elevation) * np.cos(azimuth)
    h[:, 1] = -np.cos(elevation) * np.sin(azimuth)
    h[:, 2] = -np.sin(elevation)
    for k, name in enumerate(names):
        h[k, 3 + groups.index(name)] = 1.0
    std = rng.uniform(0.5, 6.0, count)
    z = rng.normal(0.0, 1.0, count) * std
    z[rng.integers(count)] += 40.0  # one faulty satellite: statistics far from zero too
    a = rng.normal(size=(3, 3))
    return h, names, z, std, a @ a.T + np.diag([4.0, 4.0, 9.0])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    ("count", "systems", "lone"), [(8, "G", False), (20, "GCE", False), (17, "GC", True)]
)
def test_kernel_hypotheses_match_the_numpy_form(
    seed: int, count: int, systems: str, lone: bool, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """The same hypotheses in the same order (rows, prior probability, threshold), separations and
    covariances to 1e-9 m (m^2) and statistics to 1e-9 relative (1e-6 absolute for a lone satellite's
    rounding-only statistic)."""
    h, names, z, std, prior = _epoch(seed, count, systems, lone)
    compiled_result = separations(h, names, z, std, prior, BUDGET)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    reference = separations(h, names, z, std, prior, BUDGET)
    assert compiled_result.available and reference.available
    assert compiled_result.threshold == reference.threshold
    assert len(compiled_result.hypotheses) == len(reference.hypotheses)
    for got, want in zip(compiled_result.hypotheses, reference.hypotheses, strict=True):
        assert got[0] == want[0] and got[4] == want[4]
        np.testing.assert_allclose(got[1], want[1], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(got[2], want[2], rtol=1e-9, atol=1e-9)
        assert got[3] == pytest.approx(want[3], rel=1e-9, abs=1e-6)
    assert max(hypothesis[3] for hypothesis in reference.hypotheses) > 5.0


def test_cholesky_inverse() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6))
    spd = a @ a.T + np.eye(6)
    out = np.empty((6, 6))
    assert gnss_raim_kernel._invert_spd(spd, out)
    np.testing.assert_allclose(out, np.linalg.inv(spd), rtol=1e-10, atol=1e-12)
    assert not gnss_raim_kernel._invert_spd(np.diag([1.0, -1.0, 2.0]), np.empty((3, 3)))


def test_the_kernel_declines_and_the_numpy_form_decides(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A clock column without rows (a Jacobian the pipeline never builds) or a normal matrix that is not
    positive definite (an indefinite prior here): the kernel returns None, and ``separations`` gives the
    numpy form's answer."""
    h, names, z, std, prior = _epoch(1, 12, "GC", False)
    groups = np.array([0 if n == "C" else 1 for n in names])
    empty_clock = np.hstack([h, np.zeros((12, 1))])
    assert gnss_raim_kernel.separations(empty_clock, groups, 2, z, 1 / std**2, np.linalg.inv(prior)) is None
    indefinite = -np.diag([0.01, 0.02, 0.03])
    assert gnss_raim_kernel.separations(h, groups, 2, z, 1 / std**2, np.linalg.inv(indefinite)) is None
    got = separations(h, names, z, std, indefinite, BUDGET)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    want = separations(h, names, z, std, indefinite, BUDGET)
    assert got.available == want.available and got.threshold == want.threshold
    assert len(got.hypotheses) == len(want.hypotheses)
    for a, b in zip(got.hypotheses, want.hypotheses, strict=True):
        assert a[0] == b[0] and a[3] == b[3]
        np.testing.assert_array_equal(a[1], b[1])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    ("count", "systems", "lone"), [(8, "G", False), (20, "GCE", False), (17, "GC", True)]
)
@pytest.mark.parametrize("constellation_probability", [1e-4, 1e-3, 1.0])
def test_compiled_protection_level_is_the_numpy_forms_bit_for_bit(
    seed: int, count: int, systems: str, lone: bool, constellation_probability: float, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """The same protection level to the last bit, with one or two prior fault probabilities (one of them 1:
    an all-zero table), round and elongated fix covariances, and hypotheses whose bound is the largest."""
    h, names, z, std, prior = _epoch(seed, count, systems, lone)
    budget = RaimBudget(1e-5, 1e-4, 1e-4, constellation_probability, 10.0, 5.0)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    result = separations(h, names, z, std, prior, budget)  # the same hypotheses for both forms
    rng = np.random.default_rng(seed)
    for fix_cov in (np.eye(2), np.diag([0.04, 9.0]), _spd2(rng), _spd2(rng) * 1e-4):
        monkeypatch.setenv("EDGEPOS_NUMBA", "0")
        want = protection(result, fix_cov, budget)
        monkeypatch.setenv("EDGEPOS_NUMBA", "1")
        got = protection(result, fix_cov, budget)
        assert got.level == want.level and got.state == want.state
    covariance = np.eye(2)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    want_bound = raim._hypothesis_bound(result.hypotheses, covariance, 5e-6, result.threshold)
    monkeypatch.setenv("EDGEPOS_NUMBA", "1")
    assert raim._hypothesis_bound(result.hypotheses, covariance, 5e-6, result.threshold) == want_bound


def _spd2(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(2, 2))
    spd: np.ndarray = a @ a.T + 0.01 * np.eye(2)
    return spd


def test_the_bound_kernel_declines_a_value_that_is_not_finite(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A hypothesis covariance with NaN or infinity: the kernel returns NaN and the numpy form decides (a NaN
    bound it skips: the same answer either way)."""
    h, names, z, std, prior = _epoch(2, 12, "GC", False)
    result = separations(h, names, z, std, prior, BUDGET)
    for bad in (np.nan, np.inf):
        broken = list(result.hypotheses)
        rows, separation, covariance, statistic, probability = broken[3]
        broken[3] = (
            rows,
            separation,
            covariance + np.array([[bad, 0.0], [0.0, 0.0]]),
            statistic,
            probability,
        )
        separation_cov = np.array([hypothesis[2] for hypothesis in broken])
        assert np.isnan(
            raim._compiled_hypothesis_bound(broken, separation_cov, np.eye(2), 5e-6, result.threshold)
        )
    got = raim._hypothesis_bound(
        broken[:3] + [(rows, separation, covariance * np.nan, statistic, probability)],
        np.eye(2),
        5e-6,
        result.threshold,
    )
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    want = raim._hypothesis_bound(
        broken[:3] + [(rows, separation, covariance * np.nan, statistic, probability)],
        np.eye(2),
        5e-6,
        result.threshold,
    )
    assert got == want and np.isfinite(got)


def _snapshot_inputs(seed: int, count: int, fault: float):  # type: ignore[no-untyped-def]
    from edgepos.gnss.geodesy import geodetic_to_ecef
    from edgepos.gnss.measurements import PseudorangeSet

    rng = np.random.default_rng(seed)
    receiver = geodetic_to_ecef(np.radians(41.4), np.radians(2.1), 80.0)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    directions[:, 2] = np.abs(directions[:, 2])
    satellites = receiver + directions * rng.uniform(2.0e7, 2.6e7, count)[:, None]
    systems = tuple(("G", "C", "E")[k % 3] for k in range(count))
    pseudorange = np.linalg.norm(satellites - receiver, axis=1) + rng.normal(0.0, 3.0, count)
    pseudorange[rng.integers(count)] += fault
    known = rng.normal(0.0, 5.0, count)
    prs = PseudorangeSet(
        1.0e5,
        systems,
        np.arange(count),
        pseudorange + known,
        np.full(count, 40.0),
        satellites,
        np.zeros(count),
        np.full(count, 1575.42e6),
    )
    return receiver, prs, known, rng.uniform(1.0, 5.0, count)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(("count", "fault"), [(20, 0.0), (20, 60.0), (9, 40.0), (8, 0.0), (6, 0.0)])
def test_snapshot_rounds_match_the_numpy_round(seed: int, count: int, fault: float) -> None:
    """The snapshot test's compiled round (statistic, degrees of freedom, worst row and its standardised
    residual) against its numpy round, on the subsets the test tries (the worst row left out in turn while
    the statistic exceeds its chi-square median, far below any threshold the test uses: past that, rows fit
    to 1e-13 and the largest two standardised residuals tie to rounding); both None when fewer than 2
    degrees of freedom remain."""
    from edgepos.pipelines.gnss_screening import _SnapshotFit
    from scipy.stats import chi2

    fit = _SnapshotFit(*_snapshot_inputs(seed, count, fault))
    assert fit.compiled
    keep = np.arange(count)
    compared = 0
    while True:
        got, want = fit.round(keep), fit._numpy_round(keep)
        if want is None:
            assert got is None
            break
        assert got is not None
        assert got[1] == want[1]
        assert got[0] == pytest.approx(want[0], rel=1e-9) and got[3] == pytest.approx(want[3], rel=1e-9)
        if want[0] < chi2.ppf(0.5, want[1]):
            break
        assert got[2] == want[2]
        compared += 1
        keep = np.delete(keep, want[2])
    assert compared or fault == 0.0
