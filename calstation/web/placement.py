"""Where a fixture goes: an SVG top view of the platter drawn from the recipe's geometry.

Seen from above (looking down −X_P onto the platter), with the lidar's side at the bottom: the
L-target's base runs from A (toward the lidar, −Y_P) to the wall at B (DESIGN §3), so the lidar
looks from −Y_P and the scan plane crosses the platter along the Y_P axis (z_P ≈ 0). Screen
coordinates: right = −Z_P, up = +Y_P, which keeps the view right-handed from above. Fixture
outlines are the recipe's: offset (y, z) in metres, yaw about +X_P (DESIGN §3, the simulator
places meshes the same way), the L-target's tall end at z = −width/2.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from html import escape
from typing import TYPE_CHECKING, TypedDict

from calstation import display
from calstation.recipes import frustum_outline

if TYPE_CHECKING:
    from calstation.recipes import FixtureGeometry

SIZE = 360
"""Width and height of the picture (px)."""

MARGIN = 34


class Outline(TypedDict):
    """One outline of a fixture in P (y, z metres), its role and its legend's words."""

    points: list[tuple[float, float]]
    role: str
    label: str


def _place(points: list[tuple[float, float]], offset: tuple[float, float] | None, yaw_deg: float
           ) -> list[tuple[float, float]]:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    oy, oz = (float(offset[0]), float(offset[1])) if offset is not None else (0.0, 0.0)
    return [(c * y - s * z + oy, s * y + c * z + oz) for y, z in points]


def _rect(y0: float, y1: float, z0: float, z1: float) -> list[tuple[float, float]]:
    return [(y0, z0), (y1, z0), (y1, z1), (y0, z1)]


def fixture_outlines(geom: FixtureGeometry) -> list[Outline]:
    """Outlines of one fixture in P (y, z metres): ``[{"points", "label", "role"}]``."""
    yaw = float(getattr(geom, "yaw_deg", 0.0))
    offset = getattr(geom, "offset", (0.0, 0.0))
    if geom.kind == "l_target":
        w, bl, wt = geom.width, geom.base_length, geom.wall_thickness
        return [
            {"points": _place(_rect(-bl, wt, -w / 2, w / 2), offset, 0.0), "role": "base",
             "label": "base plate (A, toward the lidar)"},
            {"points": _place(_rect(0.0, wt, -w / 2, w / 2), offset, 0.0), "role": "wall",
             "label": "wall (B over the centre)"},
            {"points": _place([(0.0, -w / 2)], offset, 0.0), "role": "mark",
             "label": f"tall end {geom.h_tall * 1000:.0f} mm"},
            {"points": _place([(0.0, w / 2)], offset, 0.0), "role": "mark",
             "label": f"short end {geom.h_short * 1000:.0f} mm"},
        ]
    if geom.kind == "frustum":
        poly = frustum_outline(geom)
        return [
            {"points": _place(poly, offset, yaw), "role": "body",
             "label": f"spin target (height {geom.height * 1000:.0f} mm)"},
            {"points": _place([poly[0]], offset, yaw), "role": "mark", "label": "notch"},
        ]
    if geom.kind == "cube":
        h = geom.edge / 2
        return [{"points": _place(_rect(-h, h, -h, h), offset, yaw), "role": "body",
                 "label": f"cube {geom.edge * 1000:.0f} mm, yaw {yaw:g}°"}]
    if geom.kind == "pyramid":
        h = geom.base / 2
        return [{"points": _place(_rect(-h, h, -h, h), offset, yaw), "role": "body",
                 "label": "pyramid"}]
    if geom.kind == "prism":
        return [{"points": _place(_rect(-geom.edge / 2, geom.edge / 2, -geom.depth / 2,
                                        geom.depth / 2), offset, yaw),
                 "role": "body", "label": "prism"}]
    # a mesh: only its placement is known
    return [{"points": _place([(0.0, 0.0)], offset, yaw), "role": "mark",
             "label": f"mesh {getattr(geom, 'mesh', '')}"}]


LEGEND_LINE = 17
"""Height of one line of the legend under the platter (px)."""


def _offset_dimension(geom: FixtureGeometry, xy: Callable[[float, float], tuple[float, float]]
                      ) -> tuple[list[str], str | None]:
    """The fixture's offset from the axis drawn as a dimension line (centre to the fixture's
    centre, arrowheads, its length), and the legend's sentence for it; nothing when centred."""
    offset = getattr(geom, "offset", None)
    if offset is None:
        return [], None
    oy, oz = float(offset[0]), float(offset[1])
    distance = math.hypot(oy, oz)
    if distance < 1e-4:
        return [], "centred on the axis"
    (x0, y0), (x1, y1) = xy(0.0, 0.0), xy(oy, oz)
    mid_x, mid_y = (x0 + x1) / 2, (y0 + y1) / 2
    # the length written beside the line's middle, on the side away from the scan line
    nx, ny = (y1 - y0), -(x1 - x0)
    norm = math.hypot(nx, ny) or 1.0
    side = 1.0 if nx >= 0 else -1.0  # to the right of the line, or left when it leans so
    tx, ty = mid_x + side * nx / norm * 8, mid_y + side * ny / norm * 8
    anchor = "start" if side * nx / norm > 0.3 else "end" if side * nx / norm < -0.3 else (
        "middle")
    text = display.number("distance", distance)
    parts = [
        f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" stroke="#1b1f24" '
        'stroke-width="1.2" marker-start="url(#arrow)" marker-end="url(#arrow)" '
        'class="offset-dimension"/>',
        f'<path d="M{x1 - 5:.1f},{y1:.1f}h10M{x1:.1f},{y1 - 5:.1f}v10" stroke="#1b1f24" '
        'stroke-width="1.5"/>',
        f'<text x="{tx:.1f}" y="{ty + 4:.1f}" font-size="12" font-weight="700" '
        f'text-anchor="{anchor}" fill="#1b1f24" paint-order="stroke" stroke="#fff" '
        f'stroke-width="3" class="offset-label">{text}</text>',
    ]
    yaw = float(getattr(geom, "yaw_deg", 0.0) or 0.0)
    return parts, (f"centre (+) {text} from the axis (recipe offset y "
                   f"{display.number('distance', oy, signed=True)}, z "
                   f"{display.number('distance', oz, signed=True)})"
                   + (f", turned {yaw:g}°" if yaw else ""))


