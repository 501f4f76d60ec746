"""The supported platforms (docs/development.md "Platform tiers"): the forms that work on the
oldest numpy and OpenCV the tiers pin (Debian 12: numpy 1.24.2, OpenCV 4.6.0), the same
results as the newer forms where the newest versions have both, and the tiers' own files.

No rclpy needed: this runs in every tier.
"""
import importlib.util
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from synthetic import FRAME, epoch_at

from gnsscam_ros.core.filter import INVALID, UPDATED, FilterConfig, ParticleFilter
from gnsscam_ros.core.particles import MotionIncrement
from gnsscam_ros.core.rng import spawn, spawn_from_seed_sequence
from gnsscam_ros.datasets.emulated.config import STREAMS, stream_rng
from gnsscam_ros.vision.mapdb_cli import opencv_log_level_api

ROOT = Path(__file__).resolve().parents[1]
S = 1_000_000_000
TIERS = ('debian-bookworm', 'ubuntu-noble')


def _draws(generators, n=5):
    return [g.random(n).tolist() + g.integers(0, 2 ** 62, n).tolist() for g in generators]


# ============================================================== child random generators
def test_spawn_gives_the_children_of_the_seed_sequence():
    """On every numpy: child k of ``default_rng(seed)`` is the generator of child k of
    ``SeedSequence(seed)``, as ``Generator.spawn`` defines it; later calls give the next
    children, and the parent's own stream is untouched."""
    parent = np.random.default_rng(2024)
    first, second = spawn(parent, 2), spawn(parent, 1)
    children = np.random.SeedSequence(2024).spawn(3)
    expected = [np.random.Generator(np.random.PCG64(c)) for c in children]
    assert _draws(first + second) == _draws(expected)
    assert parent.random() == np.random.default_rng(2024).random()
    assert _draws(spawn_from_seed_sequence(np.random.default_rng(2024), 3)) == _draws(
        [np.random.Generator(np.random.PCG64(c)) for c in children])


@pytest.mark.skipif(not hasattr(np.random.Generator, 'spawn'),
                    reason='numpy < 1.25 has no Generator.spawn to compare with')
def test_the_fallback_is_generator_spawn_where_numpy_has_it():
    """The numpy 1.24 form gives the streams of ``Generator.spawn`` (so the newest
    environment's results do not change), for the default and another bit generator."""
    for make in (np.random.default_rng,
                 lambda s: np.random.Generator(np.random.Philox(np.random.SeedSequence(s)))):
        native, fallback = make(7), make(7)
        assert _draws(native.spawn(3)) == _draws(spawn_from_seed_sequence(fallback, 3))
        assert _draws(native.spawn(1)) == _draws(spawn_from_seed_sequence(fallback, 1))
        assert type(spawn(make(7), 1)[0].bit_generator) is type(make(7).bit_generator)


def test_camera_stream_children_are_those_of_its_seed_sequence():
    """The emulated camera's light, fault and exposure streams: the children of the
    ``camera`` stream's seed sequence (what the numpy >= 1.25 code drew)."""
    seed = 11
    camera_seq = np.random.SeedSequence(seed).spawn(len(STREAMS))[STREAMS.index('camera')]
    expected = [np.random.default_rng(c) for c in camera_seq.spawn(3)]
    assert _draws(spawn(stream_rng(seed, 'camera'), 3)) == _draws(expected)


# ==================================================== numerical failures reset the state
@pytest.mark.parametrize('error', [np.linalg.LinAlgError('Eigenvalues did not converge'),
                                   FloatingPointError('overflow encountered in exp')])
def test_a_linear_algebra_failure_discards_the_state(error):
    """numpy < 1.26 raises LinAlgError as no ValueError (Debian 12's 1.24): a singular or
    non-converging matrix (bias.py's inv and eigh) must still discard the state, not
    escape from the step."""
    filt = ParticleFilter(FilterConfig(n_particles=200, n_posteriors=20,
                                       acquisition_particles=0), frame=FRAME,
                          rng=np.random.default_rng(3))
    motion = MotionIncrement(1.0, 8.0, 0.0, 0.01, 1e-5)
    for i in range(2):
        assert filt.step(epoch_at([8.0 * i, 0, 0], stamp_ns=i * S),
                         None if i == 0 else motion).status == UPDATED

    class Raising:
        def joint(self, *args):
            raise error

    working, filt.likelihood = filt.likelihood, Raising()
    result = filt.step(epoch_at([16.0, 0, 0], stamp_ns=2 * S), motion)
    assert result.status == INVALID and type(error).__name__ in result.reason
    assert not filt.initialised and filt.last_stamp_ns == 1 * S
    filt.likelihood = working
    assert filt.step(epoch_at([24.0, 0, 0], stamp_ns=3 * S), None).status == UPDATED


