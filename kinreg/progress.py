"""Progress reporting protocol: stages report, front ends render. No-op by default."""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    """What a stage calls to report progress; the CLI plugs in a progress bar."""

    def start(self, stage: str, total: float | None = None, unit: str = "") -> None:
        """A stage begins; ``total`` in ``unit`` (points, scans, ...) when known."""

    def advance(self, amount: float = 1.0) -> None:
        """``amount`` more units are done."""

    def finish(self) -> None:
        """The current stage is done."""


class NullProgress:
    """Reports nowhere."""

    def start(self, stage: str, total: float | None = None, unit: str = "") -> None:
        pass

    def advance(self, amount: float = 1.0) -> None:
        pass

    def finish(self) -> None:
        pass
