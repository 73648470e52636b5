"""Fuzz test of the smoother's boundary: any sensor message after good data.

Hypothesis draws odometry (twist, covariance and integrated pose, each known or not), features
and rendezvous messages (own and a peer's) with any floats (nan, inf, huge, tiny, negative),
any stamps, empty and long observation lists, unknown labels and robots, and hands them to an
in-process smoother through its own subscription callbacks after a run of good data. No
exception may reach the callbacks' guard (``callback_error`` stays 0: one caught there is a bug
found), no local map update may fail, the node still answers ``~/flush``, and the map of the
good data is unchanged.

Runs ``CSAM_FUZZ_EXAMPLES`` examples (default 15, a few seconds); a longer run, e.g.
``CSAM_FUZZ_EXAMPLES=500 .venv/bin/python -m pytest -q -p no:cacheprovider
test/nodes/test_smoother_fuzz.py``.
"""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
from builtin_interfaces.msg import Time
from csam_msgs.msg import (
    FeatureObservation,
    FeatureObservations,
    RendezvousObservation,
    RendezvousObservations,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from nodes.test_smoother import (
    GOOD_SECONDS,
    _good_messages,
    assert_good_map_unchanged,
    deliver,
    fed_smoother,
    flushed_map,
)

from csam_ros.core.exchange.validation import CALLBACK_ERROR

EXAMPLES = int(os.environ.get("CSAM_FUZZ_EXAMPLES", "15"))
MAX_OBSERVATIONS = 6  # the node's bound, so that drawn lists also exceed it

plausible = st.floats(0.005, 2.0)  # within every bound: such values are accepted
floats = st.one_of(
    plausible,
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e-10, 1e8, 1e300, -1e300]),
    st.floats(-10.0, 10.0),
)
near = int(GOOD_SECONDS)
stamps = st.builds(
    Time,
    sec=st.one_of(
        st.integers(near, near + 2), st.integers(near - 3, near), st.integers(-(2**31), 2**31 - 1)
    ),
    nanosec=st.one_of(st.integers(0, 999_999_999), st.integers(0, 2**32 - 1)),
)


@st.composite
def odometry(draw) -> tuple[str, Odometry]:
    msg = Odometry()
    msg.header.stamp = draw(stamps)
    values = plausible if draw(st.booleans()) else floats  # whole messages accepted too
    t = msg.twist.twist
    t.linear.x, t.linear.y, t.angular.z = draw(values), draw(values), draw(values)
    covariance = np.zeros(36)
    covariance[[0, 7, 35]] = [draw(values), draw(values), draw(values)]
    if draw(st.booleans()):  # as drivers send it: unknown (-1 first) or all zero
        covariance[0] = draw(st.sampled_from([-1.0, 0.0]))
    msg.twist.covariance = covariance
    # the integrated pose, marked unknown or not, its orientation a rotation or any numbers
    pose = msg.pose.pose
    pose.position.x, pose.position.y = draw(values), draw(values)
    yaw = draw(st.floats(-4.0, 4.0))
    orientation = (
        (np.sin(yaw / 2), np.cos(yaw / 2)) if draw(st.booleans()) else (draw(floats), draw(floats))
    )
    pose.orientation.z, pose.orientation.w = (float(v) for v in orientation)
    msg.pose.covariance[0] = draw(st.sampled_from([0.0, -1.0]))
    return "/robot1/odom", msg


def _measured(draw) -> dict[str, float]:
    values = plausible if draw(st.booleans()) else floats
    names = ("range", "bearing", "sigma_range", "sigma_bearing")
    return {name: draw(values) for name in names}


@st.composite
def features(draw) -> tuple[str, FeatureObservations]:
    msg = FeatureObservations()
    msg.header.stamp = draw(stamps)
    n = draw(st.integers(0, MAX_OBSERVATIONS + 2))
    labels = draw(st.lists(st.integers(-(2**63), 2**63 - 1), min_size=n, max_size=n))
    msg.observations = [FeatureObservation(label=k, **_measured(draw)) for k in labels]
    return "/robot1/features", msg


@st.composite
def rendezvous(draw) -> tuple[str, RendezvousObservations]:
    msg = RendezvousObservations()
    msg.header.stamp = draw(stamps)
    names = st.one_of(st.sampled_from(["robot1", "robot2", "robot9", ""]), st.text(max_size=4))
    observed = draw(st.lists(names, max_size=MAX_OBSERVATIONS + 2))
    msg.observations = [
        RendezvousObservation(observed_robot=q, **_measured(draw)) for q in observed
    ]
    topic = draw(st.sampled_from(["/robot1/rendezvous", "/robot2/rendezvous"]))
    return topic, msg


def _fresh_labels(msg: FeatureObservations, taken: set[int]) -> None:
    """Labels seen nowhere else, so that accepted fuzz features add new, unconnected features
    and cannot, legitimately, move the good map."""
    for o in msg.observations:
        while o.label in taken:
            o.label = (o.label + 7919) % (2**62)
        taken.add(o.label)


def test_no_message_escapes_the_smoothers_boundary(ros_context) -> None:
    good_messages = _good_messages()
    with fed_smoother(ros_context, good_messages, max_observations=MAX_OBSERVATIONS) as fed:
        good = fed[1]
    good_labels = set(good[2])
    ran: list[int] = []
    seen: Counter[str] = Counter()  # drop reasons, and extra poses, over all examples

    @settings(
        max_examples=EXAMPLES,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )
    @given(st.lists(st.one_of(odometry(), features(), rendezvous()), max_size=12))
    def check(messages) -> None:
        ran.append(1)
        with fed_smoother(ros_context, good_messages, max_observations=MAX_OBSERVATIONS) as fed:
            node = fed[0]
            taken = set(good_labels)
            for topic, msg in messages:
                if isinstance(msg, FeatureObservations):
                    _fresh_labels(msg, taken)
                deliver(node, topic, msg)
            assert node.drops.counts[CALLBACK_ERROR] == 0
            flushed_map(node)  # answers (as ~/flush does): success and the map's stamp
            assert node.errors == 0, "a local map update failed"
            assert_good_map_unchanged(node, good)
            seen.update(node.drops.counts)
            seen["(new poses)"] += len(node.map.stamps) - len(good[0])

    check()
    print(f"{len(ran)} examples; {dict(sorted(seen.items()))}")
