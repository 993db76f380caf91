"""Modules of a package as another git revision has them, loaded beside today's for an A/B in one process.

Each module's source at the revision is written to a directory on ``sys.path`` as ``<name>_<tag>``, its
imports of the other modules loaded with it renamed alike, so that both revisions' code runs in the same
process, alternated, under the same load (``bench/kernels_ab.py``, ``bench/wrappers_ab.py``)."""

from __future__ import annotations

import importlib
import subprocess
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent


def load_revision_modules(
    revision: str, package: str, names: tuple[str, ...], tag: str, directory: Path
) -> dict[str, ModuleType]:
    """The modules ``names`` of ``package`` (e.g. ``edgepos.core``) at ``revision`` as ``<name>_<tag>``,
    written to ``directory`` (which must be on ``sys.path``), by name."""
    folder = "service/" + package.replace(".", "/")
    for name in names:
        source = subprocess.run(
            ["git", "-C", str(ROOT), "show", f"{revision}:{folder}/{name}.py"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        for other in names:
            source = source.replace(f"from {package}.{other} import", f"from {other}_{tag} import")
        (directory / f"{name}_{tag}.py").write_text(source)
    return {name: importlib.import_module(f"{name}_{tag}") for name in names}
