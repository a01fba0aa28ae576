"""The slippage monitor's settings (`SlipSettings`): keywords to `SlipMonitor` override a settings object,
derived values are worked out once, and contradictory or out-of-range settings are refused in one line."""

from __future__ import annotations

import math

import pytest

from flockcal.solver.slippage import SlipMonitor, SlippageError, SlipSettings


def test_keywords_override_the_settings_given_and_leave_the_rest():
    # Tried: a settings object for a short warm-up, then a monitor made from it with another threshold.
    base = SlipSettings(warmup_s=2.0, frame_step=None)
    mon = SlipMonitor([[1, 0], [2, 1]], 3, 100.0, ["a", "b", "c"], base, threshold=30.0)
    assert (mon.settings.warmup_s, mon.settings.threshold, mon.settings.frame_step) == (2.0, 30.0, None)
    assert base.threshold == 25.0  # the object given is not changed
    assert SlipMonitor([[1, 0]], 2, 100.0, warmup_s=3.0).settings.warmup_s == 3.0
    assert SlipMonitor([[1, 0]], 2, 100.0).settings == SlipSettings()
    assert mon.status()["threshold"] == 30.0


def test_derived_values_follow_the_options():
    # Two shares give the confirming test one share for both kinds of sensor; frame_step None turns the
    # frame test off, and with it the higher bar where the step test raised nothing.
    s = SlipSettings(extrapolation_share=(0.5, 0.25), second_look=(0.3, 0.0), frame_step=None)
    assert s.shares == (0.5, 0.25, 0.25)
    assert s.second_look_shares == (1.0, 0.3, 0.0)
    assert s.frame_step_nats is None and math.isinf(s.frame_step_alone_nats)
    d = SlipSettings()
    assert (d.shares, d.second_look_shares, d.frame_step_nats, d.frame_step_alone_nats) == ((1.0, 1.0, 1.0), None, 20.0, 25.0)
    assert SlipSettings(frame_step=30.0, frame_step_alone=25.0).frame_step_alone_nats == 30.0  # never below frame_step


@pytest.mark.parametrize("options, message", [
    ({"lag_s": 0.5, "window_s": 0.5}, "lag_s must exceed window_s"),
    ({"attribute_s": 0.5, "confirm_s": 0.4}, "confirm_s must be at least attribute_s"),
    ({"extrapolation_share": (1.0, 1.5)}, "extrapolation_share"),
    ({"extrapolation_share": (1.0, 1.0, 1.0, 1.0)}, "extrapolation_share"),
    ({"second_look": (0.5,)}, "second_look"),
])
def test_contradictory_settings_are_a_slippage_error(options, message):
    with pytest.raises(SlippageError, match=message):
        SlipSettings(**options)
    with pytest.raises(SlippageError, match=message):  # the same through the monitor's keywords
        SlipMonitor([[1, 0]], 2, 100.0, **options)


def test_an_unknown_option_is_a_type_error_naming_it():
    with pytest.raises(TypeError, match="warmup"):
        SlipMonitor([[1, 0]], 2, 100.0, warmup=2.0)
