"""Text from a model or a network peer made safe to encode and to print: it is data, never markup or control."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def well_formed(text: str) -> str:
    """`text` with every lone UTF-16 surrogate replaced by U+FFFD (a pair stays the character it encodes).
    A model's JSON may escape half an emoji (`"\\ud83d"`), and a string holding it cannot be encoded as UTF-8:
    kept, it would fail the publish of whatever message carries it."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-16", "surrogatepass").decode("utf-16", "replace")


def well_formed_tree(value: Any, leaf: Callable[[Any], Any] | None = None) -> Any:
    """A decoded JSON tree (dicts, lists or tuples, nested) with every string, keys included, through
    `well_formed`; tuples become lists; `leaf` maps every other value (unchanged without one)."""
    if isinstance(value, str):
        return well_formed(value)
    if isinstance(value, dict):
        return {well_formed_tree(k, leaf): well_formed_tree(v, leaf) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [well_formed_tree(v, leaf) for v in value]
    return value if leaf is None else leaf(value)


_C0_C1 = dict.fromkeys(c for c in (*range(0x00, 0x20), *range(0x7F, 0xA0)) if c != 0x09)
# Bidirectional overrides and isolates, zero-width and other invisible format characters: shown, they reorder
# or hide the text around them on a terminal (a reasoning that reads differently from what the model sent).
_FORMAT = dict.fromkeys((0x200B, 0x200C, 0x200D, 0x200E, 0x200F, 0x2028, 0x2029, 0x202A, 0x202B, 0x202C, 0x202D,
                         0x202E, 0x2060, 0x2066, 0x2067, 0x2068, 0x2069, 0xFEFF))


_C0_C1_BUT_NEWLINE = {c: v for c, v in _C0_C1.items() if c != 0x0A}


def plain_text(text: object, *, lines: bool = False) -> str:
    """Text a model or a network peer sent, made safe to write to a terminal as it is (Rich with
    `markup=False`, a plain print): control characters (ANSI escapes included; newlines too unless `lines`),
    bidirectional overrides and zero-width characters removed, lone surrogates replaced."""
    return well_formed(str(text)).translate(_C0_C1_BUT_NEWLINE if lines else _C0_C1).translate(_FORMAT)


def terminal_text(text: object) -> str:
    """Text a model or a network peer sent, made safe to print inside Rich markup: `plain_text`, and the
    markup escaped, so `[/dim]` in a model's reasoning is shown as written instead of raising MarkupError (and
    `[link=...]` is shown, not made a hyperlink)."""
    from rich.markup import escape

    return escape(plain_text(text))


def hidden_characters(text: str) -> list[str]:
    """The control characters (C0 but tab, DEL, C1), invisible format characters (bidirectional overrides
    and isolates, zero-width characters, line/paragraph separators, BOM) and lone surrogates (half an emoji
    sent as `\\ud83d`: no character at all, and UTF-8 cannot carry it) in `text`, as sorted U+XXXX codes: what
    an operator reading the command cannot see, yet the receiver would act on or fail to encode."""
    return sorted({f"U+{ord(c):04X}" for c in text
                   if ord(c) in _C0_C1 or ord(c) in _FORMAT or 0xD800 <= ord(c) <= 0xDFFF})
