"""Unknown keys are errors: every table a user writes is checked against the keys it may hold."""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from typing import Any


def closest(key: str, allowed: Iterable[str]) -> str | None:
    """The allowed key closest to ``key`` (a likely misspelling), or ``None``."""
    matches = difflib.get_close_matches(str(key), sorted(allowed), n=1, cutoff=0.5)
    return matches[0] if matches else None


def unknown_key_message(key: Any, allowed: Iterable[str], where: str, noun: str = "") -> str:
    """``"<where>: unknown key 'targett'; did you mean 'target'? (valid keys: ...)"``, or with
    ``noun``: ``"<where> has no setting 'warp' ... (its settings: ...)"``."""
    allowed = sorted(allowed)
    hint = closest(str(key), allowed)
    guess = f"; did you mean {hint!r}?" if hint else ""
    if noun:
        return f"{where} has no {noun} {key!r}{guess} (its {noun}s: {', '.join(allowed)})"
    return f"{where}: unknown key {key!r}{guess} (valid keys: {', '.join(allowed)})"


def check_keys(table: Mapping[str, Any], allowed: Iterable[str], where: str, error: type[Exception]) -> None:
    """Raise ``error`` naming the first key of ``table`` not in ``allowed`` and the closest valid one."""
    allowed = set(allowed)
    for key in table:
        if key not in allowed:
            raise error(unknown_key_message(key, allowed, where))
