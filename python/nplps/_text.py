"""Text shown to people, escaped for its medium.

:func:`printable` escapes control characters (ANSI escape sequences, carriage returns, bells
...) for a terminal: a capture folder or a file named with escape codes is printed as what it
is, not obeyed by the terminal.
"""

from __future__ import annotations

import unicodedata

__all__ = ["printable"]


def printable(text: str, keep_newlines: bool = False) -> str:
    r"""Return ``text`` with control characters shown as escapes (``\x1b``, ``\r``, ``\u202e``, ...).

    Tabs are kept, and newlines with ``keep_newlines``; everything else of Unicode category C
    (control, format, surrogate, private use, unassigned) is escaped the way Python's ``repr``
    writes it.
    """
    out = []
    for ch in str(text):
        if ch == "\t" or (keep_newlines and ch == "\n"):
            out.append(ch)
        elif unicodedata.category(ch).startswith("C") and ch not in ("\u200d",):
            code = ord(ch)
            out.append(f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}" if code < 0x10000 else f"\\U{code:08x}")
        else:
            out.append(ch)
    return "".join(out)
