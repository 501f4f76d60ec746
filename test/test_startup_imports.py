"""Node start-up: each node process imports only what it uses, so that a restarted node is
back in the graph quickly.

numba (with its first kernel load: ~2 s of start-up and first epoch here), scipy's
optimiser (~0.5-1 s) and OpenCV are imported by the nodes that use them: gnss_node
checks epochs in numpy and solves its fix after it has forwarded the epoch, imu_node dead
reckons in numpy, camera_node loads and queries the map database without scipy;
fusion_node loads everything its first epoch needs while it warms up, before it exists.
Each check runs in a fresh interpreter (this one has imported everything).
"""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Packages each light node must not import at start-up.
NOT_IMPORTED = {
    'gnss_node': ('numba', 'cv2', 'scipy'),
    'imu_node': ('numba', 'cv2', 'scipy'),
    'camera_node': ('numba', 'scipy'),
}


def imported_after(code: str, modules) -> list[str]:
    """Which of ``modules`` a fresh interpreter has imported after running ``code``."""
    probe = (f'{code}\nimport sys\n'
             f'print(" ".join(m for m in {tuple(modules)!r} if m in sys.modules))')
    result = subprocess.run([sys.executable, '-c', probe], cwd=ROOT, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return result.stdout.split()


@pytest.mark.ros
@pytest.mark.parametrize('node', sorted(NOT_IMPORTED))
def test_a_light_node_imports_no_heavy_package(node):
    assert imported_after(f'import gnsscam_ros.nodes.{node}', NOT_IMPORTED[node]) == []


@pytest.mark.ros
def test_gnss_node_checks_and_forwards_an_epoch_without_numba():
    code = '\n'.join([
        'import numpy as np',
        'import msg_adapters as ma',
        'from gnsscam_ros.nodes import gnss_node',
        'from gnsscam_ros.core.types import GnssEpoch',
        'k = 8',
        'epoch = GnssEpoch(stamp_ns=10**18, sv_pos_ecef_m=np.c_[np.full(k, 2.0e7), '
        'np.arange(k) * 1e6, np.ones(k)], pr_m=np.full(k, 2.1e7), var_m2=np.full(k, 4.0), '
        'sv_id=np.arange(1, k + 1), system=np.ones(k, dtype=int), '
        'elevation_deg=np.full(k, 30.0), cn0_dbhz=np.full(k, 40.0))',
        "epoch = ma.pointcloud2_to_gnss_epoch(ma.gnss_epoch_to_pointcloud2(epoch), 'earth')",
        'check = gnss_node.check_epoch(epoch, 4, 10.0, 20.0)',
        'assert check.usable, check',
        'ma.gnss_epoch_to_pointcloud2(epoch.subset(check.keep))',
    ])
    assert imported_after(code, ('numba', 'cv2', 'scipy')) == []


@pytest.mark.slow
def test_fusion_node_warm_up_imports_what_its_first_fix_needs():
    # The snapshot fix imports scipy's optimiser on first use; the warm-up solves one.
    code = 'from gnsscam_ros.core.warmup import warm_up_kernels\nwarm_up_kernels()'
    assert imported_after(code, ('numba', 'scipy.optimize')) == ['numba', 'scipy.optimize']
