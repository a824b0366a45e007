"""Self-contained HTML report (placeholder until the plotting report lands)."""

from __future__ import annotations

import html
import json
from typing import Any


def render_html(report: dict[str, Any]) -> str:
    body = html.escape(json.dumps({k: report[k] for k in ("adjustment", "before_after") if k in report}, indent=1,
                                  default=str))
    return f"<!doctype html><html><head><meta charset='utf-8'><title>kinreg report</title></head><body><pre>{body}</pre></body></html>\n"
