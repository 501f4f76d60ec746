"""Generated sections of hand-written documents, between two marker lines.

A document (the README, a page under ``docs/``) keeps a generated table between
``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``; the code that owns the facts renders the
table, :func:`replace_marked` puts it in place of the old one and :func:`rewrite_marked`
writes the document atomically (``io.atomic``). A test compares the section with a fresh
rendering, so the document cannot drift from the code.
"""
from __future__ import annotations

from pathlib import Path

from .atomic import atomic_output


def markers(name: str) -> tuple[str, str]:
    """The begin and end marker lines of the section ``name``."""
    return f'<!-- {name}:begin -->', f'<!-- {name}:end -->'


def marked_section(text: str, name: str) -> str:
    """The text between the markers of ``name`` (without them, stripped of the newlines
    right inside them).

    Raises:
        ValueError: The markers are missing, repeated or in the wrong order.
    """
    begin, end = markers(name)
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(end) < text.index(begin):
        raise ValueError(f'the document needs one {begin} line followed by one {end} line')
    return text[text.index(begin) + len(begin):text.index(end)].strip('\n')


def replace_marked(text: str, name: str, body: str) -> str:
    """``text`` with the section ``name`` replaced by ``body``.

    Raises:
        ValueError: As :func:`marked_section`.
    """
    marked_section(text, name)
    begin, end = markers(name)
    head, rest = text.split(begin, 1)
    tail = rest.split(end, 1)[1]
    return f'{head}{begin}\n{body.strip(chr(10))}\n{end}{tail}'


def rewrite_text(path: Path, transform) -> bool:
    """Rewrite a text file through ``transform(old text) -> new text``, atomically and only
    when it changes; whether it changed.

    Raises:
        ValueError: From ``transform`` (the message names the file).
    """
    path = Path(path)
    old = path.read_text(encoding='utf-8')
    try:
        new = transform(old)
    except ValueError as err:
        raise ValueError(f'{path}: {err}') from err
    if new == old:
        return False
    with atomic_output(path, force=True, encoding='utf-8') as handle:
        handle.write(new)
    return True


def rewrite_marked(path: Path, name: str, body: str) -> bool:
    """Put ``body`` into the section ``name`` of the file ``path``, atomically.

    Returns:
        Whether the file changed (it is not written when it is current).

    Raises:
        OSError: The file cannot be read or written.
        ValueError: As :func:`marked_section` (the message names the file).
    """
    return rewrite_text(path, lambda old: replace_marked(old, name, body))
