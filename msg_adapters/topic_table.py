"""The README's topic table, rendered from the topic registry (:data:`.wire.TOPICS`).

Run ``python -m msg_adapters.topic_table README.md`` after changing a topic in
:mod:`.wire`: it rewrites the section between ``<!-- topics:begin -->`` and
``<!-- topics:end -->`` (atomically; a file already current is left alone). A test fails
while the README differs from the registry.

Exit codes: 0 written or current, 2 bad usage or the markers missing, 4 a file that
cannot be read or written (the message names it).
"""
from __future__ import annotations

import argparse
import sys

from gnsscam_ros.io.marked import rewrite_marked

from .wire import RELIABLE, TOPICS, Topic
#: Name of the README section (``<!-- topics:begin -->`` ... ``<!-- topics:end -->``).
README_SECTION = 'topics'


def _qos_text(topic: Topic) -> str:
    text = 'reliable' if topic.reliability == RELIABLE else 'best effort'
    if topic.latched:
        text += ', transient local (latched)'
    return f'{text}, depth {topic.depth}'


def _frame_text(topic: Topic) -> str:
    if topic.frame_id is None:
        return ''
    own = f' (`{topic.frame_parameter}`)' if topic.frame_parameter else ''
    return f'`{topic.frame_id}`{own}'


def render_topic_table() -> str:
    """The markdown table of :data:`TOPICS` (the README's section between the markers of
    :data:`README_SECTION`): topic, type, frame, QoS, producer and consumers, content."""
    rows = ['| topic | type | frame | QoS | from → to | content |',
            '|---|---|---|---|---|---|']
    for t in TOPICS.values():
        route = ', '.join(t.producers) + ' → ' + (', '.join(t.consumers) or '(outputs)')
        rows.append(f'| `{t.name}` | `{t.interface}` | {_frame_text(t)} | {_qos_text(t)} '
                    f'| {route} | {t.description} |')
    return '\n'.join(rows)


def main(argv: list[str] | None = None) -> int:
    """``python -m msg_adapters.topic_table FILE ...``; the exit code (module docstring)."""
    parser = argparse.ArgumentParser(prog='python -m msg_adapters.topic_table',
                                     description='Render the topic registry into documents.')
    parser.add_argument('files', nargs='+', metavar='FILE',
                        help='rewrite the table between <!-- topics:begin --> and '
                             '<!-- topics:end --> of these files (README.md)')
    args = parser.parse_args(argv)
    for name in args.files:
        try:
            changed = rewrite_marked(name, README_SECTION, render_topic_table())
        except ValueError as err:
            print(f'msg_adapters.topic_table: {err}', file=sys.stderr)
            return 2
        except OSError as err:
            print(f'msg_adapters.topic_table: cannot rewrite {name}: {err.strerror or err}',
                  file=sys.stderr)
            return 4
        print(f'{name}: {"updated" if changed else "up to date"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
