"""`silo-agent report`: one self-contained file of a scan for audit and commissioning.

HTML (the map embedded as a data: URL, no other file, no script) or PNG (one matplotlib
figure). Both say the figures as `P/volume` published them, the map with walls, piles, cameras
and their footprints, each camera's coverage and drift, the calibration residual per pair, the
piles, and the key values of the config snapshot the scan was taken with. The PNG carries the
published figures as JSON in its `silo-agent:published` text chunk, for tools to check.
"""

from __future__ import annotations

import base64
import html
import io
import json
from typing import Any

from silo_agent.web.archive import ScanView
from silo_agent.web.pictures import MapLayout, legend, map_png

PNG_KEY = "silo-agent:published"
CONFIG_KEYS = (  # (section, key) of the config snapshot a commissioning engineer checks
    ("silo", "id"),
    ("silo", "floor_z"),
    ("silo", "ceiling_z"),
    ("silo", "bulk_density_t_m3"),
    ("silo", "base"),
    ("silo", "region"),
    ("reconstruction", "method"),
    ("reconstruction", "grid_step_m"),
    ("schedule", "interval_s"),
    ("schedule", "cron"),
    ("alarms", "baseline_scan_id"),
)


def _number(value: Any, digits: int, unit: str = "") -> str:
    if value is None:
        return "–"
    return f"{value:.{digits}f}{unit}"


def figures(view: ScanView) -> list[tuple[str, str, str]]:
    """(label, shown, exact) rows: `P/volume`'s figures, then the result's other ones."""
    p = view.published
    s = view.summary
    level = p.get("level") or {}
    rows = [
        ("volume", _number(p["volume_m3"], 3, " m³"), json.dumps(p["volume_m3"])),
        ("mass", _number(p["mass_t"], 3, " t"), json.dumps(p["mass_t"])),
        (
            "level min / mean / max",
            " / ".join(_number(level.get(k), 3) for k in ("min", "mean", "max")) + " m",
            json.dumps(level),
        ),
        ("coverage", _number(p["coverage"] * 100, 1, " %"), json.dumps(p["coverage"])),
        (
            "valid",
            "yes" if p["valid"] else f"NO: {s.get('invalid_reason')}",
            json.dumps(p["valid"]),
        ),
        ("degraded", "yes" if p["degraded"] else "no", json.dumps(p["degraded"])),
        ("captured", p["captured_at"], json.dumps(p["captured_at"])),
        ("scan", p["scan_id"], json.dumps(p["scan_id"])),
    ]
    for key, label, digits, unit, scale in (
        ("fill_ratio", "fill", 1, " %", 100.0),
        ("headspace_m", "headspace", 3, " m", 1.0),
        ("capacity_m3", "capacity", 3, " m³", 1.0),
    ):
        if s.get(key) is not None:
            rows.append((label, _number(s[key] * scale, digits, unit), json.dumps(s[key])))
    rows.append(("method", f"{s.get('method')}, grid {s.get('grid_step_m')} m", ""))
    return rows


def _config_rows(view: ScanView) -> list[tuple[str, str]]:
    rows = []
    for section, key in CONFIG_KEYS:
        value = (view.config.get(section) or {}).get(key)
        if value is not None:
            rows.append((f"{section}.{key}", json.dumps(value)))
    for camera in view.config.get("cameras") or []:
        where = camera.get("view") or camera.get("recording") or ""
        rows.append((f"camera {camera.get('serial')}", f"{camera.get('source')} {where}".strip()))
    return rows


def _residual_rows(view: ScanView) -> list[tuple[str, str]]:
    out = []
    detail = view.summary.get("registration_residual") or {}
    for pair, median in (view.summary.get("registration_residual_m") or {}).items():
        extra = detail.get(pair) or {}
        rest = [
            f"{key.removesuffix('_m')} {value * 1000:.1f} mm"
            if key.endswith("_m") and isinstance(value, float)
            else f"{key} {value}"
            for key, value in extra.items()
            if key != "median_m"
        ]
        median_mm = None if median is None else median * 1000
        out.append((pair, ", ".join([_number(median_mm, 1, " mm"), *rest])))
    return out


def _table(headers: list[str], rows: list[list[str]], table_id: str) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows
    )
    if not rows:
        body = f'<tr><td colspan="{len(headers)}">none</td></tr>'
    return f'<table id="{table_id}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _map(view: ScanView) -> tuple[bytes, MapLayout] | None:
    if view.heightmap is None:
        return None
    return map_png(
        view.heightmap,
        view.floor_z,
        view.region,
        piles=view.summary.get("piles") or [],
        cameras=view.cameras,
    )


def _camera_rows(view: ScanView) -> list[list[str]]:
    failed = {
        f["serial"]: f["error"] for f in (view.summary.get("cameras") or {}).get("failed", [])
    }
    rows = [
        [
            c.serial,
            "ok",
            "(" + ", ".join(f"{v:.2f}" for v in c.position) + ") m",
            str(c.points),
            _number(c.coverage * 100, 1, " %"),
            _number(c.gravity_deg, 2, "°"),
        ]
        for c in view.cameras
    ]
    rows += [[serial, f"failed: {error}", "", "", "", ""] for serial, error in failed.items()]
    return rows


