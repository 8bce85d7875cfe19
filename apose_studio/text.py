"""Text from outside (a file name, an assembly's name, a page's field) that must not forge or disguise
what a user reads: one rule for every reader and printer of the project. No imports of the project, so
that errors, safeio, the CLI and the studio can all use it."""

from __future__ import annotations

import re
import unicodedata

# Characters that never belong in a name, a path or a line of text from outside: controls (Unicode's Cc:
# C0, C1, DEL: ESC sequences retitle or clear a terminal, a newline forges a line of output), format
# characters (Cf: bidi embeddings, overrides, isolates and marks, zero-width characters, the soft
# hyphen, tag characters, U+180E, U+FEFF: "x\u202elmay.yaml" shows as "xyaml.yml"), line and paragraph
# separators (Zl, Zp), surrogates (Cs: undecodable bytes in a file name), private-use and unassigned
# code points (Co, Cn), and the characters that show as nothing though Unicode files them elsewhere
# (INVISIBLE_CODES: the combining grapheme joiner, Hangul fillers, variation selectors). The CLI escapes
# them in what it prints (cli/common.printable: all but tab, newline and \r); names, paths and one-line
# fields refuse them (`unsafe_char`).
UNSAFE_CATEGORIES = frozenset({"Cc", "Cf", "Zl", "Zp", "Cs", "Co", "Cn"})
INVISIBLE_CODES = frozenset({0x034F, 0x115F, 0x1160, 0x17B4, 0x17B5, 0x3164, 0xFFA0, 0x2800,
                             *range(0x180B, 0x1810), *range(0xFE00, 0xFE10), *range(0xE0100, 0xE01F0)})
_PLAIN = re.compile(r"[ -~\u00a0-\u00ac\u00ae-\u02ff]*")  # printable ASCII and Latin: the common case, no lookup


def _unsafe(c: str) -> bool:
    return ord(c) in INVISIBLE_CODES or unicodedata.category(c) in UNSAFE_CATEGORIES


def _escape(c: str) -> str:
    n = ord(c)
    return f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}" if n < 0x10000 else f"\\U{n:08x}"


def unsafe_char(text: str, allow: str = "") -> str | None:
    """The first character of `text` that is a control or invisible character (see above), shown as an
    escape (\\x0a, \\u202e), or None; `allow`: characters that may stay (a multi-line field's newline)."""
    if _PLAIN.fullmatch(text):
        return None
    return next((_escape(c) for c in text if c not in allow and _unsafe(c)), None)


def escaped(text: str, allow: str = "") -> str:
    """`text` with every control or invisible character but those in `allow` shown as its escape."""
    if _PLAIN.fullmatch(text):
        return text
    return "".join(_escape(c) if c not in allow and _unsafe(c) else c for c in text)


LONG_VALUE = 200  # characters without a space: a value longer than this is shortened in messages
_LONG = re.compile(r"\S{%d,}" % (LONG_VALUE + 1))


def shorten_values(text: str) -> str:
    """`text` with each run of more than LONG_VALUE non-space characters (a 5000-digit number, a pasted
    blob) cut to its start and end and its length: a value in a message is quoted only when short. The CLI's
    refusals and the studio's notices both pass through it."""
    return _LONG.sub(lambda m: f"{m[0][:80]}…({len(m[0])} characters)…{m[0][-40:]}", text)
