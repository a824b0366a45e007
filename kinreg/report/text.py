"""Numbers and text of the HTML report: plain values from numpy or JSON, formatted, escaped, tagged."""

from __future__ import annotations

import html
import math
from typing import Any

DASH = "\u2013"  # shown for missing or non-finite values


def _plain(value: Any) -> Any:
    """Numpy scalars and arrays to Python, non-finite floats to None (as ``report.json`` has them)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, str | bytes):
        return _plain(value.tolist())  # numpy arrays and scalars (``np.float64(1).tolist()`` is a float)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _get(tree: Any, *keys: str, default: Any = None) -> Any:
    """``tree[k1][k2]...`` or ``default`` where any level is missing or not a dict."""
    for key in keys:
        if not isinstance(tree, dict) or tree.get(key) is None:
            return default
        tree = tree[key]
    return tree


def _number(value: Any) -> float | None:
    """A finite float, or None for anything else (None, NaN, text, bool)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _numbers(values: Any) -> list[float | None]:
    return [_number(v) for v in values] if isinstance(values, list) else []


def _fmt(value: Any, digits: int = 1, unit: str = "") -> str:
    """``12.3 mm`` (thin space before the unit); a dash for missing values.

    >>> _fmt(1.234, 2), _fmt(None), _fmt(float("nan"))
    ('1.23', '–', '–')
    """
    v = _number(value)
    if v is None:
        return DASH
    return f"{v:.{digits}f}" + (f"\u2009{unit}" if unit else "")


def _count(value: Any) -> str:
    """Integers with thin-space thousands: ``2 025 310``."""
    v = _number(value)
    return DASH if v is None else f"{round(v):,}".replace(",", "\u202f")


def _duration(seconds: Any) -> str:
    v = _number(seconds)
    if v is None:
        return DASH
    if v < 60:
        return f"{v:.1f}\u2009s"
    minutes, rest = divmod(round(v), 60)
    return f"{minutes}:{rest:02d}\u2009min"


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _tag(name: str, content: str = "", **attrs: Any) -> str:
    """``<name a="..">content</name>``; attribute names ``class_`` -> ``class``, ``_`` -> ``-``."""
    parts = [name] + [f'{k.rstrip("_").replace("_", "-")}="{_esc(v)}"'
                      for k, v in attrs.items() if v is not None]
    return f"<{' '.join(parts)}>{content}</{name}>"