def _pile_rows(view: ScanView) -> list[list[str]]:
    rows = []
    for pile in view.summary.get("piles") or []:
        peak = pile.get("peak") or {}
        rows.append(
            [
                f"#{pile.get('id')}",
                str(pile.get("detector")),
                f"({_number(peak.get('x'), 2)}, {_number(peak.get('y'), 2)})",
                _number(pile.get("peak_height_m"), 3, " m"),
                _number(pile.get("footprint_m2"), 2, " m²"),
                _number(pile.get("volume_m3"), 3, " m³"),
            ]
        )
    return rows


STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #1d1d1d; max-width: 1100px; }
table { border-collapse: collapse; margin: 0.4em 0 1.2em; font-size: 0.92em; }
th, td { text-align: left; padding: 0.2em 0.7em; border-bottom: 1px solid #ddd; }
img { max-width: 100%; image-rendering: pixelated; }
.legend span { display: inline-block; vertical-align: middle; font-size: 0.85em; }
"""


def report_html(view: ScanView) -> str:
    """The report as one HTML document (the picture embedded)."""
    picture = _map(view)
    source = (
        "the result the agent kept with the scan (as published)"
        if view.kept
        else "the scan processed now, as `silo-agent process` does"
    )
    parts = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>silo-agent report {html.escape(view.scan_id)}</title>",
        f"<style>{STYLE}</style></head><body>",
        f"<h1>Scan {html.escape(view.scan_id)}</h1>",
        f"<p>Captured {html.escape(view.captured_at)}; figures from {source}.</p>",
        "<h2>Figures</h2>",
        '<table id="figures"><tbody>',
    ]
    for label, shown, exact in figures(view):
        parts.append(
            f'<tr><th>{html.escape(label)}</th><td data-exact="{html.escape(exact)}">'
            f"{html.escape(shown)}</td></tr>"
        )
    parts.append("</tbody></table><h2>Height map</h2>")
    if picture is not None:
        png, layout = picture
        gradient = ", ".join(legend(layout))
        low, high = layout.scale_m
        parts += [
            f'<img id="map" alt="height map" src="data:image/png;base64,'
            f'{base64.b64encode(png).decode()}">',
            f'<p class="legend"><span>{low:.2f} m</span> <span style="width:160px;'
            f'height:12px;background:linear-gradient(to right, {gradient})"></span> '
            f"<span>{high:.2f} m</span> <span>height above the floor; pale: filled (not "
            "observed); grey: outside; dashed: each camera's footprint; dotted: piles; black: "
            "walls</span></p>",
        ]
    else:
        parts.append("<p>No height map.</p>")
    parts += [
        "<h2>Cameras</h2>",
        _table(
            ["camera", "state", "position", "points", "coverage", "gravity vs extrinsic"],
            _camera_rows(view),
            "cameras",
        ),
        "<h2>Calibration residual per pair</h2>",
        _table(
            ["pair", "median height difference"],
            [list(r) for r in _residual_rows(view)],
            "residuals",
        ),
        "<h2>Piles</h2>",
        _table(
            ["pile", "detector", "peak at", "height", "footprint", "volume"],
            _pile_rows(view),
            "piles",
        ),
        "<h2>Configuration (snapshot taken with the scan)</h2>",
        _table(["key", "value"], [list(r) for r in _config_rows(view)], "config"),
        "</body></html>\n",
    ]
    return "".join(parts)


def report_png(view: ScanView) -> bytes:
    """The report as one PNG: the map on the left, the tables as text on the right."""
    from matplotlib.figure import Figure
    from matplotlib.image import imread

    picture = _map(view)
    fig = Figure(figsize=(14, 8), dpi=100)
    left = fig.add_axes((0.01, 0.02, 0.55, 0.9))
    left.set_axis_off()
    if picture is not None:
        left.imshow(imread(io.BytesIO(picture[0]), format="png"), interpolation="nearest")
    fig.suptitle(f"Scan {view.scan_id}   captured {view.captured_at}", x=0.01, ha="left")
    lines = [f"{label:<24}{shown}" for label, shown, _exact in figures(view)]
    lines += ["", "camera        points     coverage  gravity"]
    lines += [
        f"{c.serial:<14}{c.points:<11}{c.coverage * 100:5.1f} %   {_number(c.gravity_deg, 2, '°')}"
        for c in view.cameras
    ]
    lines += ["", "residual per pair"] + [
        f"  {pair}: {text}" for pair, text in _residual_rows(view)
    ]
    lines += ["", "piles"] + ["  " + "  ".join(row) for row in _pile_rows(view)]
    lines += ["", "config"] + [f"  {key} = {value}"[:70] for key, value in _config_rows(view)]
    fig.text(0.58, 0.92, "\n".join(lines), family="monospace", fontsize=8.5, va="top")
    buffer = io.BytesIO()
    fig.savefig(
        buffer, format="png", metadata={PNG_KEY: json.dumps(view.published, allow_nan=False)}
    )
    return buffer.getvalue()
