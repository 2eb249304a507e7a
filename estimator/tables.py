"""Plain-text tables whose columns fit their contents (``osa replay``, ``osa search``,
``osa evaluate`` print them).

Each column has a title, an alignment and a minimum width; its width is the largest of
the minimum, its title and its cells, plus ``gap`` spaces of padding (after the text of
a left-aligned column, before the text of a right-aligned one; a left-aligned column
right after a right-aligned one also gets ``gap`` spaces before it), so a long policy
name, mode or BSSID widens its column instead of pushing the rest of its row out of
line.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class Column:
    """One column: ``align`` ``"<"`` (text) or ``">"`` (numbers); ``width`` is the
    least width in characters, padding included."""

    title: str
    align: Literal["<", ">"] = "<"
    width: int = 0

    def __post_init__(self) -> None:
        if self.align not in ("<", ">"):
            raise ValueError(f"column {self.title!r}: align must be '<' or '>'")


def fit_columns(columns: Sequence[Column], rows: Sequence[Sequence[str]],
                gap: int = 1) -> list[Column]:
    """The columns widened to hold these rows: a table of several blocks fits its
    columns to every block's rows once, so the blocks line up."""
    out = []
    for i, c in enumerate(columns):
        longest = max([len(c.title), *(len(r[i]) for r in rows)])
        out.append(Column(c.title, c.align, max(c.width, longest + gap)))
    return out


def text_table(columns: Sequence[Column], rows: Sequence[Sequence[str]], *,
               indent: str = "", gap: int = 1, rule: str = "") -> list[str]:
    """The lines of a table: the titles, a rule of ``rule`` characters under them when
    given, then one line per row (every row holds one string per column). Trailing
    spaces are dropped."""
    rows = [tuple(r) for r in rows]
    for r in rows:
        if len(r) != len(columns):
            raise ValueError(f"a row has {len(r)} cells for {len(columns)} columns")
    fitted = fit_columns(columns, rows, gap)

    # a text column after a number column: its padding is after it, so it gets a gap
    lead = [" " * gap if c.align == "<" and k and fitted[k - 1].align == ">" else ""
            for k, c in enumerate(fitted)]

    def line(cells: Sequence[str]) -> str:
        text = "".join(f"{pad}{cell:{c.align}{c.width}}"
                       for c, pad, cell in zip(fitted, lead, cells, strict=True))
        return (indent + text).rstrip()

    out = [line([c.title for c in columns])]
    if rule:
        out.append(indent + rule * (len(out[0]) - len(indent)))
    out.extend(line(r) for r in rows)
    return out
