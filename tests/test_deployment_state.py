"""npp-deploy's state without ROS: what each event does to the counters, the last event and the status
/diagnostics publishes (npp_ros.deployment.state)."""

from __future__ import annotations

import pytest

from npp_ros.deployment.state import DeploymentState, Level, StopReason


def active() -> DeploymentState:
    state = DeploymentState()
    state.configured("ab" * 32, "the robot_model_fingerprint parameter")
    state.became("inactive")
    state.activated()
    state.became("active")
    return state


def test_a_fresh_node_is_unconfigured_and_counts_nothing() -> None:
    state = DeploymentState()
    status = state.status({})
    assert (status.doing, status.level) == ("unconfigured: not commanding", Level.OK)
    assert state.values() == {
        "answered": 0, "refused states": 0, "overtaken states": 0, "repeated stamps": 0, "clamped entries": 0,
        "outside coverage": 0, "watchdog expiries": 0,
    }  # fmt: skip


def test_a_refused_configure_is_an_error_until_a_configure_passes() -> None:
    state = DeploymentState()
    assert state.refuse("configure", "no run") == "configure refused: no run"
    status = state.status({"x": 1})
    assert (status.doing, status.level, dict(status.values)) == ("configure refused: no run", Level.ERROR, {"x": 1})
    assert state.values()["last event"] == "configure refused: no run"
    assert state.values()["last event at"].endswith(" UTC")  # type: ignore[union-attr]
    state.configured("f" * 64, "here")
    assert state.status({}).level == Level.OK and state.fingerprint == "f" * 64


def test_answers_refusals_and_the_watchdog_are_counted_and_named() -> None:
    state = active()
    assert state.status({}, now=0.0).doing == "active: waiting for the robot's first joint state"
    state.arrived(10.0)
    state.answered(0.0002, 10.0, resumed=False)
    state.arrived(10.03)
    state.repeated_stamp()
    state.arrived(10.06)
    reason = state.state_refused("a non-finite value", 10.06)
    assert reason == "joint state refused: a non-finite value"
    refused = state.status({}, now=10.5)
    assert (refused.level, refused.error) == (Level.WARN, reason)
    assert refused.doing == "active: commanding the robot; some joint states refused"
    assert state.status({}, now=11.2).doing == "active: commanding the robot"  # a second later: OK again
    stale = state.watchdog_expired(0.15, 0.1, "safe command [0.0] sent")
    assert stale.startswith("no new joint state for 150 ms; states arrived but none was usable: 1 refused (the last: ")
    assert stale.endswith(
        "(state_timeout 100 ms): safe command [0.0] sent; no commanding until usable states flow again"
    )
    expired = state.status({}, watchdog_expired=True)
    assert (expired.level, expired.error) == (Level.WARN, stale)
    assert expired.doing.startswith("active, joint states unusable: safe command sent")
    state.answered(0.0001, 11.0, resumed=True)
    assert state.stale == "" and not state.since_fresh.any()
    values = state.values()
    assert (values["answered"], values["refused states"], values["repeated stamps"], values["watchdog expiries"]) == (
        2,
        1,
        1,
        1,
    )
    assert values["state periods measured"] == 2 and values["state period p50 / p99 / max (ms)"].startswith("30.00")  # type: ignore[union-attr]


def test_a_stop_by_the_node_itself_is_a_warning_while_inactive() -> None:
    state = active()
    state.outside_coverage("state [9.0] is far")
    state.stop_requested(StopReason.OUTSIDE_COVERAGE)
    why = state.deactivating()
    assert why is StopReason.OUTSIDE_COVERAGE and state.deactivating() is StopReason.DEACTIVATED  # taken once
    assert state.stop_commanding() and not state.stop_commanding()
    state.stopped(why, "safe command [0.0] sent")
    state.became("inactive")
    status = state.status({})
    assert status.level == Level.WARN and status.doing.startswith(
        "inactive: not commanding (stopped outside the certificate's coverage (stop_outside_coverage) at "
    )
    assert state.counters.outside_coverage == 1
    assert state.values()["last event"] == "outside the certificate's coverage: state [9.0] is far"
    state.activated()  # a new activation forgets why it stopped, not what it counted
    assert state.stopped_for is None and state.counters.outside_coverage == 1


