"""The name and EPSG code of the input cloud's coordinate reference system, for ``report.json``.

With pyproj installed (optional) the WKT or the GeoTIFF keys are resolved by PROJ; without it the
name and the EPSG code are read from the WKT text itself (its first quoted name and its last
top-level ``AUTHORITY``/``ID``) or from the GeoTIFF keys (projected, else geographic type).
"""

from __future__ import annotations

import re
from typing import Any

from kinreg.io.las import LasCrs

PROJECTED_CS_TYPE, GEOGRAPHIC_TYPE, VERTICAL_CS_TYPE = 3072, 2048, 4096  # GeoTIFF key ids
USER_DEFINED = 32767


def describe_crs(crs: LasCrs) -> dict[str, Any]:
    """``{"source", "name", "epsg", "wkt", "resolved_by"}``; ``{}`` when the file declares no CRS.

    >>> describe_crs(LasCrs(wkt='PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84"],AUTHORITY["EPSG","32632"]]'))["epsg"]
    32632
    """
    if crs.wkt:
        entry: dict[str, Any] = {"source": "WKT (E)VLR", "wkt": crs.wkt, **_from_wkt_text(crs.wkt)}
    elif crs.geo_keys:
        code = next((crs.geo_keys[k] for k in (PROJECTED_CS_TYPE, GEOGRAPHIC_TYPE)
                     if 0 < crs.geo_keys.get(k, 0) < USER_DEFINED), None)
        entry = {"source": "GeoTIFF keys", "wkt": "", "name": f"EPSG:{code}" if code else "user-defined",
                 "epsg": code, "geo_keys": {str(k): v for k, v in sorted(crs.geo_keys.items())}}
        vertical = crs.geo_keys.get(VERTICAL_CS_TYPE)
        if vertical and vertical < USER_DEFINED:
            entry["vertical_epsg"] = vertical
    else:
        return {}
    entry["resolved_by"] = "text"
    try:
        import pyproj
    except ImportError:
        return entry
    try:
        resolved = pyproj.CRS.from_wkt(crs.wkt) if crs.wkt else pyproj.CRS.from_epsg(int(entry["epsg"]))
    except (pyproj.exceptions.CRSError, TypeError, ValueError):
        return entry
    entry["name"] = resolved.name
    entry["epsg"] = resolved.to_epsg() or entry.get("epsg")
    entry["resolved_by"] = f"pyproj {pyproj.__version__}"
    return entry


def _from_wkt_text(wkt: str) -> dict[str, Any]:
    """Name and EPSG code from WKT 1 or 2 text, without PROJ."""
    name = re.match(r'\s*\w+\s*\[\s*"([^"]*)"', wkt)
    depth, top_level = 0, []
    for match in re.finditer(r'[\[\]]|(?:AUTHORITY|ID)\[\s*"EPSG"\s*,\s*"?(\d+)"?', wkt):
        token = match.group(0)
        if token == "[":
            depth += 1
        elif token == "]":
            depth -= 1
        else:  # the key word and its opening bracket
            if depth == 1:
                top_level.append(int(match.group(1)))
            depth += 1
    return {"name": name.group(1) if name else "", "epsg": top_level[-1] if top_level else None}
