"""Per-track plots as small SVG files, drawn directly (no plotting library: a track plot is two
polylines on integer layer ticks, and the report draws twenty of them).

Top panel: area [mm^2]; bottom: height = signed max deviation [mm] with its zero line.
"""

from __future__ import annotations

from html import escape
from pathlib import Path

import numpy as np

from dm2.core.tolerances import ROUNDING_SLACK

W, H = 460, 300
LEFT, RIGHT, TOP, GAP, BOTTOM = 62, 12, 26, 22, 34


def _ticks(lo: float, hi: float, n: int = 4) -> list[float]:
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / n
    mag = 10 ** np.floor(np.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = np.ceil(lo / step) * step
    return [float(v) for v in np.arange(first, hi + step * ROUNDING_SLACK, step)]


def _panel(x, y, y0: float, h: float, x_lo, x_hi, label: str, colour: str,
           zero: bool) -> list[str]:
    lo, hi = (min(min(y), 0.0), max(max(y), 0.0)) if zero else (0.0, max(max(y), 1e-6))
    pad = 0.08 * (hi - lo or 1.0)
    lo, hi = lo - (pad if zero or lo < 0 else 0), hi + pad

    def px(v):
        return LEFT + (v - x_lo) / (x_hi - x_lo) * (W - LEFT - RIGHT)

    def py(v):
        return y0 + h - (v - lo) / (hi - lo) * h

    out = [f'<rect x="{LEFT}" y="{y0}" width="{W - LEFT - RIGHT}" height="{h}" fill="none" '
           'stroke="#888"/>']
    for t in _ticks(lo, hi):
        out.append(f'<line x1="{LEFT - 4}" x2="{LEFT}" y1="{py(t):.1f}" y2="{py(t):.1f}" '
                   'stroke="#888"/>'
                   f'<text x="{LEFT - 6}" y="{py(t) + 4:.1f}" text-anchor="end">{t:g}</text>')
    if zero and lo < 0 < hi:
        out.append(f'<line x1="{LEFT}" x2="{W - RIGHT}" y1="{py(0):.1f}" y2="{py(0):.1f}" '
                   'stroke="#aaa" stroke-dasharray="3,3"/>')
    pts = " ".join(f"{px(a):.1f},{py(b):.1f}" for a, b in zip(x, y, strict=True))
    out.append(f'<polyline points="{pts}" fill="none" stroke="{colour}" stroke-width="2"/>')
    out += [f'<circle cx="{px(a):.1f}" cy="{py(b):.1f}" r="3" fill="{colour}"/>'
            for a, b in zip(x, y, strict=True)]
    out.append(f'<text x="14" y="{y0 + h / 2:.1f}" transform="rotate(-90 14 {y0 + h / 2:.1f})" '
               f'text-anchor="middle">{escape(label)}</text>')
    return out


def track_svg(track: dict, colour: str = "#b2182b") -> str:
    """SVG text of one report track dict's area and height against layer."""
    layers = [h["layer"] for h in track["history"]]
    x_lo, x_hi = min(layers) - 0.6, max(layers) + 0.6
    ph = (H - TOP - GAP - BOTTOM) / 2
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" '
             f'viewBox="0 0 {W} {H}" font-family="sans-serif" font-size="11">',
             '<rect width="100%" height="100%" fill="white"/>',
             f'<text x="{W / 2}" y="16" text-anchor="middle" font-size="13">Track {track["id"]}: '
             f'{escape(track["kind"].replace("_", " "))} ({escape(str(track.get("trend", "")))})'
             '</text>']
    parts += _panel(layers, [h["area_mm2"] for h in track["history"]], TOP, ph, x_lo, x_hi,
                    "area [mm²]", colour, zero=False)
    parts += _panel(layers, [h["max_deviation_mm"] for h in track["history"]], TOP + ph + GAP,
                    ph, x_lo, x_hi, "max deviation [mm]", colour, zero=True)
    step = max(1, int(np.ceil((x_hi - x_lo) / 10)))
    base = TOP + 2 * ph + GAP
    for lay in range(int(np.ceil(x_lo)), int(np.floor(x_hi)) + 1, step):
        xp = LEFT + (lay - x_lo) / (x_hi - x_lo) * (W - LEFT - RIGHT)
        parts.append(f'<line x1="{xp:.1f}" x2="{xp:.1f}" y1="{base}" y2="{base + 4}" '
                     f'stroke="#888"/><text x="{xp:.1f}" y="{base + 16}" '
                     f'text-anchor="middle">{lay}</text>')
    parts.append(f'<text x="{(LEFT + W - RIGHT) / 2}" y="{H - 4}" text-anchor="middle">layer'
                 '</text></svg>')
    return "".join(parts)


def write_track_svgs(items, colours: dict) -> None:
    """Write ``track_svg`` for each ``(path, track)``."""
    for path, track in items:
        Path(path).write_text(track_svg(track, colours.get(track["kind"], "#333")),
                              encoding="utf-8")
