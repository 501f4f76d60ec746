"""The filter configuration: parts with one source per parameter, flat names on top.

* every parameter has a doc, a unit matching its name's suffix, and an admissible default;
* validation follows the metadata (ranges, open bounds, choices) and names every problem;
* flat construction, reading and ``dataclasses.replace`` work as on a flat dataclass;
* config/fusion_node.yaml's filter block is the one the metadata renders.
"""
import dataclasses
import math
import pickle
from pathlib import Path

import pytest
import yaml

from gnsscam_ros.core import config as cfgmod
from gnsscam_ros.core.config import (PARTS, CameraConfig, FilterConfig, ParameterSpec, Range,
                                     render_yaml_block, update_yaml, yaml_value)

ROOT = Path(__file__).resolve().parents[1]
SPECS = FilterConfig.parameter_specs()
# Unit implied by a name's suffix (units in names); the longest matching suffix wins.
SUFFIX_UNITS = {'_m': 'm', '_m2': 'm^2/s', '_rad2': 'rad^2/s', '_s': 's', '_deg': 'deg',
                '_dbhz': 'dB-Hz', '_mps': 'm/s', '_rps': 'rad/s', '_nats': 'nats',
                '_m2_per_m': 'm^2/m'}


def test_every_parameter_is_documented_once_with_the_unit_of_its_name():
    names = [s.name for s in SPECS]
    assert len(names) == len(set(names))
    assert {s.part for s in SPECS} == {name for name, _ in PARTS}
    for spec in SPECS:
        assert spec.doc.endswith('.') and '[' not in spec.doc, spec.name
        suffix = max((k for k in SUFFIX_UNITS if spec.name.endswith(k)), key=len, default='')
        if suffix == '_m2':          # a variance: per second or not, as the doc says
            assert spec.unit in ('m^2', 'm^2/s'), spec.name
        elif suffix:
            assert spec.unit == SUFFIX_UNITS[suffix], spec.name
        else:
            assert spec.unit == '', spec.name
        assert spec.problem(spec.default) is None, spec.name
        assert isinstance(spec.default, (bool, int, float, str, tuple)), spec.name


def test_defaults_and_flat_reads_come_from_the_parts():
    config = FilterConfig()
    flat = config.as_flat()
    assert list(flat) == [s.name for s in SPECS]
    for spec in SPECS:
        part = getattr(config, spec.part)
        assert getattr(config, spec.name) == getattr(part, spec.name) == spec.default
    assert list(config.as_parameters()) == [s.name for s in SPECS if s.node_parameter]
    assert 'extra_alert_limits_m' not in config.as_parameters()
    assert FilterConfig.from_flat(flat) == config
    assert [f.name for f in dataclasses.fields(FilterConfig)] == [n for n, _ in PARTS]


def test_flat_construction_replace_and_parts():
    config = FilterConfig(alert_limit_m=25, n_particles=300, use_camera=False)
    assert (config.alert_limit_m, config.n_particles, config.use_camera) == (25, 300, False)
    assert config.integrity.alert_limit_m == 25 and config.camera.use_camera is False
    changed = dataclasses.replace(config, alert_limit_m=16.0, likelihood='particle_raim')
    assert changed.alert_limit_m == 16.0 and changed.likelihood == 'particle_raim'
    assert changed.n_particles == 300 and config.alert_limit_m == 25      # a copy
    assert changed.camera is config.camera or changed.camera == config.camera
    # A whole part, with flat names overriding it.
    whole = FilterConfig(camera=CameraConfig(camera_gate_m=7.0), camera_temperature_m=2.0)
    assert (whole.camera_gate_m, whole.camera_temperature_m) == (7.0, 2.0)
    assert pickle.loads(pickle.dumps(changed)) == changed
    assert hash(changed) == hash(dataclasses.replace(changed))
    with pytest.raises(dataclasses.FrozenInstanceError):
        changed.n_particles = 5
    with pytest.raises(TypeError, match='alert_limit'):
        FilterConfig(alert_limit=3.0)
    with pytest.raises(TypeError, match='CameraConfig'):
        FilterConfig(camera=FilterConfig().integrity)


def test_alert_limits_and_derived_values():
    config = FilterConfig(alert_limit_m=8.0, extra_alert_limits_m=(16.0, 8.0, 25.0))
    assert config.alert_limits_m.tolist() == [8.0, 16.0, 25.0]
    assert FilterConfig(bias_model='none', n_posteriors=30).motion_sample_count == 30
    assert FilterConfig(n_posteriors=5, n_motion_samples=10).motion_sample_count == 5
    # The 'cn0' hypotheses are the part's model; the 'learned' ones decorrelate with the
    # GNSS errors (one error process, one correlation time).
    cn0 = FilterConfig(bias_model='cn0')
    assert cn0.bias == cn0.bias_hypotheses.model
    assert config.bias.correlation_time_s == config.error_correlation_time_s
    assert cn0.bias.correlation_time_s == cn0.bias_correlation_time_s
    assert config.bias.floor_m == config.bias_floor_m


