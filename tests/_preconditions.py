"""Premises of strict xfails, kept apart from the divergence they expect.

A strict xfail (``raises=AssertionError``) counts any AssertionError as the expected MJX
failure, so a premise checked with ``assert`` that breaks (a MuJoCo upgrade changes C's side,
a model no longer makes the contact) would keep it green. :func:`precondition` raises
:class:`PreconditionBroken` instead, which is not an AssertionError: the test fails."""


class PreconditionBroken(Exception):
    """The setup of a strict xfail no longer holds: the divergence it documents cannot be seen."""


def precondition(ok, message: str) -> None:
    """Raises :class:`PreconditionBroken` with ``message`` unless ``ok``."""
    if not ok:
        raise PreconditionBroken(message)
