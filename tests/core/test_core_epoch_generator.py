"""gnss_tight's per-epoch generator (core/particles/upf_resample_kernel.py ``epoch_generator``) against the one
numpy makes, ``np.random.default_rng([seed, epoch])``: the same PCG64 state and draws for any seed a session
may have, numpy's own with the kernels off or for entropy beyond the compiled pool, and one generator per
thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from edgepos.core import compiled
from edgepos.core.particles.upf_resample_kernel import epoch_generator

SEEDS = [0, 1, 2, 7, 2**32 - 1, 2**32, 2**32 + 5, 2**62 + 12345, 2**63 - 1]
EPOCHS = [0, 1, 2, 300, 65535, 2**31, 2**32 - 1]


@pytest.mark.skipif(not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)")
def test_the_generator_is_default_rngs() -> None:
    seeds = SEEDS + [int(s) for s in np.random.default_rng(3).integers(0, 2**63 - 1, 40)]
    for seed in seeds:
        for epoch in EPOCHS:
            got, want = epoch_generator(seed, epoch), np.random.default_rng([seed, epoch])
            assert got.bit_generator.state == want.bit_generator.state, (seed, epoch)
            np.testing.assert_array_equal(got.standard_normal((3, 4)), want.standard_normal((3, 4)))
            np.testing.assert_array_equal(got.random(3), want.random(3))


def test_numpys_generator_with_the_kernels_off_or_more_entropy(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Five 32-bit words of entropy (beyond the pool of four the kernel hashes) and ``EDGEPOS_NUMBA=0``: numpy
    builds the generator, a new one each call, with the same state."""
    big = epoch_generator(2**70 + 3, 2**40 + 1)
    assert big.bit_generator.state == np.random.default_rng([2**70 + 3, 2**40 + 1]).bit_generator.state
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    first, second = epoch_generator(5, 9), epoch_generator(5, 9)
    assert first is not second
    assert first.bit_generator.state == np.random.default_rng([5, 9]).bit_generator.state


@pytest.mark.skipif(not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)")
def test_one_generator_per_thread() -> None:
    """A thread's generator is set again at each call (the caller draws before its next one); another
    thread gets its own, so that two filter threads never share one."""
    mine = epoch_generator(1, 1)
    assert epoch_generator(1, 2) is mine
    theirs: list[np.random.Generator] = []
    thread = threading.Thread(target=lambda: theirs.append(epoch_generator(1, 2)))
    thread.start()
    thread.join()
    assert theirs[0] is not mine
    assert theirs[0].bit_generator.state == np.random.default_rng([1, 2]).bit_generator.state
