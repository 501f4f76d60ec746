"""Limits of the same quantity in two layers: the message layer's (``msg_adapters.limits``,
what one message may carry) and the core's backstops (``core.engine``,
``core.gnss_checks``), named by layer, in the order their comments give."""
from gnsscam_ros.core import engine, gnss_checks
from msg_adapters import limits


def test_the_core_never_refuses_as_corrupt_what_a_message_may_carry():
    assert limits.MAX_MESSAGE_YAW_RATE_RPS < engine.MAX_DR_YAW_RATE_RPS
    assert limits.MAX_SPEED_MPS <= engine.MAX_DR_SPEED_MPS
    assert limits.MAX_POSITION_M <= engine.MAX_ODOM_COORDINATE
    assert limits.MAX_MESSAGE_SATELLITE_RADIUS_M < gnss_checks.MAX_SATELLITE_RADIUS_M
    assert limits.MAX_MESSAGE_PSEUDORANGE_M < gnss_checks.MAX_PSEUDORANGE_M


def test_a_message_may_carry_more_satellites_than_an_epoch_uses():
    # The filter keeps the strongest MAX_EPOCH_SATELLITES; the parser must not choose.
    assert limits.MAX_MESSAGE_SATELLITES > gnss_checks.MAX_EPOCH_SATELLITES


def test_no_limit_name_means_two_values_across_the_layers():
    core = {**vars(engine), **vars(gnss_checks)}
    clashes = {name: (value, core[name]) for name, value in vars(limits).items()
               if name.isupper() and name in core and core[name] != value}
    assert not clashes, clashes
