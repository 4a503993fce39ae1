"""The engine's opt-in clock: where a registration's seconds go, for the speed benchmark."""

from __future__ import annotations

import time

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.clock import clocked, current, timed
from vehicle_pose.render.synth import synthesize

from helpers import perturbed, view


@timed("inner")
def _inner(seconds: float) -> str:
    time.sleep(seconds)
    return "inner"


@timed("outer")
def _outer(seconds: float) -> str:
    time.sleep(seconds)
    return _inner(seconds)


def test_nothing_is_charged_without_a_clock_and_a_nested_call_counts_once():
    assert current() is None
    assert _outer(0.001) == "inner"  # no clock: the calls run, nothing is kept
    with clocked() as clock:
        assert current() is clock
        assert _outer(0.02) == "inner"
        assert _inner(0.01) == "inner"
    assert current() is None
    # The inner call made inside the outer one is the outer one's time, not its own as well.
    assert clock.calls == {"outer": 1, "inner": 1}
    assert clock.seconds["outer"] >= 0.04 and 0.01 <= clock.seconds["inner"] < 0.03


def test_a_registration_on_the_clock_says_where_its_seconds_went(sedan, renderer):
    truth = view(sedan, 50.0, 12.0, width=160, height=120, focal=225.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer, seed=1)
    options = RegistrationOptions.from_flat(max_evaluations=40, fine_evaluations=20, focal_starts=())
    with clocked() as clock:
        result = register(photo, sedan, init_camera=perturbed(truth, 1), renderer=renderer, options=options)
    # Every evaluation renders and scores its frame; the edge term's chamfer and GrabCut run too.
    assert clock.calls["draw"] == clock.calls["read"] >= result.evaluations
    assert clock.calls["loss"] >= result.evaluations and clock.calls["chamfer"] >= result.evaluations
    assert clock.calls["grabcut"] >= 1
    assert all(seconds > 0 for seconds in clock.seconds.values())
    assert sum(clock.seconds.values()) <= result.seconds
    # Off the clock, the same registration charges nothing to the clock it left.
    before = dict(clock.calls)
    register(photo, sedan, init_camera=perturbed(truth, 1), renderer=renderer, options=options)
    assert current() is None and clock.calls == before
