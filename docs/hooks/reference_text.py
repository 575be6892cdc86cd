"""Text from the code (help strings, docstrings, schema descriptions) made safe in Markdown."""

from __future__ import annotations


def cell(markdown: str) -> str:
    """Markdown safe in a table cell: one line, no pipe read as a column."""
    return " ".join(markdown.split()).replace("|", r"\|")


def text(plain: str) -> str:
    """Plain text, which may hold `code spans`, as Markdown for a table cell or a paragraph:
    outside code spans no angle bracket read as HTML, no asterisk as emphasis and no square
    bracket as a link."""
    parts = " ".join(plain.split()).split("`")
    for i in range(0, len(parts), 2):
        for char, escaped in (("<", "&lt;"), (">", "&gt;"), ("*", r"\*"), ("[", r"\[")):
            parts[i] = parts[i].replace(char, escaped)
    return cell("`".join(parts))
