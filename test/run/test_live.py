"""What a live run's monitor decides from the messages it sees."""

from __future__ import annotations

from csam_ros.run.live import MarkersAfterJoined


def test_only_markers_after_the_latest_joined_map_are_its_markers() -> None:
    markers = MarkersAfterJoined()
    markers.on_markers(object())  # latched, of an earlier solve
    markers.on_joined()
    assert not markers.came()
    markers.on_markers(object())
    assert markers.came()
    markers.on_joined()  # a newer joined map: its markers have not come yet
    assert not markers.came()
