"""The kernels' on-disk cache is stamped with every kernel module's source (core.kernel_cache): an edit to
a callee's module makes its callers' cached code stale too, not only its own."""

from __future__ import annotations

from pathlib import Path

import pytest
from edgepos.core import compiled, kernel_cache

SERVICE = Path(kernel_cache.__file__).resolve().parent.parent


def test_every_module_that_defines_a_kernel_is_stamped() -> None:
    defining = {
        path.resolve()
        for path in SERVICE.rglob("*.py")
        if "@_jit" in path.read_text() or "numba.njit(" in path.read_text()
    }
    assert defining == set(kernel_cache.KERNEL_FILES)
    assert all(path.is_file() for path in kernel_cache.KERNEL_FILES + kernel_cache.READ_FILES)


def test_the_digest_follows_any_file_it_covers(tmp_path: Path) -> None:
    files = (tmp_path / "a.py", tmp_path / "b.py")
    files[0].write_text("x = 1\n")
    files[1].write_text("def f():\n    return 2\n")
    before = kernel_cache.sources_digest(files)
    assert kernel_cache.sources_digest(files) == before
    files[1].write_text("def f():\n    return 3\n")
    assert kernel_cache.sources_digest(files) != before


@pytest.mark.skipif(not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)")
def test_every_kernel_caches_under_the_sources_stamp() -> None:
    assert kernel_cache.installed
    dispatchers = compiled._kernel_dispatchers()
    assert dispatchers
    for dispatcher in dispatchers:
        cache = getattr(dispatcher, "_cache", None)
        locator = getattr(getattr(cache, "_impl", None), "locator", None)
        if locator is None:  # no writable cache directory: compiled in memory, nothing to go stale
            continue
        assert isinstance(locator, kernel_cache._KernelSourcesStamp), dispatcher
        assert locator.get_source_stamp()[1] == kernel_cache.DIGEST


def test_functions_outside_the_kernel_modules_keep_numbas_locators(tmp_path: Path) -> None:
    from numba.core import caching

    stamped = [
        cls for cls in caching.CacheImpl._locator_classes if issubclass(cls, kernel_cache._KernelSourcesStamp)
    ]
    assert stamped
    outside = tmp_path / "elsewhere.py"
    outside.write_text("def f():\n    return 1\n")
    for cls in stamped:
        assert cls.from_function(lambda: 1, str(outside)) is None
    assert kernel_cache.install()  # again: nothing added twice
    again = [
        cls for cls in caching.CacheImpl._locator_classes if issubclass(cls, kernel_cache._KernelSourcesStamp)
    ]
    assert again == stamped
