"""Plain-text tables for the command-line tools."""
from __future__ import annotations


def _fmt(value, digits: int = 2) -> str:
    if value is None:
        return '-'
    if isinstance(value, float):
        return f'{value:.{digits}f}'
    return str(value)


def format_table(headers: list[str], rows: list[list]) -> str:
    """A plain-text table with right-aligned columns."""
    cells = [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h)
              for i, h in enumerate(headers)]
    line = '  '.join(h.rjust(w) for h, w in zip(headers, widths))
    out = [line, '-' * len(line)]
    out += ['  '.join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    return '\n'.join(out)
