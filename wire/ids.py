"""The id rule: what a ``vehicle``, ``session``, ``map`` or service ``instance`` name may be.

One regular expression, :data:`ID_REGEX`: 1-64 letters, digits, ``_``, ``.`` and ``-``, starting
with a letter or digit. An id becomes a Zenoh key-expression chunk (``randt/fleet/<vehicle>/scan``)
and a file or directory name (``maps/<map>/``), so it may hold none of ``/ * $ ? #``, no spaces, no
leading dot or dash, and it is never ``.`` or ``..``. Every place that checks an id uses this module:
the wire decoders (:class:`wire.messages.WireLimits`), the service's settings, its store and its
HTTP path parameters, and the vehicle publisher.
"""

from __future__ import annotations

import re
from typing import Final

__all__ = [
    "ID_MAX_LENGTH",
    "ID_PATTERN",
    "ID_REGEX",
    "UNKNOWN_ID",
    "UNSAFE_ID_SAMPLES",
    "is_valid_id",
    "validate_id",
]

#: The id rule, anchored; matched in full (``re.fullmatch``).
ID_REGEX: Final = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"

#: :data:`ID_REGEX` compiled.
ID_PATTERN: Final = re.compile(ID_REGEX)

#: Longest id, in characters.
ID_MAX_LENGTH: Final = 64

#: ``vehicle`` / ``session`` of an error message when the failed message did not say (never an id).
UNKNOWN_ID: Final = "?"

#: Strings that would break a key expression or a file path: no id rule may accept any of them
#: (:class:`wire.messages.WireLimits` refuses a configured ``id_pattern`` that does).
UNSAFE_ID_SAMPLES: Final = ("", "a/b", "*", "**", "$*", "a?b", "a#b", "a b", ".", "..", "a\nb")


def is_valid_id(value: object) -> bool:
    """Whether ``value`` is a ``str`` that is a valid id (:data:`ID_REGEX`, in full)."""
    return isinstance(value, str) and ID_PATTERN.fullmatch(value) is not None


def validate_id(value: object, what: str = "name") -> str:
    """Return ``value`` if it is a valid id, else raise.

    Parameters
    ----------
    value:
        The candidate.
    what:
        What the id names (``"map"``, ``"vehicle"``, ``"session"``), for the message.

    Raises
    ------
    ValueError
        Not a string, or not a valid id (path separators, ``..``, leading dot or dash, empty,
        longer than 64 characters, characters outside ``A-Z a-z 0-9 _ . -``).
    """
    if not isinstance(value, str):
        raise ValueError(f"{what} name must be a string, got {type(value).__name__}")
    if not is_valid_id(value):
        raise ValueError(
            f"invalid {what} name {value!r}: use 1-{ID_MAX_LENGTH} characters from A-Z a-z 0-9 _ . -, "
            "starting with a letter or digit"
        )
    return value
