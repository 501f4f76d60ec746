"""The one integrity verdict (core.verdict): each finding of the filter against OK, in
its order, and the limit-independent part (``valid``)."""
import math

import numpy as np
import pytest

from gnsscam_ros.core.config import FilterConfig
from gnsscam_ros.core.consistency import ConsistencyState
from gnsscam_ros.core.filter import INVALID, PROPAGATED, UPDATED, EpochResult
from gnsscam_ros.core.integrity import RiskBound
from gnsscam_ros.core.verdict import ERROR, OK, STALE, integrity_verdict

CONFIG = FilterConfig(alert_limit_m=10.0, extra_alert_limits_m=(20.0,), target_risk=0.1,
                      integrity_settling_s=30.0)


def _result(bound=0.05, level_m=6.0, settling_s=40.0, motion_unknown_s=0.0,
            inconsistent=False, status=UPDATED):
    risk = RiskBound(alert_limits_m=np.array([10.0, 20.0]),
                     empirical_risk=np.array([bound / 2, 0.0]),
                     divergence_risk=np.array([bound / 2, 0.01]),
                     risk_bound=np.array([bound, 0.01]), kl_nats=0.5, epsilon=0.02)
    return EpochResult(stamp_ns=7, status=status, reason='' if status == UPDATED else 'why',
                       position_enu_m=np.zeros(3), covariance_m2=np.eye(3), yaw_rad=0.0,
                       risk=risk if status == UPDATED else None,
                       protection_level_m=level_m if status == UPDATED else None,
                       settling_s=settling_s, motion_unknown_s=motion_unknown_s,
                       consistency=ConsistencyState(statistic_nats=3.0 if inconsistent
                                                    else 0.0, separation_m=4.0,
                                                    inconsistent=inconsistent))


def test_every_finding_for_ok_gives_ok_with_its_figures():
    verdict = integrity_verdict(_result(), CONFIG, dead_reckoning_resets=2)
    assert verdict.level == OK and verdict.ok and verdict.valid and verdict.reasons == ()
    assert verdict.message.startswith('integrity sufficient: protection level 6.0 m')
    assert (verdict.risk_bound, verdict.protection_level_m, verdict.alert_limit_m) == (
        0.05, 6.0, 10.0)
    assert verdict.risk_bounds_by_limit == {20.0: 0.01}
    assert verdict.details['dead_reckoning_resets'] == 2
    assert verdict.details['integrity_valid'] is True


@pytest.mark.parametrize('finding, words, valid', [
    ({'motion_unknown_s': 0.5}, 'motion unknown', False),
    ({'inconsistent': True}, 'inconsistent', False),
    ({'settling_s': 29.9}, 'settling', False),
    ({'settling_s': -1.0}, 'settling', False),
    ({'level_m': 10.5}, 'protection level 10.5 m above the alert limit 10 m', True),
    ({'level_m': math.inf}, 'protection level inf m above', True),
    ({'bound': 0.15}, 'risk bound 0.15 > target 0.1', True),
])
def test_each_finding_against_ok_alone_makes_an_error(finding, words, valid):
    verdict = integrity_verdict(_result(**finding), CONFIG)
    assert verdict.level == ERROR and not verdict.ok
    assert len(verdict.reasons) == 1 and words in verdict.reasons[0]
    assert verdict.message == f'integrity insufficient: {verdict.reasons[0]}'
    # valid: what does not depend on the alert limit (motion known, settled).
    assert verdict.valid is valid


def test_reasons_come_most_fundamental_first():
    verdict = integrity_verdict(_result(bound=0.5, level_m=30.0, settling_s=0.0,
                                        motion_unknown_s=1.0, inconsistent=True), CONFIG)
    assert [r.split()[0] for r in verdict.reasons] == [
        'dead', 'the', 'settling', 'protection', 'risk']
    assert 'motion unknown' in verdict.message


def test_no_update_is_stale_and_says_why():
    verdict = integrity_verdict(_result(status=PROPAGATED), CONFIG, 'restarting')
    assert verdict.level == STALE and not verdict.valid and math.isnan(verdict.risk_bound)
    assert verdict.reasons == ('no valid solution (propagated): why', 'restarting')
    assert verdict.message == 'no valid solution (propagated): why; restarting'
    assert verdict.epoch_status == PROPAGATED and verdict.epoch_stamp_ns == 7
    # The epoch that discarded the state says so itself, once.
    invalid = integrity_verdict(_result(status=INVALID), CONFIG, 'restarting')
    assert invalid.reasons == ('no valid solution (invalid): why',)
