"""Context-local suppression and recording of accelcal's own warnings.

``warnings.catch_warnings`` swaps the process-wide filter list: before Python 3.14 two threads
inside it at once can leave an ``ignore`` filter installed for good, silencing every warning
of the process. Library code therefore never touches ``warnings.filters``: a step that runs
another quietly enters :func:`quiet` (or :func:`recording`), which sets a context variable
(local to the thread and to the asyncio task), and accelcal's warning sites call :func:`warn`,
which consults it before handing the warning to :func:`warnings.warn`.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

#: The active handlers, innermost last: ``(categories, None)`` drops a warning of one of the
#: categories, ``(categories, list)`` records it in the list instead of issuing it.
_HANDLERS: ContextVar[tuple[tuple[tuple[type[Warning], ...],
                                  list[warnings.WarningMessage] | None], ...]] = ContextVar(
    "accelcal_warning_handlers", default=())


@contextmanager
def quiet(*categories: type[Warning]) -> Iterator[None]:
    """Drop accelcal's warnings of ``categories`` (every category when none is given) issued
    through :func:`warn` in this context (thread or task) only; the warning filters stay as
    they are."""
    token = _HANDLERS.set((*_HANDLERS.get(), (categories or (Warning,), None)))
    try:
        yield
    finally:
        _HANDLERS.reset(token)


@contextmanager
def recording(*categories: type[Warning]) -> Iterator[list[warnings.WarningMessage]]:
    """Collect accelcal's warnings of ``categories`` (every category when none is given)
    issued through :func:`warn` in this context into the list yielded, instead of issuing
    them: a context-local ``catch_warnings(record=True)``."""
    caught: list[warnings.WarningMessage] = []
    token = _HANDLERS.set((*_HANDLERS.get(), (categories or (Warning,), caught)))
    try:
        yield caught
    finally:
        _HANDLERS.reset(token)


def _handler(category: type[Warning]) -> list[warnings.WarningMessage] | None | bool:
    """What the innermost handler taking ``category`` does with it: its record list, None to
    drop it, or False when no handler takes it (issue it)."""
    for cats, caught in reversed(_HANDLERS.get()):
        if issubclass(category, cats):
            return caught
    return False


def silenced(category: type[Warning]) -> bool:
    """A warning of ``category`` issued through :func:`warn` here is dropped (so its text need
    not be built)."""
    return _handler(category) is None


def recorded(category: type[Warning]) -> bool:
    """A warning of ``category`` issued through :func:`warn` here is recorded, whatever the
    warning filters say."""
    return isinstance(_handler(category), list)


def warn(message: str, category: type[Warning] = UserWarning, stacklevel: int = 1) -> None:
    """:func:`warnings.warn` unless this context is :func:`quiet` for ``category`` (dropped)
    or :func:`recording` it (collected). ``stacklevel`` counts as :func:`warnings.warn`'s does
    from the caller, so the warning still points at the user's line."""
    caught = _handler(category)
    if caught is False:
        warnings.warn(message, category, stacklevel=stacklevel + 1)
    elif isinstance(caught, list):
        try:
            frame = sys._getframe(stacklevel)
            where = (frame.f_code.co_filename, frame.f_lineno)
        except ValueError:  # fewer frames than stacklevel: as warnings.warn says it
            where = ("sys", 1)
        caught.append(warnings.WarningMessage(category(message), category, *where))
