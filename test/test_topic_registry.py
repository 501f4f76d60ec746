"""The topic registry (``msg_adapters.wire.TOPICS``) is the one table of topic facts: the
README's topic table is its rendering, the node modules name no topic by a string of their
own, and the bag layout is made of its entries. No rclpy needed (the nodes' endpoints are
checked against it in test_topic_registry_nodes.py)."""
import ast
from pathlib import Path

import pytest

from gnsscam_ros.bags import schema
from gnsscam_ros.io.marked import marked_section, replace_marked, rewrite_marked
from msg_adapters import topic_table, wire

ROOT = Path(__file__).resolve().parents[1]
NODES = ('gnss_node', 'camera_node', 'imu_node', 'fusion_node')


@pytest.mark.parametrize('page', ['README.md', 'docs/nodes.md'])
def test_the_topic_tables_are_the_registry_rendered(page):
    text = (ROOT / page).read_text(encoding='utf-8')
    assert marked_section(text, topic_table.README_SECTION) == \
        topic_table.render_topic_table(), (
            f'{page} differs from msg_adapters/wire.py TOPICS: run '
            f'python -m msg_adapters.topic_table {page}')


def test_the_rendered_table_has_one_row_per_topic_with_its_facts():
    rows = topic_table.render_topic_table().splitlines()[2:]
    assert len(rows) == len(wire.TOPICS)
    for row, topic in zip(rows, wire.TOPICS.values()):
        cells = [c.strip() for c in row.strip('|').split('|')]
        assert cells[0] == f'`{topic.name}`' and cells[1] == f'`{topic.interface}`'
        assert (topic.frame_id is None) == (cells[2] == '')
        assert f'depth {topic.depth}' in cells[3]
        assert ('latched' in cells[3]) == topic.latched
        assert cells[4].startswith(', '.join(topic.producers))


def test_a_changed_registry_makes_the_readme_check_fail(monkeypatch, tmp_path):
    readme = tmp_path / 'README.md'
    readme.write_text('intro\n<!-- topics:begin -->\nold\n<!-- topics:end -->\nrest\n')
    assert topic_table.main([str(readme)]) == 0
    current = readme.read_text()
    assert current.startswith('intro\n') and current.endswith('\nrest\n')
    assert marked_section(current, 'topics') == topic_table.render_topic_table()
    assert rewrite_marked(readme, 'topics', topic_table.render_topic_table()) is False
    changed = dict(wire.TOPICS)
    changed[wire.POSE] = wire.Topic(**{**vars(wire.TOPICS[wire.POSE]), 'depth': 7})
    monkeypatch.setattr(topic_table, 'TOPICS', changed)
    assert marked_section(current, 'topics') != topic_table.render_topic_table()


def test_missing_markers_are_refused_with_the_file_named(tmp_path, capsys):
    doc = tmp_path / 'doc.md'
    doc.write_text('no markers\n')
    assert topic_table.main([str(doc)]) == 2
    assert str(doc) in capsys.readouterr().err
    assert doc.read_text() == 'no markers\n'
    with pytest.raises(ValueError):
        replace_marked('<!-- topics:end -->\n<!-- topics:begin -->\n', 'topics', 'x')


def _string_constants(tree: ast.AST) -> list[tuple[str, int]]:
    """Every string constant of a module that is not a docstring."""
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                       ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr)
                  and isinstance(node.body[0].value, ast.Constant)}
    return [(node.value, node.lineno) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and id(node) not in docstrings]


def test_the_node_modules_take_every_topic_name_from_the_registry():
    names = set(wire.TOPICS) | {'/' + n for n in wire.TOPICS}
    literals = []
    for path in sorted((ROOT / 'gnsscam_ros' / 'nodes').glob('*.py')):
        for value, line in _string_constants(ast.parse(path.read_text())):
            if value in names:
                literals.append(f'{path.relative_to(ROOT)}:{line} {value!r}')
    assert not literals, literals


def test_the_scan_finds_a_topic_literal():
    # The scan above must see a topic named by hand, in code and not in a docstring.
    tree = ast.parse('"""pose"""\ndef f(node):\n    node.create_publisher(T, "pose", 10)\n')
    assert [v for v, _ in _string_constants(tree) if v in wire.TOPICS] == ['pose']


def test_every_producer_and_consumer_is_a_node_or_the_dataset():
    known = {*NODES, wire.DATASET, wire.EVERY_NODE}
    for topic in wire.TOPICS.values():
        assert set(topic.producers) <= known and set(topic.consumers) <= set(NODES), topic
        assert topic.reliability in (wire.RELIABLE, wire.BEST_EFFORT)
        assert topic.durability in (wire.VOLATILE, wire.TRANSIENT_LOCAL)
        assert topic.depth >= 1 and topic.record_depth >= 1
        # A once-only topic keeps its last message, for late subscribers and recorders.
        assert not topic.latched or topic.depth == topic.record_depth == 1


def test_node_to_node_topics_are_reliable():
    for topic in wire.TOPICS.values():
        if wire.DATASET not in topic.producers and topic.consumers:
            assert topic.reliability == wire.RELIABLE, topic.name


def test_the_bag_layout_is_the_registry():
    assert list(schema.DATASET_TOPICS) == list(wire.DATASET_BAG_TOPICS)
    for layout in (schema.DATASET_TOPICS, schema.RESULT_TOPICS):
        assert all(spec is wire.TOPICS[name] for name, spec in layout.items())
    assert schema.TOPIC_TYPES == {t.name: t.msgtype for t in wire.TOPICS.values()}
    # Inputs of the nodes come from the dataset bag; the nodes' outputs from the nodes.
    for name in wire.DATASET_BAG_TOPICS:
        assert wire.DATASET in wire.TOPICS[name].producers
    for name in wire.RESULT_BAG_TOPICS:
        assert wire.TOPICS[name].producers == ('fusion_node',)
