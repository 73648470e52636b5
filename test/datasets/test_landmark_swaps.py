"""Swapped landmarks in a ground truth, found from the measurements."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from noise_models import noise_model

from csam_ros.datasets.landmark_swaps import detect_landmark_swaps, exchange_landmarks


def test_swapped_landmarks_in_the_truth_are_found_from_the_measurements() -> None:
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.datasets.simulation import simulate

    log = simulate(load_scenario("map_joining"), 1)
    assert log.truth is not None
    noise = noise_model((0.01, 0.0, 0.012), (0.1, 0.1, 0.1))
    assert detect_landmark_swaps(log, noise) == []  # the simulator's truth is right
    # the most observed feature of each area, metres apart
    observed = np.concatenate(
        [
            [log.truth.label_to_feature[name][int(k)] for k in robot.features.labels]
            for name, robot in log.robots.items()
        ]
    )
    subjects, counts = np.unique(observed, return_counts=True)
    x = log.truth.feature_positions[np.searchsorted(log.truth.feature_ids, subjects), 0]
    a = int(subjects[x < 0][np.argmax(counts[x < 0])])
    b = int(subjects[x > 0][np.argmax(counts[x > 0])])
    swapped = replace(log, truth=exchange_landmarks(log.truth, a, b))
    (swap,) = detect_landmark_swaps(swapped, noise)
    assert swap.subjects == (min(a, b), max(a, b))
    assert min(swap.gross_before) > 0.5 and max(swap.gross_after) <= 0.1
    assert f"subjects {min(a, b)} and {max(a, b)} exchanged" in swap.line()
