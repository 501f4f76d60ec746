"""Shared fixtures. Tests never read ../shared: fixtures live in test/data."""
import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

DATA = Path(__file__).parent / 'data'
SMARTLOC_EXCERPT = DATA / 'smartloc_excerpt'


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope='session')
def smartloc_excerpt():
    from gnsscam_ros.datasets.smartloc import discover_files, load_smartloc
    return load_smartloc(*discover_files(SMARTLOC_EXCERPT))
