"""The ``kinreg`` command run in this process, as the tests call it."""

from __future__ import annotations

import pytest
from kinreg_cli.main import main


def run_cli(args: list[object], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Exit code (0 for a clean exit), standard output and standard error of ``kinreg ARGS``."""
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in args])
    captured = capsys.readouterr()
    code = info.value.code
    return (code if isinstance(code, int) else 0), captured.out, captured.err
