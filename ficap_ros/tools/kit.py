"""The printable Fi-Cap kit: 1:1 tag sheets (PDF, SVG), an assembly sheet, and a cap-shell STL.

Tag sheets are described once as a list of vector primitives in page millimetres (``SheetPage``,
origin at the top-left corner of the paper, y down) and written by two thin back ends: SVG (user
unit = 1 mm) and PDF (matplotlib's PDF back end, 72 pt per inch, so 1 mm = 72 / 25.4 pt). The tests
rasterise the same primitives and decode the tags with cv2.aruco, so what is printed is what is
checked.

Tag images are the ones OpenCV draws (``cv2.aruco.generateImageMarker`` with
``DICT_APRILTAG_36h11``, 1-cell black border), i.e. the official apriltag-imgs PNGs turned by
180 deg; every page says so. Each tag is drawn upright (its top row toward the top of the page), as
it is mounted on the cap (top row toward +z, cap-spec.md).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence
from xml.sax.saxutils import escape

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.files import OutputFolder
from ficap_ros.geometry.cap_model import (
    FACE_SIDE_MM,
    ROWS,
    TAG_SIDE_MM,
    CapModel,
    nominal_model,
    write_atomic,
)
from ficap_ros.geometry.tag36h11 import TAG_CELLS

__all__ = [
    "PAPER_SIZES_MM",
    "MM_PER_INCH",
    "PT_PER_MM",
    "SCALE_BAR_MM",
    "ORIENTATION_NOTE",
    "Rect",
    "Text",
    "TagPlacement",
    "SheetPage",
    "KitResult",
    "tag_cells",
    "tag_black_rects_mm",
    "layout_tag_sheets",
    "sheet_svg",
    "write_sheets_pdf",
    "rasterize_page",
    "rear_view_polygons",
    "write_assembly_sheet",
    "cap_shell_triangles",
    "write_stl",
    "make_kit",
]

#: Paper sizes (width, height), portrait, mm.
PAPER_SIZES_MM: dict[str, tuple[float, float]] = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}
MM_PER_INCH = 25.4
#: PDF user space: 72 pt per inch.
PT_PER_MM = 72.0 / MM_PER_INCH
#: Length of the printed scale bar, mm.
SCALE_BAR_MM = 100.0
CELL_MM = TAG_SIDE_MM / TAG_CELLS

ORIENTATION_NOTE = (
    "Tags: tag36h11 exactly as OpenCV draws them (cv2.aruco.generateImageMarker, DICT_APRILTAG_36h11)"
    " = the official apriltag-imgs PNGs turned 180 deg. Mount each face upright: id label below,"
    " tag top row toward the top of the cap (+z)."
)
SCALE_NOTE = (
    "Print at 100 % / actual size (no fit to page). Black squares 32 mm, faces (cut lines) 40 mm;"
    " the bar must measure 100 mm. Before cutting, write each id and an up arrow on the back of"
    " its face."
)

_MARGIN_MM = 10.0
_HEADER_MM = 20.0
_FOOTER_MM = 20.0
_GAP_X_MM = 8.0
_LABEL_MM = 9.0
_GAP_Y_MM = 4.0
_CUT_GREY = 0.55


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle in page mm (x right, y down from the top-left paper corner).

    ``fill`` is a grey level in [0, 1] (0 black) or None; ``stroke`` likewise, with
    ``stroke_mm`` line width. Rectangles of one ``group`` with the same fill are written as one
    path (non-zero rule) so adjacent black cells print without hairline seams.
    """

    x_mm: float
    y_mm: float
    w_mm: float
    h_mm: float
    fill: float | None = 0.0
    stroke: float | None = None
    stroke_mm: float = 0.0
    group: str = ""


@dataclass(frozen=True)
class Text:
    """A line of text; ``x_mm``/``y_mm`` is the anchor (``ha`` left|center|right, baseline)."""

    x_mm: float
    y_mm: float
    text: str
    size_mm: float
    ha: str = "left"
    bold: bool = False
    grey: float = 0.0


