"""What ``pip wheel .`` installs: the product, never the workshop.

The fault-injection kit (``tools/fuzz``) and the other developer tools under ``tools/``
serve the tests and the hand-run campaigns; a robot installing the package gets neither.
The wheel is built from a copy of the source tree (the build leaves ``build/`` and
``*.egg-info`` behind, which must not land in the working tree while other tests run).
"""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: What setup.py reads to build (package sources, data files, metadata).
SOURCES = ('setup.py', 'setup.cfg', 'package.xml', 'LICENSE', 'resource', 'config',
           'gnsscam_ros', 'msg_adapters', 'tools')


@pytest.fixture(scope='module')
def wheel(tmp_path_factory) -> dict[str, bytes]:
    """``{path in the wheel: content}`` of a wheel built from a copy of the tree."""
    src = tmp_path_factory.mktemp('wheel_src')
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name,
                            ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
        else:
            shutil.copy2(path, src / name)
    out = tmp_path_factory.mktemp('wheel_out')
    proc = subprocess.run([sys.executable, '-m', 'pip', 'wheel', str(src), '--no-deps',
                           '--no-build-isolation', '--no-index', '-q', '-w', str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    wheels = list(out.glob('gnsscam_ros-*.whl'))
    assert len(wheels) == 1, wheels
    with zipfile.ZipFile(wheels[0]) as zf:
        return {name: zf.read(name) for name in zf.namelist()}


def test_wheel_holds_the_product(wheel):
    top = {name.split('/')[0] for name in wheel}
    assert {'gnsscam_ros', 'msg_adapters'} <= top, sorted(top)
    for module in ('gnsscam_ros/core/engine.py', 'gnsscam_ros/bench/filter.py',
                   'msg_adapters/__init__.py'):
        assert module in wheel, module


def test_wheel_holds_no_fault_injection_code(wheel):
    kit = {p.read_bytes(): p.name for p in (ROOT / 'tools' / 'fuzz').glob('*.py')}
    assert {'corrupt_inputs.py', 'messages.py', '__main__.py'} <= set(kit.values())
    by_path = [name for name in wheel if name.startswith('tools/') or 'fuzz' in name]
    assert not by_path, f'the wheel ships the workshop: {by_path}'
    # Nor a copy of a kit module under another package.
    copies = sorted(f'{name} (= tools/fuzz/{kit[data]})' for name, data in wheel.items()
                    if name.endswith('.py') and data in kit and data.strip())
    assert not copies, f'the wheel ships the workshop: {copies}'