def _outside(spec: ParameterSpec):
    """Values just outside each bound of the spec's range (and NaN for floats)."""
    r = spec.range
    out = []
    step = 1 if isinstance(spec.default, int) else 1e-9
    if r.low is not None:
        out.append(r.low if r.low_open else r.low - step)
    if r.high is not None:
        out.append(r.high if r.high_open else r.high + step)
    if isinstance(spec.default, float):
        out.append(math.nan)
    return out


@pytest.mark.parametrize('spec', [s for s in SPECS if s.range is not None],
                         ids=lambda s: s.name)
def test_ranges_refuse_what_lies_outside_and_take_the_bounds_they_include(spec):
    part_cls = dict(PARTS)[spec.part]
    for value in _outside(spec):
        with pytest.raises(ValueError, match=f'{spec.name} must be'):
            FilterConfig(**{spec.name: value})
        with pytest.raises(ValueError, match=spec.name):
            part_cls(**{spec.name: value})
    r = spec.range
    for bound, is_open in ((r.low, r.low_open), (r.high, r.high_open)):
        if bound is not None and not is_open:
            # The part takes it; the whole configuration too unless the sizes together
            # exceed the memory budget (then that is the only reason given).
            assert getattr(part_cls(**{spec.name: bound}), spec.name) == bound
            try:
                assert getattr(FilterConfig(**{spec.name: bound}), spec.name) == bound
            except ValueError as err:
                assert 'budget' in str(err) and f'{spec.name} must be' not in str(err)
                assert spec.name in ('n_particles', 'acquisition_particles', 'n_posteriors',
                                     'n_motion_samples')


def test_choices_and_every_problem_in_one_message():
    for spec in (s for s in SPECS if s.choices):
        for choice in spec.choices:
            assert getattr(FilterConfig(**{spec.name: choice}), spec.name) == choice
    with pytest.raises(ValueError) as info:
        FilterConfig(likelihood='magic', target_risk=1.5, n_particles=1)
    message = str(info.value)
    assert message.startswith('invalid filter configuration: ')
    assert "likelihood must be one of ('particle_raim', 'robust')" in message
    assert 'target_risk must be in (0, 1)' in message and 'n_particles' in message


def test_ranges_render_as_written_and_close_for_ros():
    assert str(Range(0.0, 1.0, True, True)) == 'in (0, 1)'
    assert str(Range(0.0, low_open=True)) == '> 0' and str(Range(1.0)) == '>= 1'
    assert str(Range(2, 10_000_000)) == 'in [2, 10000000]'
    assert Range(0.0).closed(1e12) == (0.0, 1e12)
    assert Range(high=3).closed(10) == (-10, 3)
    assert not Range(0.0).contains(math.nan)


def test_yaml_values_load_back_as_themselves():
    for value in (True, 3, 0.0003, 1e-05, 1e20, 'robust', 'a "b"', (), (8.0, 16.0)):
        loaded = yaml.safe_load(f'x: {yaml_value(value)}')['x']
        assert loaded == (list(value) if isinstance(value, tuple) else value), value
        assert type(loaded) is (list if isinstance(value, tuple) else type(value)), value


def test_fusion_node_yaml_filter_block_is_generated_from_the_metadata():
    path = ROOT / 'config' / 'fusion_node.yaml'
    text = path.read_text(encoding='utf-8')
    assert update_yaml(text) == text, (
        f'{path} is out of date: python -m gnsscam_ros.core.config config/fusion_node.yaml')
    block = render_yaml_block()
    assert block in text
    params = yaml.safe_load(text)['fusion_node']['ros__parameters']
    comments = ' '.join(line.strip()[2:] for line in block.splitlines()
                        if line.strip().startswith('# '))
    for spec in SPECS:
        if spec.node_parameter:
            assert params[spec.name] == spec.default, spec.name
            assert f'{spec.description} Default: {yaml_value(spec.default)}' in comments
        else:
            assert spec.name not in params
    assert max(len(line) for line in text.splitlines()) <= 99