@dataclass(frozen=True)
class TagPlacement:
    """Where one tag is on a sheet: its 40 mm face's top-left corner, page mm."""

    tag_id: int
    face_x_mm: float
    face_y_mm: float

    @property
    def tag_x_mm(self) -> float:
        return self.face_x_mm + (FACE_SIDE_MM - TAG_SIDE_MM) / 2.0

    @property
    def tag_y_mm(self) -> float:
        return self.face_y_mm + (FACE_SIDE_MM - TAG_SIDE_MM) / 2.0


@dataclass(frozen=True)
class SheetPage:
    """One page of tag sheet: paper size, tag placements and every primitive to draw."""

    paper: str
    width_mm: float
    height_mm: float
    number: int
    of: int
    tags: tuple[TagPlacement, ...]
    rects: tuple[Rect, ...]
    texts: tuple[Text, ...]


@dataclass(frozen=True)
class KitResult:
    """Files written by ``make_kit``."""

    out_dir: Path
    files: tuple[Path, ...]
    pages: tuple[SheetPage, ...] = field(repr=False)


# -- tags ---------------------------------------------------------------------------------------
def tag_cells(tag_id: int) -> np.ndarray:
    """The 8x8 cells of a tag36h11 tag as OpenCV draws it, True = black, row 0 at the top
    (``detection.tag_cells``, read-only), after checking the id is one of the family's."""
    import cv2

    from ficap_ros.geometry.tag36h11 import tag_cells as detected_tag_cells

    count = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11).bytesList.shape[0]
    if not 0 <= tag_id < count:
        raise ConfigError(f"tag id {tag_id} is not a tag36h11 id (0..{count - 1})")
    return detected_tag_cells(int(tag_id))


def tag_black_rects_mm(tag_id: int, x_mm: float, y_mm: float, group: str = "") -> list[Rect]:
    """Black cells of a tag whose 32 mm square has its top-left corner at (x_mm, y_mm).

    Horizontal runs of black cells are merged into one rectangle (fewer, exact vector shapes).
    """
    cells = tag_cells(tag_id)
    rects: list[Rect] = []
    for row in range(TAG_CELLS):
        col = 0
        while col < TAG_CELLS:
            if not cells[row, col]:
                col += 1
                continue
            start = col
            while col < TAG_CELLS and cells[row, col]:
                col += 1
            rects.append(
                Rect(x_mm + start * CELL_MM, y_mm + row * CELL_MM, (col - start) * CELL_MM, CELL_MM,
                     fill=0.0, group=group)
            )
    return rects


def _row_and_position(tag_id: int) -> tuple[int, int] | None:
    """(row 1..5 from the top, position 1..n from the wearer's left) of a nominal id."""
    first = 0
    for row, (_, count, _) in enumerate(ROWS):
        if first <= tag_id < first + count:
            return row + 1, tag_id - first + 1
        first += count
    return None


