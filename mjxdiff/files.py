"""Files written whole or not at all: every file mjxdiff writes (reports, pages, reproducers,
history runs, compiled artifacts) goes through :func:`atomic_write`, so an interrupted run or a
concurrent reader never sees half of one."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Callable

__all__ = ["atomic_write"]


def atomic_write(path: str | Path, data: str | bytes | Callable[[Path], object]) -> Path:
    """Writes ``data`` to ``path`` and returns ``path``: text (UTF-8), bytes, or a function that
    writes the file it is given. The data goes to a hidden temporary beside ``path``, renamed
    into place (``os.replace``, atomic on one file system), so a reader sees the old file or the
    whole new one. The temporary's name ends in ``.tmp`` and carries a random 128-bit suffix,
    unique across hosts, processes and threads sharing a directory; it is removed if writing
    fails. Creates the parent directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        if isinstance(data, str):
            tmp.write_text(data, encoding="utf-8")
        elif isinstance(data, bytes):
            tmp.write_bytes(data)
        else:
            data(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
