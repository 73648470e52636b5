"""Nearest and matching stamps."""

from __future__ import annotations

import numpy as np

from csam_ros.core.model.stamps import matching_stamp, nearest_stamp


def test_nearest_stamp_of_queries_inside_and_outside_the_span() -> None:
    stamps = np.array([1.0, 2.0, 4.0])
    query = np.array([-5.0, 1.2, 1.5, 2.9, 3.1, 9.0])
    np.testing.assert_array_equal(nearest_stamp(stamps, query), [0, 0, 0, 1, 2, 2])
    np.testing.assert_array_equal(nearest_stamp([3.0], [-1.0, 3.0, 7.0]), [0, 0, 0])


def test_matching_stamp_within_the_tolerance_else_minus_one() -> None:
    stamps = np.array([1.0, 2.0, 4.0])
    query = np.array([1.05, 2.2, 3.95, 0.0])
    np.testing.assert_array_equal(matching_stamp(stamps, query, 0.1), [0, -1, 2, -1])
    np.testing.assert_array_equal(matching_stamp(stamps, [2.0, 2.5], 0.0), [1, -1])
    np.testing.assert_array_equal(matching_stamp(np.zeros(0), [1.0, 2.0], 1.0), [-1, -1])