# -- tag sheets ---------------------------------------------------------------------------------
def layout_tag_sheets(ids: Sequence[int] | None = None, paper: str = "a4") -> tuple[SheetPage, ...]:
    """Lay the tags out on as many pages of ``paper`` as needed, with labels and a scale bar.

    Raises:
        ConfigError: unknown paper size or a duplicate/invalid id.
    """
    if paper not in PAPER_SIZES_MM:
        raise ConfigError(f"unknown paper {paper!r}; expected one of {', '.join(PAPER_SIZES_MM)}")
    ids = list(nominal_model().ids if ids is None else ids)
    if len(set(ids)) != len(ids):
        raise ConfigError("tag ids for the kit must be unique")
    width, height = PAPER_SIZES_MM[paper]
    pitch_x = FACE_SIDE_MM + _GAP_X_MM
    pitch_y = FACE_SIDE_MM + _LABEL_MM + _GAP_Y_MM
    cols = int((width - 2 * _MARGIN_MM + _GAP_X_MM) // pitch_x)
    rows = int((height - 2 * _MARGIN_MM - _HEADER_MM - _FOOTER_MM + _GAP_Y_MM) // pitch_y)
    per_page = cols * rows
    n_pages = max(1, math.ceil(len(ids) / per_page))
    grid_w = cols * pitch_x - _GAP_X_MM
    x0 = (width - grid_w) / 2.0
    y0 = _MARGIN_MM + _HEADER_MM + 4.0
    pages: list[SheetPage] = []
    for p in range(n_pages):
        chunk = ids[p * per_page:(p + 1) * per_page]
        tags: list[TagPlacement] = []
        rects: list[Rect] = []
        texts: list[Text] = [
            Text(_MARGIN_MM, _MARGIN_MM + 5.0,
                 f"Fi-Cap tag sheet {p + 1}/{n_pages}  ({paper.upper()}, 1:1 scale, tag36h11)",
                 4.2, bold=True),
        ]
        texts += [Text(_MARGIN_MM, _MARGIN_MM + 10.0 + 4.2 * k, line, 2.6)
                  for k, line in enumerate(_wrap(ORIENTATION_NOTE, 105))]
        for k, tag_id in enumerate(chunk):
            r, c = divmod(k, cols)
            place = TagPlacement(int(tag_id), x0 + c * pitch_x, y0 + r * pitch_y)
            tags.append(place)
            group = f"tag-{tag_id}"
            rects += tag_black_rects_mm(int(tag_id), place.tag_x_mm, place.tag_y_mm, group=group)
            # Cut line: the 40 mm face outline, a thin grey hairline centred on the face edge.
            rects.append(Rect(place.face_x_mm, place.face_y_mm, FACE_SIDE_MM, FACE_SIDE_MM,
                              fill=None, stroke=_CUT_GREY, stroke_mm=0.15, group=f"cut-{tag_id}"))
            # Up mark just outside the cut line, centred over the face.
            cx = place.face_x_mm + FACE_SIDE_MM / 2.0
            texts.append(Text(cx, place.face_y_mm - 0.8, "TOP", 2.0, ha="center", grey=0.4))
            label = f"id {tag_id}"
            where = _row_and_position(int(tag_id))
            texts.append(Text(cx, place.face_y_mm + FACE_SIDE_MM + 5.0, label, 3.8, ha="center",
                              bold=True))
            if where is not None:
                texts.append(Text(cx, place.face_y_mm + FACE_SIDE_MM + 8.4,
                                  f"row {where[0]}, #{where[1]} from left", 2.3, ha="center",
                                  grey=0.3))
        # Scale bar: ten alternating 10 mm segments in an outline, with the length written.
        bar_x = _MARGIN_MM
        bar_y = height - _MARGIN_MM - 13.0
        for s in range(10):
            rects.append(Rect(bar_x + 10.0 * s, bar_y, 10.0, 3.0,
                              fill=0.0 if s % 2 == 0 else 1.0, group="scale-bar"))
        rects.append(Rect(bar_x, bar_y, SCALE_BAR_MM, 3.0, fill=None, stroke=0.0, stroke_mm=0.2,
                          group="scale-bar-outline"))
        texts.append(Text(bar_x, bar_y - 1.2, "0", 2.6))
        texts.append(Text(bar_x + SCALE_BAR_MM, bar_y - 1.2, f"{SCALE_BAR_MM:.0f} mm", 2.6,
                          ha="center"))
        texts += [Text(bar_x, bar_y + 7.0 + 3.6 * k, line, 2.6)
                  for k, line in enumerate(_wrap(SCALE_NOTE, 110))]
        pages.append(SheetPage(paper, width, height, p + 1, n_pages, tuple(tags), tuple(rects),
                               tuple(texts)))
    return tuple(pages)


def _wrap(text: str, width: int) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width)


def _grey_hex(grey: float) -> str:
    v = int(round(255 * min(max(grey, 0.0), 1.0)))
    return f"#{v:02x}{v:02x}{v:02x}"


def _fmt(v: float) -> str:
    return f"{v:.4f}".rstrip("0").rstrip(".")


def _fill_groups(rects: Iterable[Rect]) -> dict[tuple[str, float], list[Rect]]:
    groups: dict[tuple[str, float], list[Rect]] = {}
    for r in rects:
        if r.fill is not None:
            groups.setdefault((r.group, r.fill), []).append(r)
    return groups


def sheet_svg(page: SheetPage) -> str:
    """The page as an SVG document whose user unit is exactly 1 mm (width/height in mm)."""
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_fmt(page.width_mm)}mm" '
        f'height="{_fmt(page.height_mm)}mm" viewBox="0 0 {_fmt(page.width_mm)} {_fmt(page.height_mm)}">',
        f"<title>Fi-Cap tag sheet {page.number}/{page.of} ({page.paper}, 1:1, 1 unit = 1 mm)</title>",
        f"<desc>{escape(ORIENTATION_NOTE)} {escape(SCALE_NOTE)}</desc>",
        f'<rect x="0" y="0" width="{_fmt(page.width_mm)}" height="{_fmt(page.height_mm)}" fill="#ffffff"/>',
    ]
    for (group, grey), rects in _fill_groups(page.rects).items():
        d = " ".join(
            f"M{_fmt(r.x_mm)} {_fmt(r.y_mm)}h{_fmt(r.w_mm)}v{_fmt(r.h_mm)}h{_fmt(-r.w_mm)}z"
            for r in rects
        )
        tag_attr = f' data-tag-id="{group[4:]}"' if group.startswith("tag-") else ""
        out.append(f'<path id="{escape(group)}-fill"{tag_attr} fill="{_grey_hex(grey)}" '
                   f'fill-rule="nonzero" d="{d}"/>')
    for r in page.rects:
        if r.stroke is not None:
            out.append(
                f'<rect class="{escape(r.group.split("-")[0])}" x="{_fmt(r.x_mm)}" y="{_fmt(r.y_mm)}" '
                f'width="{_fmt(r.w_mm)}" height="{_fmt(r.h_mm)}" fill="none" '
                f'stroke="{_grey_hex(r.stroke)}" stroke-width="{_fmt(r.stroke_mm)}"/>'
            )
    anchor = {"left": "start", "center": "middle", "right": "end"}
    for t in page.texts:
        weight = ' font-weight="bold"' if t.bold else ""
        out.append(
            f'<text x="{_fmt(t.x_mm)}" y="{_fmt(t.y_mm)}" font-family="Helvetica, Arial, sans-serif" '
            f'font-size="{_fmt(t.size_mm)}" text-anchor="{anchor[t.ha]}"{weight} '
            f'fill="{_grey_hex(t.grey)}">{escape(t.text)}</text>'
        )
    out.append("</svg>")
    return "\n".join(out) + "\n"