def test_a_model_mismatch_warns_while_commanding_and_an_operator_stop_does_not() -> None:
    state = active()
    state.answered(0.0001, 1.0, resumed=False)
    mismatch = state.status({}, model_mismatch="3 of the last 5 transitions exceed", now=5.0)
    assert (mismatch.level, mismatch.error) == (Level.WARN, "3 of the last 5 transitions exceed")
    assert state.status({}, overridden=True, now=5.0).level == Level.WARN  # the gate overridden: WARN while active
    state.stop_requested(StopReason.STOP_REQUESTED)
    state.stop_commanding()
    state.stopped(state.deactivating(), "safe command [0.0] sent")
    state.became("inactive")
    assert state.status({}).level == Level.OK
    assert state.status({}).doing.startswith("inactive: not commanding (stop requested at ")
    state.stopped(StopReason.MODEL_MISMATCH, "safe command [0.0] sent")
    assert state.status({}).level == Level.WARN


def test_a_model_mismatch_stays_a_warning_until_the_operator_clears_it() -> None:
    """The monitor's finding is latched: a robot found outside the set is the same robot when its transitions look
    fine a while later, and after a stop; only the operator (or a cleanup) clears it."""
    state = active()
    state.answered(0.0001, 1.0, resumed=False)
    assert state.mismatch_found("gear x0.6: 12 of the last 20 transitions exceed")
    assert not state.mismatch_found("a later finding")  # the first is kept
    latched = state.status({}, model_mismatch=state.model_mismatch, now=5.0)
    assert (latched.level, latched.error) == (Level.WARN, "gear x0.6: 12 of the last 20 transitions exceed")
    state.stopped(StopReason.MODEL_MISMATCH, "safe command [0.0] sent")
    state.became("inactive")
    state.activated()  # activated again: still the robot that was found outside
    assert state.status({}, model_mismatch=state.model_mismatch, now=6.0).level == Level.WARN
    assert state.mismatch_cleared() == "gear x0.6: 12 of the last 20 transitions exceed"
    assert state.values()["last event"] == "the operator cleared the model monitor's finding"
    assert state.status({}, model_mismatch=state.model_mismatch, now=7.0).level == Level.OK
    assert state.mismatch_cleared() == ""
    state.mismatch_found("found again")
    state.cleaned_up()
    assert state.model_mismatch == ""


def inactive_after(why: StopReason) -> DeploymentState:
    state = active()
    state.stop_requested(why)
    state.stop_commanding()
    state.stopped(state.deactivating(), "safe command [0.0] sent")
    state.became("inactive")
    return state


def test_the_level_of_a_stop_follows_from_its_reasons_kind_not_its_words() -> None:
    """Inactive after a stop: WARN exactly for a reason the node stopped for by itself (a finding of its own), OK for
    one the operator or the process asked for. The words are only what /diagnostics shows: a reason given in words
    alone, even a by-itself reason's own, is refused where it comes in, so no text decides a level."""
    by_itself = {StopReason.OUTSIDE_COVERAGE, StopReason.MODEL_CHANGED, StopReason.MODEL_MISMATCH}
    assert {why for why in StopReason if why.by_itself} == by_itself
    for why in StopReason:
        status = inactive_after(why).status({})
        assert status.level == (Level.WARN if why in by_itself else Level.OK), why
        assert status.doing.startswith(f"inactive: not commanding ({why.words} at "), status.doing
    state = active()
    with pytest.raises(TypeError, match="a stop's reason is a StopReason"):
        state.stop_requested(StopReason.MODEL_MISMATCH.words)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="a stop's reason is a StopReason"):
        state.stopped(StopReason.MODEL_MISMATCH.words, "safe command [0.0] sent")  # type: ignore[arg-type]
    assert state.commanding and state.stopped_for is None and state.stopping_for is None


def test_the_words_of_each_stop_are_the_ones_diagnostics_has_always_shown() -> None:
    """Operators and npp-deploy-ctl read these: they stay as they were when the reasons were free text."""
    assert {why.name: why.words for why in StopReason} == {
        "DEACTIVATED": "deactivated",
        "STOP_REQUESTED": "stop requested",
        "OUTSIDE_COVERAGE": "stopped outside the certificate's coverage (stop_outside_coverage)",
        "MODEL_CHANGED": "the robot's model changed",
        "MODEL_MISMATCH": "the robot's transitions left the certified set of robots (on_model_mismatch stop)",
        "SHUTDOWN": "shutting down",
        "ERROR": "error",
        "SIGINT": "SIGINT",
        "SIGTERM": "SIGTERM",
        "EXITING": "exiting",
    }


def test_the_levels_are_diagnostic_msgs_own() -> None:
    """/diagnostics publishes the level as it is (npp_ros_graph/runtime/diagnostics.py, DiagnosticStatus)."""
    assert [int(level) for level in Level] == [0, 1, 2]
