"""The notes of a result: each kind's text reads back to its kind, the kinds' properties."""

from __future__ import annotations

import numpy as np

from csam_ros.core.joining.notes import NOT_CONVERGED, Note, NoteKind
from csam_ros.core.model import rendezvous
from csam_ros.core.model.log import RendezvousLog

# every kind of note but OTHER, as its constructor writes it
NOTES = [
    Note.no_local_map("robot2", "1 usable odometry sample(s), a map needs two"),
    Note.no_local_map("robot3", "its solve failed (the solution is not finite)"),
    Note.local_map_inconsistent("robot4", "inconsistent local map: 64 of 64 factors", False),
    Note.local_map_inconsistent("robot1", "inconsistent local map: 63 of 64 factors", True),
    Note.features_not_associated("robot4", [410, 414]),
    Note.not_converged_alignment("maximum iterations reached", 1, 14.483),
    Note.not_converged_joint("maximum iterations reached", 1, 1903.1),
    Note.provisional("the local maps placed by the last join, not solved"),
]


def _left_out_rendezvous() -> list[str]:
    """Every note :func:`~csam_ros.core.model.rendezvous.collect` writes."""
    log = RendezvousLog(
        np.array([1.0, 2.0, 2.5, 3.0]),
        ["robot1", "ghost", "robot2", "robot2"],
        *(np.ones(4) for _ in range(4)),
    )
    logs = {"robot1": log, "nobody": log}
    stamps = {"robot1": [1.0, 2.0, 2.5, 3.0], "robot2": [3.0]}
    _, texts = rendezvous.collect(logs, stamps, skip_missing_poses=True)
    assert len(texts) == 4
    return texts


def test_a_notes_kind_reads_back_from_its_text() -> None:
    notes = NOTES + [Note.rendezvous_left_out(text) for text in _left_out_rendezvous()]
    assert {n.kind for n in notes} == set(NoteKind) - {NoteKind.OTHER}
    for note in notes:
        assert Note.of_text(note.text) == note
        assert str(note) == note.text
    assert tuple(n.kind for n in notes if n.not_converged) == NOT_CONVERGED
    assert Note.of_text("the moon was full") == Note(NoteKind.OTHER, "the moon was full")