def _draw_page_matplotlib(page: SheetPage):  # type: ignore[no-untyped-def]
    """A matplotlib figure of exactly the paper size whose data coordinates are page mm."""
    from matplotlib.figure import Figure
    from matplotlib.patches import PathPatch, Rectangle
    from matplotlib.path import Path as MplPath

    fig = Figure(figsize=(page.width_mm / MM_PER_INCH, page.height_mm / MM_PER_INCH))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, page.width_mm)
    ax.set_ylim(page.height_mm, 0.0)
    ax.set_axis_off()
    for (_, grey), rects in _fill_groups(page.rects).items():
        verts: list[tuple[float, float]] = []
        codes: list[int] = []
        for r in rects:
            x1, y1 = r.x_mm + r.w_mm, r.y_mm + r.h_mm
            verts += [(r.x_mm, r.y_mm), (x1, r.y_mm), (x1, y1), (r.x_mm, y1), (r.x_mm, r.y_mm)]
            codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO,
                      MplPath.CLOSEPOLY]
        ax.add_patch(PathPatch(MplPath(verts, codes), facecolor=str(grey), edgecolor="none",
                               linewidth=0.0, snap=False, antialiased=True))
    for r in page.rects:
        if r.stroke is not None:
            ax.add_patch(Rectangle((r.x_mm, r.y_mm), r.w_mm, r.h_mm, fill=False,
                                   edgecolor=str(r.stroke), linewidth=r.stroke_mm * PT_PER_MM,
                                   snap=False))
    for t in page.texts:
        ax.text(t.x_mm, t.y_mm, t.text, fontsize=t.size_mm * PT_PER_MM, ha=t.ha,
                va="baseline", color=str(t.grey), fontweight="bold" if t.bold else "medium",
                fontfamily="Helvetica")
    return fig


