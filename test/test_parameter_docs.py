"""The parameter reference (``nodes.parameter_reference``) rendered from the metadata:
its columns, its command, and docs/nodes.md kept current. No rclpy needed."""
from pathlib import Path

from gnsscam_ros.core.parameters import PARAMETER_SECTION
from gnsscam_ros.io.marked import marked_section
from gnsscam_ros.nodes import parameter_reference


def table_rows() -> dict[tuple[str, str], list[str]]:
    """``{(node, parameter): cells}`` of the rendered reference."""
    text = parameter_reference.render_parameter_reference()
    body = marked_section(text, PARAMETER_SECTION).splitlines()
    rows = {}
    for line in body[2:]:
        cells = [c.strip() for c in line.strip('|').split(' | ')]
        node = cells[-1].split(':', 1)[0]
        key = (node, cells[0].strip('`'))
        assert key not in rows, f'{key} twice in the reference'
        rows[key] = cells
    return rows


def test_the_reference_shows_units_ranges_and_provenance():
    rows = table_rows()
    name, default, unit, admissible, meaning, provenance, where = rows[
        ('fusion_node', 'error_correlation_time_s')]
    assert (default, unit, admissible) == ('`10.0`', 's', '>= 0')
    assert 'smartLoc' in provenance and 'Correlation time' in meaning
    assert where == 'fusion_node: FilterConfig.gnss'
    assert rows[('fusion_node', 'odometry_wait_s')][3] == 'in [0, 10]'
    assert rows[('fusion_node', 'odometry_wait_s')][-1] == 'fusion_node: InputTiming'
    assert rows[('imu_node', 'yaw_rate_source')][3] == 'one of odometry, imu'


def test_the_command_rewrites_the_marked_section(tmp_path):
    doc = tmp_path / 'params.md'
    doc.write_text('# Parameters\n<!-- parameters:begin -->\n<!-- parameters:end -->\n')
    assert parameter_reference.main([str(doc)]) == 0
    assert doc.read_text() == '# Parameters\n' + parameter_reference.render_parameter_reference()
    assert parameter_reference.main([str(tmp_path / 'missing.md')]) == 4
    (tmp_path / 'plain.md').write_text('no markers\n')
    assert parameter_reference.main([str(tmp_path / 'plain.md')]) == 2


def test_docs_nodes_md_holds_the_reference_rendered():
    path = Path(__file__).resolve().parents[1] / 'docs' / 'nodes.md'
    expected = marked_section(parameter_reference.render_parameter_reference(),
                              PARAMETER_SECTION)
    assert marked_section(path.read_text(encoding='utf-8'), PARAMETER_SECTION) == expected, (
        'docs/nodes.md is out of date: python -m gnsscam_ros.nodes.parameter_reference '
        'docs/nodes.md')


def test_every_node_yaml_is_its_parameters_rendered():
    config = Path(__file__).resolve().parents[1] / 'config'
    for node in parameter_reference.NODE_PARAMETERS:
        text = (config / f'{node}.yaml').read_text(encoding='utf-8')
        assert parameter_reference.update_node_yaml(text, node) == text, (
            f'config/{node}.yaml is out of date: python -m '
            f'gnsscam_ros.nodes.parameter_reference config/{node}.yaml')


def test_a_yaml_file_of_no_node_is_refused(tmp_path, capsys):
    other = tmp_path / 'other_node.yaml'
    other.write_text('other_node:\n  ros__parameters:\n    x: 1\n')
    assert parameter_reference.main([str(other)]) == 2
    assert 'not the YAML file of a node' in capsys.readouterr().err
    stale = tmp_path / 'gnss_node.yaml'
    stale.write_text('# head\ngnss_node:\n  ros__parameters:\n    min_satellites: 9\n')
    assert parameter_reference.main([str(stale)]) == 0
    text = stale.read_text()
    assert text.startswith('# head\n') and '    min_satellites: 4\n' in text
