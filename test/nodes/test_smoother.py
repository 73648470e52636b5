"""The smoother node's rendezvous thinning: its own and its peers' measurements, as offline."""

from __future__ import annotations

import numpy as np
from rclpy.parameter import Parameter

from csam_ros.core.log import RendezvousLog
from csam_ros.core.robust import select_rendezvous, thin_rendezvous
from csam_ros.ros.conversions import rendezvous_message, stamp_to_ns

ROBOTS = ["robot1", "robot2", "robot3"]


def _log(observer: str, rng: np.random.Generator, n: int) -> RendezvousLog:
    stamps = np.sort(rng.choice(np.arange(0.0, 300.0, 0.25), n, replace=False))
    others = [r for r in ROBOTS if r != observer]
    return RendezvousLog(
        stamps,
        list(rng.choice(others, n)),
        rng.uniform(0.5, 4.0, n),
        rng.uniform(-1.0, 1.0, n),
        np.full(n, 0.05),
        np.full(n, 0.02),
    )


def _messages(robot: str, log: RendezvousLog):
    for i in range(log.stamps.size):
        sl = slice(i, i + 1)
        yield rendezvous_message(
            robot,
            stamp_to_ns(log.stamps[i]),
            log.observed[sl],
            log.ranges[sl],
            log.bearings[sl],
            log.sigma_range[sl],
            log.sigma_bearing[sl],
        )


def test_smoother_keeps_the_offline_thinned_rendezvous(ros_context) -> None:
    from csam_ros.nodes.smoother import Smoother

    rng = np.random.default_rng(7)
    logs = {r: _log(r, rng, 150) for r in ROBOTS}
    logs["robot2"].ranges[5] = -1.0  # a bad peer measurement: its own smoother drops it
    valid = {r: select_rendezvous(log, log.ranges > 0) for r, log in logs.items()}
    expected, _ = thin_rendezvous(valid, 2.0, 6)
    smoother = Smoother(
        context=ros_context,
        namespace="robot1",
        parameter_overrides=[
            Parameter("robots", value=ROBOTS),
            Parameter("rendezvous_min_interval", value=2.0),
            Parameter("rendezvous_max_per_pair", value=6),
        ],
    )
    try:
        for msg in _messages("robot1", logs["robot1"]):
            smoother.on_own_rendezvous(msg)
        for peer in ("robot2", "robot3"):
            for msg in _messages(peer, logs[peer]):
                smoother.on_peer_rendezvous(peer, msg)
        own, stamps = smoother.kept_rendezvous()
        np.testing.assert_allclose(own.stamps, expected["robot1"].stamps, atol=1e-9)
        assert own.observed == expected["robot1"].observed
        of_me = [
            t
            for peer in ("robot2", "robot3")
            for t, o in zip(expected[peer].stamps, expected[peer].observed, strict=True)
            if o == "robot1"
        ]
        np.testing.assert_allclose(
            stamps, np.unique(np.concatenate([own.stamps, of_me])), atol=1e-9
        )
        assert 0 < own.stamps.size <= 12  # two peers, at most 6 each
    finally:
        smoother.destroy_node()