def write_sheets_pdf(pages: Sequence[SheetPage], path: Path) -> None:
    """Write the pages as one PDF (vector; standard Helvetica, so text stays searchable)."""
    import io

    import matplotlib
    from matplotlib.backends.backend_pdf import PdfPages

    buffer = io.BytesIO()
    # Standard 14 fonts: plain text strings in the page stream (searchable, no embedding).
    with matplotlib.rc_context({"pdf.use14corefonts": True, "font.family": "sans-serif"}):
        with PdfPages(buffer, metadata={"Title": "Fi-Cap tag sheets (1:1)",
                                        "Subject": ORIENTATION_NOTE}) as pdf:
            for page in pages:
                pdf.savefig(_draw_page_matplotlib(page))
    write_atomic(Path(path), buffer.getvalue())


def rasterize_page(page: SheetPage, px_per_mm: float = 10.0) -> np.ndarray:
    """Grey uint8 raster of a page's filled rectangles (the printed cells; no text), y down.

    Pixel (i, j) covers page mm [j, j+1) / px_per_mm; used to check that what is printed decodes.
    """
    h = int(round(page.height_mm * px_per_mm))
    w = int(round(page.width_mm * px_per_mm))
    image = np.full((h, w), 255, dtype=np.uint8)
    for r in page.rects:
        if r.fill is None:
            continue
        j0, j1 = int(round(r.x_mm * px_per_mm)), int(round((r.x_mm + r.w_mm) * px_per_mm))
        i0, i1 = int(round(r.y_mm * px_per_mm)), int(round((r.y_mm + r.h_mm) * px_per_mm))
        image[i0:i1, j0:j1] = int(round(255 * r.fill))
    return image


