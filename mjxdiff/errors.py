"""Exceptions said in one line: every exception shown to a user or stored in a report goes
through :func:`one_line`."""

from __future__ import annotations

__all__ = ["one_line"]


def one_line(e: BaseException, limit: int | None = None) -> str:
    """``"Type: message"`` of an exception on one line (runs of whitespace, newlines included,
    become one space), cut to ``limit`` characters where given."""
    text = " ".join(f"{type(e).__name__}: {e}".split())
    return text if limit is None else text[:limit]
