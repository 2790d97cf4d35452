"""JSON from outside (a socket request, the state file, a calibration file) with its size and nesting bounded;
the same bound for TOML (gravcald's configuration), whose parser recurses the same way.

Python's json parser recurses once per nesting level, so 1000 ``[`` raise RecursionError from deep inside it
(and a larger recursion limit would overflow the C stack instead). The depth is therefore measured first, by a
linear scan of the brackets outside strings, and the text refused before json sees it. Every other failure of
the parser (bad syntax, bad UTF-8, an integer over Python's digit limit) comes out as the same JSONInputError,
so each caller catches one exception and reports one line.
"""
from __future__ import annotations

import json
import re
from typing import Any

from .errors import InputError

MAX_DEPTH = 64  # gravcal's own files nest 5 levels at most
MAX_BYTES = 16 << 20  # the largest state or calibration file is a few kB

# A string (an unterminated one runs to the end, so no start is scanned twice) or a bracket.
_TOKENS = re.compile(rb'"(?:[^"\\]|\\.)*(?:"|\Z)|[\[\]{}]', re.DOTALL)
# TOML: literal and basic strings, single and multi-line (an unterminated one runs to its line's or the text's
# end), comments, brackets
_TOML_TOKENS = re.compile(rb"""'''.*?(?:'''|\Z)|""" rb'"""(?:[^\\]|\\.)*?(?:"""|\Z)|' rb"""'[^'\n]*(?:'|$)|"""
                          rb'"(?:[^"\\\n]|\\.)*(?:"|$)|#[^\n]*|[\[\]{}]', re.DOTALL | re.MULTILINE)
_SYNTAX = {"json": _TOKENS, "toml": _TOML_TOKENS}
_OPEN = frozenset(b"[{")
_CLOSE = frozenset(b"]}")


class JSONInputError(InputError):
    """The text is not JSON within the bounds; the message names the problem (never echoes the text)."""


def nesting_depth(data: bytes | str, start: int = 0, *, stop_over: int = MAX_DEPTH, syntax: str = "json") -> int:
    """The deepest bracket nesting of ``data[start:]`` outside strings (stops counting above ``stop_over``).

    Unbalanced closing brackets count as nothing; an unterminated string hides the rest, which json rejects.
    """
    if isinstance(data, str):  # the scan runs on bytes: positions in characters are sliced off first
        data, start = data[start:].encode("utf-8", "surrogatepass"), 0
    depth = deepest = 0
    for m in _SYNTAX[syntax].finditer(data, start):
        c = m.group()[0]
        if c in _OPEN:
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > stop_over:
                    break
        elif c in _CLOSE:
            depth = max(depth - 1, 0)
    return deepest


def check_bounds(data: bytes | str, start: int = 0, *, max_depth: int = MAX_DEPTH, max_bytes: int = MAX_BYTES,
                 syntax: str = "json") -> None:
    """JSONInputError if ``data[start:]`` is larger than ``max_bytes`` or nests deeper than ``max_depth``
    (``syntax`` "json" or "toml": which strings and comments hide brackets)."""
    size = len(data) - start
    name = syntax.upper()
    if size > max_bytes:
        raise JSONInputError(f"{name} too large ({size} bytes; the limit is {max_bytes})")
    if nesting_depth(data, start, stop_over=max_depth, syntax=syntax) > max_depth:
        raise JSONInputError(f"{name} nested deeper than {max_depth} levels")


def _failure(exc: Exception) -> JSONInputError:
    if isinstance(exc, json.JSONDecodeError):
        return JSONInputError(f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}")
    if isinstance(exc, UnicodeDecodeError):
        return JSONInputError(f"not valid UTF-8 at byte {exc.start}")
    if isinstance(exc, RecursionError):  # a guard: check_bounds keeps the parser far from the limit
        return JSONInputError("JSON nested too deeply")
    # any other ValueError, e.g. an integer over Python's digit limit: its first clause names it
    return JSONInputError(f"not usable JSON: {str(exc).partition(':')[0]}")


def loads(data: bytes | str, *, max_depth: int = MAX_DEPTH, max_bytes: int = MAX_BYTES) -> Any:
    """``json.loads`` within the bounds; every failure is a JSONInputError."""
    check_bounds(data, max_depth=max_depth, max_bytes=max_bytes)
    try:
        return json.loads(data)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise _failure(exc) from None


def raw_decode(text: str, pos: int = 0, *, max_depth: int = MAX_DEPTH, max_bytes: int = MAX_BYTES) -> tuple[Any, int]:
    """``json.JSONDecoder().raw_decode(text, pos)`` within the bounds (measured on ``text[pos:]``): (value, end)."""
    check_bounds(text, pos, max_depth=max_depth, max_bytes=max_bytes)
    try:
        return _DECODER.raw_decode(text, pos)
    except (ValueError, RecursionError) as exc:
        raise _failure(exc) from None


_DECODER = json.JSONDecoder()
