"""Output files of the commands (``--json FILE``, ``--plots DIR``): their directories are created on demand,
so that ``--json results/run.json`` works in a fresh checkout without a ``mkdir`` first."""

from __future__ import annotations

from pathlib import Path


def prepare_output(path: str | Path, *, directory: bool = False) -> str | None:
    """Create the missing directories of ``path`` (its parent, or ``path`` itself when ``directory``)
    before a long run rather than after it; returns the error to report when that is impossible."""
    target = Path(path) if directory else Path(path).parent
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot create the directory {target}: {exc.strerror or exc}"
    return None


def write_output(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` (UTF-8), creating its missing parent directories."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(text, encoding="utf-8")
