"""Pictures and GeoJSON of segment maps and paths — the only plotting module.

A picture is a list of layers: segment sets (walls, mapped elements) and paths (trajectories).
SVG is written by hand (exact, small, diffable); PNG goes through matplotlib's Agg backend,
imported lazily so nothing else pays for it.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Distinct colours for robots (colour-blind friendly, Okabe–Ito).
ROBOT_COLOURS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442")
SVG_PX_PER_M = 20.0
SVG_MARGIN_M = 1.0


@dataclass
class SegmentLayer:
    segments: np.ndarray  # (N,2,2) metres
    colour: str = "#222222"
    width_m: float = 0.06
    label: str = ""
    opacity: float = 1.0


@dataclass
class PathLayer:
    xy: np.ndarray  # (T,2) metres
    colour: str = "#0072B2"
    width_m: float = 0.04
    label: str = ""
    start_marker: bool = True


@dataclass
class Picture:
    segments: list[SegmentLayer] = field(default_factory=list)
    paths: list[PathLayer] = field(default_factory=list)
    title: str = ""

    def bounds(self) -> np.ndarray:
        pts = [s.segments.reshape(-1, 2) for s in self.segments if len(s.segments)]
        pts += [p.xy.reshape(-1, 2) for p in self.paths if len(p.xy)]
        if not pts:
            return np.array([0.0, 0.0, 1.0, 1.0])
        allp = np.concatenate(pts)
        allp = allp[np.all(np.isfinite(allp), axis=1)]
        lo, hi = allp.min(axis=0) - SVG_MARGIN_M, allp.max(axis=0) + SVG_MARGIN_M
        return np.array([lo[0], lo[1], hi[0], hi[1]])


def robot_colour(index: int) -> str:
    return ROBOT_COLOURS[index % len(ROBOT_COLOURS)]


def save_svg(path: str | Path, pic: Picture, px_per_m: float = SVG_PX_PER_M) -> None:
    x0, y0, x1, y1 = pic.bounds()
    w, h = (x1 - x0) * px_per_m, (y1 - y0) * px_per_m
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.0f}" height="{h:.0f}" '
        f'viewBox="{x0:.3f} {-y1:.3f} {x1 - x0:.3f} {y1 - y0:.3f}">',
        f'<rect x="{x0:.3f}" y="{-y1:.3f}" width="{x1 - x0:.3f}" height="{y1 - y0:.3f}" fill="white"/>',
    ]
    if pic.title:
        out.append(f"<title>{_xml(pic.title)}</title>")
    for layer in pic.segments:
        out.append(
            f'<g stroke="{layer.colour}" stroke-width="{layer.width_m}" stroke-linecap="round" '
            f'opacity="{layer.opacity}"><title>{_xml(layer.label)}</title>'
        )
        for (ax, ay), (bx, by) in np.asarray(layer.segments).reshape(-1, 2, 2):
            out.append(f'<line x1="{ax:.3f}" y1="{-ay:.3f}" x2="{bx:.3f}" y2="{-by:.3f}"/>')
        out.append("</g>")
    for p in pic.paths:
        xy = np.asarray(p.xy).reshape(-1, 2)
        if len(xy) == 0:
            continue
        pts = " ".join(f"{x:.3f},{-y:.3f}" for x, y in xy)
        out.append(
            f'<polyline fill="none" stroke="{p.colour}" stroke-width="{p.width_m}" '
            f'points="{pts}"><title>{_xml(p.label)}</title></polyline>'
        )
        if p.start_marker:
            out.append(f'<circle cx="{xy[0, 0]:.3f}" cy="{-xy[0, 1]:.3f}" r="0.25" fill="{p.colour}"/>')
    out.append("</svg>")
    Path(path).write_text("\n".join(out))


def save_png(path: str | Path, pic: Picture, dpi: int = 110) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    x0, y0, x1, y1 = pic.bounds()
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig, ax = plt.subplots(figsize=(10, max(3.0, min(10 * aspect, 14))))
    for layer in pic.segments:
        if len(layer.segments):
            ax.add_collection(
                LineCollection(
                    np.asarray(layer.segments).reshape(-1, 2, 2),
                    colors=layer.colour,
                    linewidths=max(0.6, layer.width_m * 25),
                    alpha=layer.opacity,
                    label=layer.label or None,
                )
            )
    for p in pic.paths:
        xy = np.asarray(p.xy).reshape(-1, 2)
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], color=p.colour, lw=1.0, label=p.label or None)
            if p.start_marker:
                ax.plot(xy[0, 0], xy[0, 1], "o", color=p.colour, ms=5)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if pic.title:
        ax.set_title(pic.title)
    if any(layer.label for layer in pic.segments) or any(p.label for p in pic.paths):
        ax.legend(loc="upper right", fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def save_picture(stem: str | Path, pic: Picture) -> list[Path]:
    """Write ``stem.svg`` and ``stem.png``; returns the paths."""
    stem = Path(stem)
    svg, png = stem.with_suffix(".svg"), stem.with_suffix(".png")
    save_svg(svg, pic)
    save_png(png, pic)
    return [svg, png]


def segments_geojson(
    segments: np.ndarray, properties: Sequence[dict] | None = None, kind: str = "segment"
) -> dict:
    """A FeatureCollection with one LineString per segment ``(N,2,2)``."""
    seg = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    props = properties if properties is not None else [{} for _ in range(len(seg))]
    feats = [
        {
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": s.round(4).tolist()},
            "properties": {"kind": kind, **p},
        }
        for s, p in zip(seg, props, strict=True)
    ]
    return {"type": "FeatureCollection", "features": feats}


def save_geojson(path: str | Path, collection: dict) -> None:
    Path(path).write_text(json.dumps(collection))


def _xml(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


# -- occupancy grids for navigation stacks ----------------------------------------------------

# Pixel values of a trinary map (negate 0: the darker, the more occupied): what ROS map_saver writes.
NAV2_OCCUPIED_PX, NAV2_FREE_PX, NAV2_UNKNOWN_PX = 0, 254, 205
NAV2_OCCUPIED_THRESH = 0.65
NAV2_FREE_THRESH = 0.196  # unknown's 205 reads as 1 - 205/255 = 0.19608: not below this, so unknown


def nav2_image(grid) -> np.ndarray:
    """A :class:`shared.occupancy.Grid` as the 8-bit image of a trinary nav2 map (row 0 on top)."""
    from shared.occupancy import FREE, OCCUPIED

    img = np.full(grid.cells.shape, NAV2_UNKNOWN_PX, np.uint8)
    img[grid.cells == FREE] = NAV2_FREE_PX
    img[grid.cells == OCCUPIED] = NAV2_OCCUPIED_PX
    return img[::-1]


def save_nav2(yaml_path: str | Path, grid) -> tuple[Path, Path]:
    """``grid`` as the map pair ROS ``map_server`` defined and nav2's reads: ``<stem>.pgm`` (binary
    P5, 8 bit) and ``yaml_path`` (``image``, ``mode: trinary``, ``resolution``, ``origin`` — the
    lower-left pixel's corner, ``[x, y, yaw]`` — ``negate``, ``occupied_thresh``, ``free_thresh``).
    Both are written beside their targets and renamed over them."""
    import os

    yaml_path = Path(yaml_path)
    if yaml_path.suffix not in (".yaml", ".yml"):
        raise ValueError(f"{yaml_path}: a nav2 map is named *.yaml (its image goes beside it as *.pgm)")
    pgm = yaml_path.with_suffix(".pgm")
    img = nav2_image(grid)
    h, w = img.shape
    header = f"P5\n# fleet-slam occupancy grid, {grid.resolution_m} m per pixel\n{w} {h}\n255\n".encode()
    yaml = (
        f"image: {pgm.name}\n"
        f"mode: trinary\n"
        f"resolution: {grid.resolution_m:.6g}\n"
        f"origin: [{grid.origin_x:.6f}, {grid.origin_y:.6f}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {NAV2_OCCUPIED_THRESH}\n"
        f"free_thresh: {NAV2_FREE_THRESH}\n"
    )
    for target, data in ((pgm, header + img.tobytes()), (yaml_path, yaml.encode())):
        tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, target)
    return pgm, yaml_path
