"""package.xml as rosdep, colcon and ament read it; the LICENSE it names.

* every dependency key is one checked for ROS 2 Jazzy (``test/data/rosdep_keys.txt``):
  ``rosdep install --from-paths src`` fails on a single unknown key;
* every ament linter declared as a test dependency has its test in ``test/`` (what
  ``colcon test`` runs for an ament_python package);
* the LICENSE file is the license package.xml and setup.py name.
"""
import ast
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KEYS_FILE = ROOT / 'test' / 'data' / 'rosdep_keys.txt'
# The ament linters that ament_python packages run through a test file of their own.
LINTERS = {'ament_copyright': 'test_copyright.py', 'ament_flake8': 'test_flake8.py',
           'ament_pep257': 'test_pep257.py', 'ament_xmllint': 'test_xmllint.py',
           'ament_mypy': 'test_mypy.py'}


def package() -> ET.Element:
    return ET.parse(ROOT / 'package.xml').getroot()


def dependencies(root: ET.Element) -> dict[str, list[str]]:
    """``{key: [tags]}`` of every ``*depend`` element."""
    out: dict[str, list[str]] = {}
    for element in root:
        if isinstance(element.tag, str) and element.tag.endswith('depend'):
            out.setdefault(element.text.strip(), []).append(element.tag)
    return out


def known_keys() -> set[str]:
    lines = KEYS_FILE.read_text(encoding='utf-8').splitlines()
    return {line.strip() for line in lines if line.strip() and not line.startswith('#')}


def test_every_dependency_is_a_known_rosdep_key():
    deps = dependencies(package())
    assert deps, 'package.xml declares no dependencies'
    unknown = sorted(set(deps) - known_keys())
    assert not unknown, (f'package.xml keys not checked for Jazzy: {unknown}; check them in '
                         f'the rosdistro index and add them to {KEYS_FILE.name}')
    # The key the issue was about: a pip key that does not exist.
    assert 'python3-pymap3d-pip' not in deps and 'python3-pymap3d' in deps


def test_known_keys_file_is_well_formed():
    keys = known_keys()
    assert 'python3-pymap3d-pip' not in keys and 'python3-rosbags-pip' not in keys
    assert all(' ' not in k for k in keys), [k for k in keys if ' ' in k]


def test_runtime_and_test_dependencies_are_declared():
    deps = dependencies(package())
    for key in ('rclpy', 'sensor_msgs', 'diagnostic_msgs', 'nav_msgs', 'geometry_msgs',
                'python3-numpy', 'python3-scipy', 'python3-opencv', 'python3-pymap3d'):
        assert 'exec_depend' in deps.get(key, []), key
    for key in ('python3-pytest', 'python3-hypothesis', 'python3-colcon-common-extensions',
                'ament_index_python'):
        assert 'test_depend' in deps.get(key, []), key


def test_each_declared_ament_linter_has_its_test():
    deps = dependencies(package())
    declared = [k for k in deps if k in LINTERS]
    assert 'ament_flake8' in declared
    for linter in declared:
        test = ROOT / 'test' / LINTERS[linter]
        assert test.is_file(), f'{linter} is a test_depend but {test} is missing'
        assert f"'{linter}." in test.read_text(encoding='utf-8'), test


def test_license_file_matches_package_xml_and_setup_py():
    root = package()
    licenses = [e.text.strip() for e in root.findall('license')]
    assert licenses == ['Apache-2.0']
    setup = ast.parse((ROOT / 'setup.py').read_text(encoding='utf-8'))
    setup_license = [ast.literal_eval(k.value) for k in ast.walk(setup)
                     if isinstance(k, ast.keyword) and k.arg == 'license']
    assert setup_license == ['Apache-2.0']
    text = (ROOT / 'LICENSE').read_text(encoding='utf-8')
    head = ' '.join(text.split()[:6])
    assert head == 'Apache License Version 2.0, January 2004', head
    assert 'TERMS AND CONDITIONS FOR USE, REPRODUCTION, AND DISTRIBUTION' in text
    assert 'END OF TERMS AND CONDITIONS' in text
    assert 'APPENDIX: How to apply the Apache License to your work.' in text