def test_update_yaml_needs_its_markers_and_main_rewrites(tmp_path):
    with pytest.raises(ValueError, match='generated block'):
        update_yaml('fusion_node:\n  ros__parameters:\n    seed: -1\n')
    stale = tmp_path / 'fusion_node.yaml'
    stale.write_text('head\n' + cfgmod.YAML_BEGIN + '\n    n_particles: 3\n'
                     + cfgmod.YAML_END + '\n    seed: -1\n', encoding='utf-8')
    assert cfgmod.main([str(stale)]) == 0
    text = stale.read_text(encoding='utf-8')
    assert text.startswith('head\n') and text.endswith(cfgmod.YAML_END + '\n    seed: -1\n')
    # The stale value is replaced by the default's.
    assert update_yaml(text) == text
    assert f'    n_particles: {FilterConfig().n_particles}\n' in text
    assert 'n_particles: 3\n' not in text
    assert cfgmod.main([]) == 2


def test_part_docstrings_list_their_parameters():
    for _, cls in PARTS:
        for spec in (s for s in SPECS if dict(PARTS)[s.part] is cls):
            assert f'        {spec.name}: ' in cls.__doc__, spec.name


# ===================================================================== memory budget
def test_sizes_admissible_one_by_one_are_refused_together_beyond_the_memory_budget():
    """n_particles up to 10,000,000 and n_posteriors up to 10,000 are each in range; what
    an epoch of them would allocate is not: refused with the estimate, before anything
    is allocated."""
    budget = cfgmod.EPOCH_MEMORY_BUDGET_BYTES
    assert budget == 2 * 2 ** 30
    assert FilterConfig().epoch_memory_bytes() < budget / 4          # the defaults
    for values, figure in (({'n_particles': 10_000_000, 'n_posteriors': 10_000}, '6,729.4'),
                           ({'n_particles': 10_000_000}, '158.0'),
                           ({'n_posteriors': 10_000, 'bias_model': 'none'}, '83.5')):
        with pytest.raises(ValueError) as info:
            FilterConfig(**values)
        text = str(info.value)
        assert text.startswith('invalid filter configuration: an epoch would need an '
                               f'estimated {figure} GiB of memory') and '\n' not in text
        assert text.endswith('16 satellites), more than the 2.0 GiB budget'), text
    # A change goes through the same check (dataclasses.replace validates): refused.
    config = FilterConfig(n_particles=2000)
    with pytest.raises(ValueError, match='budget'):
        dataclasses.replace(config, n_particles=5_000_000)
    assert config.n_particles == 2000


def test_large_sizes_use_fewer_satellites_instead_of_more_memory():
    """Up to 64 satellites per epoch; sizes that would exceed the budget with 64 use the
    strongest that fit (the largest sizes this repository benchmarks and documents), so
    that no epoch can exceed it whatever a message holds."""
    default = FilterConfig()
    assert default.satellite_limit == 64 == cfgmod.MAX_EPOCH_SATELLITES
    for values, limit in (({'n_particles': 100_000, 'acquisition_particles': 0}, 50),
                          ({'bias_model': 'none'}, 23),
                          ({'bias_model': 'none', 'n_posteriors': 30}, 64)):
        config = FilterConfig(**values)
        assert config.satellite_limit == limit, values
        assert config.epoch_memory_bytes() <= cfgmod.EPOCH_MEMORY_BUDGET_BYTES
        assert config.epoch_memory_bytes(limit + 1) > cfgmod.EPOCH_MEMORY_BUDGET_BYTES \
            or limit == 64
    # Derived, not a parameter: equality, hashing and copies see the parameters only.
    assert dataclasses.replace(default) == default and 'satellite_limit' not in \
        default.as_flat()
    assert pickle.loads(pickle.dumps(default)).satellite_limit == 64
    # A minimum above what fits is refused as well (every epoch would be unusable).
    with pytest.raises(ValueError, match='30 satellites'):
        FilterConfig(bias_model='none', min_satellites=30)


def test_memory_estimate_grows_with_each_size_and_covers_heading_acquisition():
    est = cfgmod.epoch_memory_bytes
    base = est(1000, 0, 200, 10)
    assert est(2000, 0, 200, 10) > base and est(1000, 0, 400, 10) > base
    assert est(1000, 0, 200, 20) > base and est(1000, 0, 200, 10, satellites=12) < base
    # During heading acquisition the sets hold acquisition_particles; the bound sees them
    # thinned to about n_particles (every 10th of 10,000 here).
    assert est(1000, 10_000, 2000, 10, satellites=8) == (
        est(10_000, 0, 2000, 10, satellites=8) - 72 * 2000 * 9000)
    # The formula: S N (128 + 8 k) + max(32 S N k, 40 K S N, 72 M N_int) + 8 (256 + 64) M
    # + 16 MiB.
    assert est(100, 0, 10, 2, satellites=8, camera_images=4) == (
        16 * 2 ** 20 + 200 * (128 + 64) + max(32 * 200 * 8, 40 * 4 * 200, 72 * 10 * 100)
        + 8 * 320 * 10)