# -- assembly sheet -----------------------------------------------------------------------------
def rear_view_polygons(
    model: CapModel, distance_mm: float = 600.0, f_px: float = 1000.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cap as a pinhole camera right behind it sees it (the rear camera's view).

    Returns:
        faces_px (N, 4, 2), tags_px (N, 4, 2), depth_mm (N,) of the face centres and
        cells_px (N, 8, 8, 4, 2), the projected corners of every tag cell; image x to the right
        (the wearer's right), y down.
    """
    from ficap_ros.geometry.camera import CameraModel
    from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform

    # Camera on the cap's -x axis looking forward (+x): optical axis = cap x.
    T_cam_cap = Transform(CAM_FROM_FORWARD, np.array([0.0, 0.0, distance_mm]))
    camera = CameraModel.pinhole(1000, 1000, f_px=f_px)
    faces = model.face_corners_mm()
    tags = model.corners_mm
    # Cell corners by bilinear interpolation of the tag corners (a tag is planar and square).
    s = np.linspace(0.0, 1.0, TAG_CELLS + 1)
    tl, tr, br, bl = (tags[:, k][:, None, None, :] for k in range(4))
    a = s[None, :, None, None]  # down
    b = s[None, None, :, None]  # right
    grid = (1 - a) * ((1 - b) * tl + b * tr) + a * ((1 - b) * bl + b * br)  # (N, 9, 9, 3)

    def project(points: np.ndarray) -> np.ndarray:
        return camera.project(T_cam_cap.apply(points.reshape(-1, 3))).reshape(points.shape[:-1] + (2,))

    grid_px = project(grid)
    cells = np.stack([grid_px[:, :-1, :-1], grid_px[:, :-1, 1:], grid_px[:, 1:, 1:],
                      grid_px[:, 1:, :-1]], axis=3)
    depth = T_cam_cap.apply(model.centres_mm)[:, 2]
    return project(faces), project(tags), depth, cells


def write_assembly_sheet(model: CapModel, png_path: Path, pdf_path: Path | None = None) -> None:
    """Face layout and ids as the rear camera sees the cap, with a row table; PNG (and PDF)."""
    import io

    from matplotlib.figure import Figure
    from matplotlib.patches import PathPatch, Polygon
    from matplotlib.path import Path as MplPath

    faces_px, _, depth, cells = rear_view_polygons(model)
    width_mm, height_mm = PAPER_SIZES_MM["a4"][1], PAPER_SIZES_MM["a4"][0]  # landscape
    fig = Figure(figsize=(width_mm / MM_PER_INCH, height_mm / MM_PER_INCH))
    ax = fig.add_axes((0.03, 0.08, 0.62, 0.82))
    colours = ["#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#ff7f0e"]
    order = np.argsort(-depth)  # far faces first
    rows_of = {}
    for tag_id in model.ids:
        where = _row_and_position(tag_id)
        rows_of[tag_id] = where
    for i in order:
        tag_id = model.ids[i]
        where = rows_of[tag_id]
        colour = colours[(where[0] - 1) % 5] if where else "#555555"
        ax.add_patch(Polygon(faces_px[i], closed=True, facecolor="white", edgecolor=colour,
                             linewidth=1.6))
        black = tag_cells(tag_id)
        # All black cells of a tag as one compound path: no seams between neighbouring cells.
        quads = cells[i][black]
        if len(quads):
            verts = np.concatenate([np.vstack([q, q[:1]]) for q in quads])
            codes = np.tile([MplPath.MOVETO] + [MplPath.LINETO] * 3 + [MplPath.CLOSEPOLY], len(quads))
            ax.add_patch(PathPatch(MplPath(verts, codes), facecolor="0.72", edgecolor="none",
                                   linewidth=0))
        centre = faces_px[i].mean(axis=0)
        ax.text(centre[0], centre[1], str(tag_id), ha="center", va="center", fontsize=15,
                fontweight="bold", color=colour,
                bbox={"boxstyle": "circle,pad=0.25", "facecolor": "white", "edgecolor": colour,
                      "linewidth": 1.2})
    lo = faces_px.reshape(-1, 2).min(axis=0) - 15
    hi = faces_px.reshape(-1, 2).max(axis=0) + 15
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(hi[1], lo[1])  # image y down
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title("Fi-Cap seen from behind (the rear camera's view)", fontsize=13)
    ax.set_xlabel("wearer's LEFT  <-  image left                    image right  ->  wearer's RIGHT",
                  fontsize=9)
    # Row table.
    tx = fig.add_axes((0.67, 0.08, 0.31, 0.82))
    tx.set_axis_off()
    tx.set_xlim(0, 1)
    tx.set_ylim(1, 0)
    tx.text(0.0, 0.03, "Rows (top to bottom), ids from the\nwearer's left to right:", fontsize=11,
            fontweight="bold", va="top")
    first = 0
    y = 0.17
    for row, (elevation, count, step) in enumerate(ROWS):
        ids = [t for t in model.ids if first <= t < first + count]
        tx.text(0.0, y, f"row {row + 1}  (el {elevation:+.1f} deg, {count} faces, "
                f"az step {step:.2f} deg)", fontsize=9, color=colours[row], va="top")
        tx.text(0.05, y + 0.045, "  ".join(f"{t:2d}" for t in ids), fontsize=12, fontweight="bold",
                color=colours[row], va="top", family="monospace")
        y += 0.12
        first += count
    notes = (
        "Faces: 40 mm squares, tags 32 mm, tangent to a sphere of radius "
        "92.11 mm; adjacent faces 24.5 deg apart meet edge to edge.\n\n"
        "Each tag upright on its face: its top row toward the top of the cap (+z); "
        "the centre tag (id 11) faces straight back.\n\n"
        "Grey cells: the tag as printed (OpenCV's drawing = apriltag-imgs PNG turned 180 deg)."
    )
    tx.text(0.0, y + 0.02, notes, fontsize=8.5, va="top", wrap=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=150)
    write_atomic(Path(png_path), buffer.getvalue())
    if pdf_path is not None:
        buffer = io.BytesIO()
        fig.savefig(buffer, format="pdf")
        write_atomic(Path(pdf_path), buffer.getvalue())


# -- cap shell STL ------------------------------------------------------------------------------
def cap_shell_triangles(model: CapModel, thickness_mm: float = 2.0) -> np.ndarray:
    """Triangles (23*12, 3, 3) of the face plates, mm, wound counter-clockwise seen from outside.

    Each plate is the 40 mm face extruded ``thickness_mm`` inward toward the sphere centre (its
    sides lie on planes through the centre), so plates that meet edge to edge on the outside share
    their side walls: the plates join into one shell.
    """
    if not 0.0 < thickness_mm < 20.0:
        raise ConfigError(f"shell thickness must be in (0, 20) mm, got {thickness_mm}")
    faces = model.face_corners_mm()
    normals = model.normals
    tris: list[np.ndarray] = []
    for outer, n in zip(faces, normals):
        plane_distance = float(np.dot(outer.mean(axis=0), n))
        inner = outer * (1.0 - thickness_mm / plane_distance)
        quads = [outer[::-1], inner]  # outside (wound so the normal points outward), inside
        for k in range(4):
            j = (k + 1) % 4
            quads.append(np.array([outer[k], inner[k], inner[j], outer[j]]))
        centroid = np.vstack([outer, inner]).mean(axis=0)
        for q in quads:
            for tri in (q[[0, 1, 2]], q[[0, 2, 3]]):
                normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
                if np.dot(normal, tri.mean(axis=0) - centroid) < 0:
                    tri = tri[[0, 2, 1]]
                tris.append(tri)
    return np.array(tris)


def write_stl(triangles: np.ndarray, path: Path, name: str = "ficap shell") -> None:
    """Binary STL of triangles (M, 3, 3) in mm."""
    tris = np.asarray(triangles, dtype=np.float64)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    record = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    data = np.zeros(len(tris), dtype=record)
    data["normal"] = normals
    data["v"] = tris
    header = f"{name}, units mm".encode()[:80].ljust(80, b" ")
    write_atomic(Path(path), header + struct.pack("<I", len(tris)) + data.tobytes())


# -- the kit ------------------------------------------------------------------------------------
def make_kit(
    out_dir: str | Path,
    paper: str = "a4",
    model: CapModel | None = None,
    stl: bool = True,
    shell_thickness_mm: float = 2.0,
    inputs: Iterable[str | Path | None] = (),
) -> KitResult:
    """Write the whole kit into ``out_dir`` under the output rule (``files.OutputFolder``: new,
    empty or ficap's, never a recording or an input; built beside it and swapped in whole, the
    kit files of other papers already there kept), so a failure leaves no partial kit.

    Files: ``ficap_tags_<paper>.pdf``, ``ficap_tags_<paper>_p<k>.svg`` (one per page),
    ``ficap_assembly.png``/``.pdf``, and ``ficap_shell.stl`` when ``stl``.

    Args:
        inputs: the files the kit is made from (the model's), never overwritten.
    """
    with OutputFolder(out_dir, inputs, merge=True) as tmp:
        result = _make_kit(tmp, paper, model or nominal_model(), stl, shell_thickness_mm)
    out = Path(out_dir)
    return KitResult(out, tuple(out / p.name for p in result.files), result.pages)


def _make_kit(out: Path, paper: str, model: CapModel, stl: bool,
              shell_thickness_mm: float) -> KitResult:
    """Every file of the kit into the (temporary) folder ``out``."""
    pages = layout_tag_sheets(model.ids, paper)
    files: list[Path] = []
    pdf = out / f"ficap_tags_{paper}.pdf"
    write_sheets_pdf(pages, pdf)
    files.append(pdf)
    for page in pages:
        svg = out / f"ficap_tags_{paper}_p{page.number}.svg"
        write_atomic(svg, sheet_svg(page))
        files.append(svg)
    png, apdf = out / "ficap_assembly.png", out / "ficap_assembly.pdf"
    write_assembly_sheet(model, png, apdf)
    files += [png, apdf]
    if stl:
        path = out / "ficap_shell.stl"
        write_stl(cap_shell_triangles(model, shell_thickness_mm), path)
        files.append(path)
    return KitResult(out, tuple(files), pages)
