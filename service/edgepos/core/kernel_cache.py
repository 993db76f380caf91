"""numba's on-disk cache for the kernels, made stale by a change to any kernel module.

numba decides whether a cached kernel is fresh from the source of the file that defines it, and nothing
else. A kernel compiles its callees from the other kernel modules into itself, so an edit to one of those
(``kernels_correct``'s update, say) left every caller's cached machine code running the old callee: a
checkout that changed one kernel file tested or served stale code until the cache was deleted by hand.
Here the kernels' cache locators stamp each entry with the digest of every kernel module's source (and
of the modules whose constants they read) as well, so a change to any of them recompiles them all once. The cache directories stay numba's own
(``NUMBA_CACHE_DIR``, next to the sources, or the user's cache directory).

The locators are numba's (``numba.core.caching``), extended and put first in the list numba tries; with a
numba that lays its cache out differently, nothing is installed and the kernels cache as numba alone
decides (``installed`` tells).
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

_log = logging.getLogger(__name__)

_PACKAGE = Path(__file__).resolve().parent.parent
#: Every module with compiled kernels; a kernel may inline a function of any of them.
KERNEL_FILES = tuple(
    _PACKAGE / name
    for name in (
        "core/kernels_base.py",
        "core/kernels.py",
        "core/kernels_correct.py",
        "core/kernels_motion.py",
        "core/kernels_turn.py",
        "core/kernels_integrity.py",
        "core/kernels_epoch.py",
        "core/kernels_run.py",
        "core/kernels_grouping.py",
        "core/measurements/gnss_kernel.py",
        "core/measurements/gnss_geometry.py",
        "core/measurements/gnss_raim_kernel.py",
        "core/measurements/gnss_noise_kernel.py",
        "core/particles/upf_kernel.py",
        "core/particles/upf_step_kernel.py",
        "core/particles/upf_resample_kernel.py",
        "pipelines/gnss_tdcp_kernel.py",
        "pipelines/gnss_carrier_kernel.py",
    )
)
#: The modules whose globals the kernels read (numba freezes a global into the machine code) or whose
#: compiled tables they call: a change there makes the kernels stale too.
READ_FILES = tuple(
    _PACKAGE / name
    for name in (
        "core/integrity_bank.py",
        "core/motion/base.py",
        "core/motion/riss.py",
        "gnss/corrections.py",
        "gnss/geodesy.py",
        "gnss/orbits.py",
        "gnss/tdcp.py",
    )
)


def sources_digest(files: tuple[Path, ...] = KERNEL_FILES + READ_FILES) -> str:
    """SHA-256 of the kernel modules' sources, in a fixed order."""
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


DIGEST = sources_digest()
_KERNEL_PATHS = frozenset(str(path) for path in KERNEL_FILES)


class _KernelSourcesStamp:
    """Mixed into numba's locators: the entry's stamp is numba's own and the kernel sources' digest; the
    locator declines functions outside the kernel modules (numba's own locators take them)."""

    def get_source_stamp(self) -> Any:
        return (super().get_source_stamp(), DIGEST)  # type: ignore[misc]  # numba's locator, mixed in below

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> Any:
        if str(Path(py_file).resolve()) not in _KERNEL_PATHS:
            return None
        return super().from_function(py_func, py_file)  # type: ignore[misc]  # as above


def install() -> bool:
    """Put the stamped locators before numba's (once); False when this numba has no such list."""
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover - numba is a dependency; compiled.py then runs the reference
        return False
    classes = getattr(getattr(caching, "CacheImpl", None), "_locator_classes", None)
    if not isinstance(classes, list):
        _log.warning("numba's cache locators not found: a kernel's cache follows only its own file")
        return False
    if any(isinstance(cls, type) and issubclass(cls, _KernelSourcesStamp) for cls in classes):
        return True
    names = ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator")
    bases = [getattr(caching, name) for name in names if hasattr(caching, name)]
    stamped = [type(f"KernelSources{base.__name__}", (_KernelSourcesStamp, base), {}) for base in bases]
    classes[:0] = stamped
    return True


installed = install()
