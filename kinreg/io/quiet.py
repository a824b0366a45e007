"""Library calls that speak in one line naming the file.

laspy, lazrs, libE57Format and numpy report problems their own way: warnings (numpy's
``RuntimeWarning: invalid value``), log records (laspy logs lazrs' ``IoError`` at ERROR level
before raising it) and Rust panics (``pyo3_runtime.PanicException``, a ``BaseException`` that
``except Exception`` does not catch). Inside :func:`library_calls` a warning becomes one log
record naming the file, and a panic becomes :class:`~kinreg.errors.CloudError` naming the file.
laspy's own log records are the command line's to silence (``kinreg_cli``).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from kinreg.errors import CloudError

log = logging.getLogger(__name__)


def _is_panic(e: BaseException) -> bool:
    return type(e).__name__ == "PanicException"


@contextmanager
def library_calls(path: str | Path, error: type[CloudError] = CloudError) -> Iterator[None]:
    """Run library calls on the file at ``path``: their warnings become one log line each
    (``path: category: message``), a Rust panic becomes ``error`` naming the file."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield
        except BaseException as e:
            if _is_panic(e):
                text = str(e).strip().splitlines()
                raise error(f"the decoder failed: {text[0] if text else 'panic'}", path) from None
            raise
        finally:
            for w in caught:
                log.warning("%s: %s: %s", path, w.category.__name__, str(w.message).splitlines()[0])
