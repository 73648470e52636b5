"""The notes of a C-SAM result: what C-SAM remarks on a join, each of a kind
(:class:`NoteKind`) with its text, the text ``summary.json`` holds (``notes``).

Each kind's text (but :attr:`NoteKind.OTHER`'s) is written by one constructor of :class:`Note`;
:meth:`Note.of_text` reads the kind back from such a text, so a summary keeps the texts alone.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum


class NoteKind(Enum):
    """What a note of a :class:`~csam_ros.core.joining.result.CsamResult` is about."""

    NO_LOCAL_MAP = "no_local_map"  # a robot left out of the join: it has no local map
    RENDEZVOUS_LEFT_OUT = "rendezvous_left_out"  # measurements with no map or pose to join
    LOCAL_MAP_INCONSISTENT = "local_map_inconsistent"  # a map failed its check (section 6.5)
    FEATURES_NOT_ASSOCIATED = "features_not_associated"  # features that failed the check
    NOT_CONVERGED_ALIGNMENT = "not_converged_alignment"  # Algorithm 1 stopped unconverged
    NOT_CONVERGED_JOINT = "not_converged_joint"  # the joint solve stopped unconverged
    PROVISIONAL = "provisional"  # the last join's placement of newer maps, not solved
    OTHER = "other"  # a text none of the above has (a summary of another version)


NOT_CONVERGED = (NoteKind.NOT_CONVERGED_ALIGNMENT, NoteKind.NOT_CONVERGED_JOINT)

# each kind's text as the constructors of Note write it, in the order they are tried
_TEXT_PATTERNS = (
    (NoteKind.NOT_CONVERGED_ALIGNMENT, re.compile(r"Algorithm 1 not converged: ")),
    (NoteKind.NOT_CONVERGED_JOINT, re.compile(r"joint solve not converged: ")),
    (NoteKind.PROVISIONAL, re.compile(r"provisional: ")),
    (NoteKind.RENDEZVOUS_LEFT_OUT, re.compile(r"\d+ rendezvous measurement\(s\) ")),
    (NoteKind.NO_LOCAL_MAP, re.compile(r"[^:]*: no local map: ")),
    (
        NoteKind.FEATURES_NOT_ASSOCIATED,
        re.compile(r"[^:]*: features \[.*\] not associated: their observations disagree$"),
    ),
    (NoteKind.LOCAL_MAP_INCONSISTENT, re.compile(r"[^:]*: .* \((pending|reference kept)\)$")),
)


@dataclass(frozen=True)
class Note:
    """A remark of C-SAM on its result: its kind and its text (the summary's ``notes``)."""

    kind: NoteKind
    text: str

    def __str__(self) -> str:
        return self.text

    @property
    def not_converged(self) -> bool:
        """Whether the note says that Algorithm 1 or the joint solve stopped unconverged."""
        return self.kind in NOT_CONVERGED

    @classmethod
    def of_text(cls, text: str) -> Note:
        """The note whose text is ``text``, its kind read from the text (:data:`NoteKind.OTHER`
        when no constructor writes such a text)."""
        for kind, pattern in _TEXT_PATTERNS:
            if pattern.match(text):
                return cls(kind, text)
        return cls(NoteKind.OTHER, text)

    @classmethod
    def no_local_map(cls, robot: str, why: str) -> Note:
        """``robot`` is left out of the join: it has no local map, for the reason ``why``."""
        return cls(NoteKind.NO_LOCAL_MAP, f"{robot}: no local map: {why}")

    @classmethod
    def provisional(cls, what: str) -> Note:
        """A result that is ``what``, not a solved join (a provisional joined map)."""
        return cls(NoteKind.PROVISIONAL, f"provisional: {what}")

    @classmethod
    def rendezvous_left_out(cls, text: str) -> Note:
        """Rendezvous measurements left out, as
        :func:`~csam_ros.core.model.rendezvous.collect` describes them."""
        return cls(NoteKind.RENDEZVOUS_LEFT_OUT, text)

    @classmethod
    def local_map_inconsistent(cls, robot: str, reason: str, reference: bool) -> Note:
        """``robot``'s local map failed its check for ``reason``: it stays pending, or, the
        reference, is kept."""
        what = "reference kept" if reference else "pending"
        return cls(NoteKind.LOCAL_MAP_INCONSISTENT, f"{robot}: {reason} ({what})")

    @classmethod
    def features_not_associated(cls, robot: str, labels: Sequence[int]) -> Note:
        """``robot``'s features ``labels`` failed the local-map check: not associated."""
        return cls(
            NoteKind.FEATURES_NOT_ASSOCIATED,
            f"{robot}: features {list(labels)} not associated: their observations disagree",
        )

    @classmethod
    def not_converged_alignment(cls, reason: str, iterations: int, cost: float) -> Note:
        """Algorithm 1 stopped for ``reason`` before it converged."""
        return cls(
            NoteKind.NOT_CONVERGED_ALIGNMENT,
            f"Algorithm 1 not converged: {reason} after {iterations} iterations (cost {cost:.6g})",
        )

    @classmethod
    def not_converged_joint(cls, reason: str, iterations: int, cost: float) -> Note:
        """The joint solve stopped for ``reason`` before it converged."""
        return cls(
            NoteKind.NOT_CONVERGED_JOINT,
            f"joint solve not converged: {reason} after {iterations} iterations (cost {cost:.6g})",
        )
