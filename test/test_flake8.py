"""ament_flake8, as ``colcon test`` runs it on a ROS 2 machine (package.xml declares it).

Skipped where the ament linter is not installed (the project's PyPI virtual environment,
where ``./run test`` runs plain flake8 with the same setup.cfg rules).
"""
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch):
    ament_flake8 = pytest.importorskip(
        'ament_flake8.main', reason='ament_flake8 not installed (rosdep install on ROS 2)')
    # ament_flake8 checks the working directory and skips its hidden folders (.venv).
    monkeypatch.chdir(ROOT)
    # The package's own flake8 rules (setup.cfg [flake8]: 99 columns, pycodestyle and
    # pyflakes), not ament's default plugin set.
    rc, errors = ament_flake8.main_with_errors(argv=[
        '--config', str(ROOT / 'setup.cfg'), '--exclude', 'build', 'install', 'log', 'out'])
    assert rc == 0, f'{len(errors)} code style errors:\n' + '\n'.join(errors)
