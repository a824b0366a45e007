"""One run of ``kinreg process`` as its stages see it: what it read, how it is configured, and
where it runs (the output folder and its stage cache, the executor, the progress, the clock)."""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass

from kinreg.config import KinregConfig
from kinreg.progress import Progress
from kinreg.run.executor import ExecutorContext
from kinreg.run.inputs import ProcessInputs, ReadInputs
from kinreg.run.output_folder import RunCache


class StageClock:
    """Seconds per stage, each from the end of the previous one."""

    def __init__(self) -> None:
        self.timings_s: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        """The time since the last lap, added to ``stage`` (a stage done twice counts twice)."""
        now = time.perf_counter()
        self.timings_s[stage] = self.timings_s.get(stage, 0.0) + now - self._last
        self._last = now


@dataclass(frozen=True, eq=False)
class RunContext:
    """What every stage of one ``kinreg process`` run is handed. ``config`` is the configuration
    as given (the estimation may choose shorter windows: :class:`kinreg.run.estimation.Estimated`);
    ``stack`` holds what the run keeps open until its outputs are written (the executor, the
    runs' spills)."""

    inputs: ProcessInputs
    read: ReadInputs
    config: KinregConfig
    folder: RunCache
    stack: contextlib.ExitStack
    progress: Progress
    executor: ExecutorContext
    clock: StageClock
