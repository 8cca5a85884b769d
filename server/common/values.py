"""The constrained value types every boundary shares: a finite number, a whole number, a name.

Why one module: the same kind of value enters through request bodies, query
parameters, settings and files; checked at each boundary its own way, one would
let through what another refuses (Infinity into the KPIs as a design cycle time,
a NUL or a right-to-left override into the audit trail as a token's name). Declared once
here, each type also states its constraint in openapi.json, so what a client
reads is what the server enforces.

Strict on purpose: a request that says "8" or true where a number belongs is a
script bug, and guessing what it meant is how a wrong value gets in silently. A
JSON integer is still a valid float.
"""

from __future__ import annotations

import re
from typing import Annotated, Any

from pydantic import AfterValidator, AllowInfNan, BeforeValidator, Field, Strict

# A number as JSON has it: never a string or a boolean, never Infinity or NaN.
# Bounds are the field's own: `Annotated[FiniteNumber, Field(ge=..., le=...)]`.
FiniteNumber = Annotated[float, Strict(), AllowInfNan(False)]


def _integral(value: object) -> object:
    """2.0 is the integer 2 (JSON Schema says so); 2.5, "2" and true are left to be refused."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def whole_number(*constraints: Any) -> Any:
    """A whole number within `constraints`, written 2 or 2.0: never 2.5, "2" or true.

    A function, not a type: the bounds must come before the step that reads 2.0 as 2,
    or openapi.json would not state them as `minimum`/`maximum` (a pydantic quirk).
    """
    return Annotated[int, Strict(), *constraints, BeforeValidator(_integral)]


# What a name may not hold (first and last code point of each range): C0 and C1
# control characters (NUL, line breaks, escape sequences that repaint a terminal),
# the line and paragraph separators, and the bidirectional marks, embeddings,
# overrides and isolates that make a name read differently from what it is.
NAME_FORBIDDEN_RANGES = (
    (0x00, 0x1F),
    (0x7F, 0x9F),
    (0x061C, 0x061C),
    (0x200E, 0x200F),
    (0x2028, 0x202E),
    (0x2066, 0x2069),
)
NAME_MAX_LENGTH = 100


def _escaped(code: int) -> str:
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


_CLASS = "".join(
    _escaped(low) if low == high else f"{_escaped(low)}-{_escaped(high)}"
    for low, high in NAME_FORBIDDEN_RANGES
)
# As openapi.json states it: ECMA-262 escapes, which Python's `re` reads the same way.
NAME_PATTERN = f"^[^{_CLASS}]+$"
_FORBIDDEN = re.compile(f"[{_CLASS}]")


def _printable_name(text: str) -> str:
    """Refuse a name that would not read as what it is (the message names the character)."""
    found = _FORBIDDEN.search(text)
    if found is not None:
        raise ValueError(
            f"a name may not hold U+{ord(found.group()):04X} (control, line-separator and "
            f"bidirectional-override characters are refused), found at position {found.start()}"
        )
    return text


Name = Annotated[
    str,
    Strict(),
    Field(
        min_length=1,
        max_length=NAME_MAX_LENGTH,
        description="1-100 characters of any script; no control, line-separator or "
        "bidirectional-override characters",
        json_schema_extra={"pattern": NAME_PATTERN},
    ),
    AfterValidator(_printable_name),
]


_BYTE_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([KMG]?B?)\s*$", re.IGNORECASE)
_BYTE_UNITS = {"": 1, "B": 1, "K": 1024, "KB": 1024, "M": 1024**2, "MB": 1024**2}
_BYTE_UNITS |= {"G": 1024**3, "GB": 1024**3}
BYTE_SIZE_ACCEPTS = "a size such as 10MB (a number, then B, KB, MB or GB)"


def byte_size(text: str) -> int:
    """'10MB' → bytes (KB = 1024); ValueError saying what is accepted otherwise."""
    match = _BYTE_SIZE.match(text)
    if not match:
        raise ValueError(f"{text!r} is not {BYTE_SIZE_ACCEPTS}")
    return int(float(match.group(1)) * _BYTE_UNITS[match.group(2).upper()])