LEGEND_CHARACTERS = 50
"""Characters of a legend line at most (12 px text across the drawing's width): longer
sentences wrap between words rather than run out of the picture."""


def _wrapped(line: str) -> list[str]:
    """``line`` in pieces of at most :data:`LEGEND_CHARACTERS`, cut between words (the
    continuations indented)."""
    out: list[str] = []
    for word in line.split(" "):
        if out and len(out[-1]) + 1 + len(word) <= LEGEND_CHARACTERS:
            out[-1] += " " + word
        else:
            out.append(("    " if out else "") + word)
    return out


def placement_svg(platter_radius: float, geom: FixtureGeometry, title: str) -> str:
    """The top view (SVG text) of ``geom`` on a platter of ``platter_radius`` metres, its offset
    from the axis dimensioned; every label sits in a numbered legend under the platter, so that
    none covers the drawing or another label."""
    scale = (SIZE / 2 - MARGIN) / platter_radius
    cx = cy = SIZE / 2

    def xy(y: float, z: float) -> tuple[float, float]:
        return cx - z * scale, cy - y * scale

    outlines = fixture_outlines(geom)
    dimension, offset_note = _offset_dimension(geom, xy)
    legend = [escape(title),
              f"top view, platter ⌀ {display.number('distance', 2 * platter_radius)}",
              "dashed red: the scan line"]
    colours = {"base": "#b6e3ff", "wall": "#0969da", "body": "#fff8c5"}
    drawing: list[str] = []
    for number, outline in enumerate(outlines, start=1):
        pts = [xy(y, z) for y, z in outline["points"]]
        label = escape(outline["label"])
        legend.append(f"{number}  {label}")
        if outline["role"] == "mark" or len(pts) == 1:
            x, y = pts[0]
            dx = 7 if x >= cx else -7  # the number away from the centre
            drawing.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="4" fill="#8250df"/>'
                           f'<text x="{x + dx:.1f}" y="{y - 6:.1f}" font-size="12" '
                           f'font-weight="700" text-anchor="{"start" if dx > 0 else "end"}" '
                           f'fill="#8250df" data-label="{label}">{number}</text>')
            continue
        poly = " ".join(f"{x:.1f},{y:.1f}" for x, y in pts)
        drawing.append(f'<polygon points="{poly}" fill="{colours[outline["role"]]}" '
                       f'stroke="#1b1f24" stroke-width="1.5" fill-opacity="0.85">'
                       f"<title>{label}</title></polygon>")
        # the number between the outline's centre and its corner farthest from the axis, clear
        # of the offset's dimension
        far = max(pts, key=lambda p: math.hypot(p[0] - cx, p[1] - cy))
        x = (sum(p[0] for p in pts) / len(pts) + far[0]) / 2
        y = (sum(p[1] for p in pts) / len(pts) + far[1]) / 2
        drawing.append(f'<text x="{x:.1f}" y="{y + 4:.1f}" font-size="11" text-anchor="middle" '
                       f'fill="#1b1f24" data-label="{label}">{number}</text>')
    if offset_note:
        legend.append(escape(offset_note))
    legend = [part for line in legend for part in _wrapped(line)]
    height = SIZE + LEGEND_LINE * len(legend) + 6
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {SIZE} {height}" '
        f'class="placement" role="img" aria-label="{escape(title)}">',
        f"<title>{escape(title)}</title>",
        '<defs><marker id="arrow" viewBox="0 0 10 10" refX="9" refY="5" markerWidth="7" '
        'markerHeight="7" orient="auto-start-reverse"><path d="M0,0L10,5L0,10z" '
        'fill="#1b1f24"/></marker></defs>',
        f'<circle cx="{cx}" cy="{cy}" r="{platter_radius * scale:.1f}" fill="#eef1f4" '
        'stroke="#57606a" stroke-width="2"/>',
        # the scan plane crosses the platter along Y_P
        f'<line x1="{cx}" y1="{MARGIN - 20}" x2="{cx}" y2="{SIZE - MARGIN + 12}" '
        'stroke="#cf222e" stroke-width="1.5" stroke-dasharray="6 4"/>',
        f'<circle cx="{cx}" cy="{cy}" r="3" fill="#57606a"/>',
        f'<polygon points="{cx - 10},{SIZE - 4} {cx + 10},{SIZE - 4} {cx},{SIZE - 20}" '
        'fill="#cf222e"/>',
        f'<text x="{cx + 14}" y="{SIZE - 6}" font-size="12" fill="#cf222e">lidar</text>',
        *drawing, *dimension,
    ]
    for i, line in enumerate(legend):
        weight = ' font-weight="700"' if i == 0 else ""
        parts.append(f'<text x="6" y="{SIZE + 14 + i * LEGEND_LINE}" font-size="12"{weight} '
                     f'fill="#1b1f24" class="legend">{line}</text>')
    parts.append("</svg>")
    return "".join(parts)