# ========================================================================== OpenCV
def test_opencv_log_level_is_set_and_restored_on_this_opencv():
    """``cv2.utils.logging`` is OpenCV >= 4.13; 4.6 has ``cv2.setLogLevel``: either way
    the level goes to silent and back."""
    get_level, set_level, silent = opencv_log_level_api()
    before = get_level()
    set_level(silent)
    try:
        assert get_level() == silent == 0
    finally:
        set_level(before)
    assert get_level() == before
    if not hasattr(getattr(cv2, 'utils', None), 'logging'):
        assert (get_level, set_level) == (cv2.getLogLevel, cv2.setLogLevel)


# ===================================================================== the tiers' files
def _pins(tier: str) -> dict:
    text = (ROOT / 'constraints' / f'{tier}.txt').read_text(encoding='utf-8')
    pins = dict(re.findall(r'^([A-Za-z0-9._-]+)==(\S+)$', text, flags=re.M))
    pins.update(re.findall(r'^# import: (cv2)==(\S+)$', text, flags=re.M))
    return pins


def _minimums() -> dict:
    text = (ROOT / 'requirements.txt').read_text(encoding='utf-8')
    return {name.lower(): tuple(int(p) for p in version.split('.'))
            for name, version in re.findall(r'^([A-Za-z0-9_-]+)(?:\[\w+\])?>=([\d.]+)$',
                                            text, flags=re.M)}


def _version(text: str) -> tuple:
    return tuple(int(p) for p in re.findall(r'\d+', text)[:3])


def test_requirements_minimums_are_what_a_tier_tests():
    """Each minimum of requirements.txt that a tier pins is the oldest pinned version (the
    one the suite runs with), not a guess."""
    minimums = _minimums()
    pinned = {}
    for tier in TIERS:
        for name, version in _pins(tier).items():
            key = {'cv2': 'opencv-python-headless'}.get(name, name).lower()
            pinned.setdefault(key, []).append(_version(version))
    checked = 0
    for name, versions in pinned.items():
        if name in minimums:
            oldest = min(versions)
            assert minimums[name] == oldest[:len(minimums[name])], (name, versions)
            checked += 1
    assert checked >= 7


def test_the_run_script_knows_each_tier_and_the_ci_runs_them():
    run = (ROOT / 'run').read_text(encoding='utf-8')
    ci = (ROOT / '.ci' / 'run').read_text(encoding='utf-8')
    for tier in TIERS:
        assert f'{tier})' in run and f'--tier {tier}' in ci
    # Debian's apt packages are named in one place, the constraints file, and each is a
    # rosdep key of package.xml.
    text = (ROOT / 'constraints' / 'debian-bookworm.txt').read_text(encoding='utf-8')
    apt = ' '.join(re.findall(r'^# apt: (.*)$', text, flags=re.M)).split()
    package_xml = (ROOT / 'package.xml').read_text(encoding='utf-8')
    assert apt and all(f'<exec_depend>{name}</exec_depend>' in package_xml for name in apt)


def test_check_bootstrap_compares_the_pins(tmp_path):
    spec = importlib.util.spec_from_file_location('check_bootstrap',
                                                  ROOT / 'tools' / 'check_bootstrap.py')
    cb = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cb)
    constraints = tmp_path / 'tier.txt'
    constraints.write_text(f'# a comment\nnumpy=={np.__version__}\npytest==0.0.1\n'
                           f'no-such-dist-xyz==1.0\n# import: cv2=={cv2.__version__}\n'
                           '# import: json==9\n')
    dists, modules = cb.read_pins(constraints)
    assert dists == {'numpy': np.__version__, 'pytest': '0.0.1', 'no-such-dist-xyz': '1.0'}
    problems = cb.version_problems(dists, modules)
    assert problems == [f'pytest is {pytest.__version__}, pinned to 0.0.1',
                        'no-such-dist-xyz==1.0 is pinned but not installed',
                        'json.__version__ is 2.0.9, pinned to 9']
    assert cb.main([str(ROOT), str(tmp_path), '--constraints']) == 2
