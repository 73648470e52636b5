"""A context manager that closes what it holds on exit (a bag writer, a worker, a reservation)."""

from __future__ import annotations

from types import TracebackType
from typing import Self


class Closing:
    """``with thing:`` gives ``thing`` and calls its ``close`` at the end, also on an error."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()
