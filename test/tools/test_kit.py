"""The printable kit: exact 1:1 scale, every id present, every printed tag decodes to its id."""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.cap_model import FACE_SIDE_MM, TAG_SIDE_MM, nominal_model
from ficap_ros.tools.kit import (
    PAPER_SIZES_MM,
    PT_PER_MM,
    SCALE_BAR_MM,
    cap_shell_triangles,
    layout_tag_sheets,
    make_kit,
    rasterize_page,
    tag_cells,
)

PX_PER_MM = 10.0
ALL_IDS = set(range(23))


@pytest.fixture(scope="module")
def kit_a4(tmp_path_factory: pytest.TempPathFactory):
    return make_kit(tmp_path_factory.mktemp("kit_a4"), paper="a4")


def _detect(image: np.ndarray) -> dict[int, np.ndarray]:
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(image)
    assert ids is not None
    return {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners)}


def _check_decoded(found: dict[int, np.ndarray], expected: set[int]) -> None:
    """Every expected id decodes, upright (c0 top-left), 32 mm on a side."""
    assert set(found) == expected
    for tag_id, c in found.items():
        # Upright: OpenCV's c0 (top-left of the drawn tag) is the top-left corner on the page.
        assert np.argmin(c.sum(axis=1)) == 0, tag_id
        sides_mm = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1) / PX_PER_MM
        np.testing.assert_allclose(sides_mm, TAG_SIDE_MM, atol=0.25)


# -- a tiny PDF content-stream reader (paths and text are all we need) -------------------------
_TOKEN = re.compile(rb"\((?:[^()\\]|\\.)*\)|/[^\s/\[\]()<>]+|[A-Za-z*'\"]+|[-+]?(?:\d+\.?\d*|\.\d+)")


def _pdf_pages(data: bytes) -> list[tuple[tuple[float, float], bytes]]:
    """(mediabox size in pt, decompressed content stream) of each page, in order."""
    boxes = [tuple(float(v) for v in m.group(1).split()[2:4])
             for m in re.finditer(rb"/MediaBox \[([^\]]*)\]", data)]
    streams = []
    for m in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            content = zlib.decompress(m.group(1))
        except zlib.error:
            continue
        if b" re" in content or b" m\n" in content or b"Tj" in content:
            streams.append(content)
    assert len(boxes) == len(streams)
    return list(zip(boxes, streams))  # type: ignore[arg-type]


def _pdf_paths(content: bytes) -> list[tuple[bytes, float, list[np.ndarray]]]:
    """(paint operator, fill grey, subpaths in pt) of every painted path; clip paths skipped."""
    out = []
    stack: list[float] = []
    grey, grey_stack = 0.0, []
    subpaths: list[list[tuple[float, float]]] = []
    for tok in _TOKEN.findall(content):
        if tok[:1].isdigit() or tok[:1] in b"-+.":
            stack.append(float(tok))
            continue
        if tok.startswith((b"(", b"/")):
            stack.clear()
            continue
        if tok == b"m":
            subpaths.append([(stack[-2], stack[-1])])
        elif tok == b"l":
            subpaths[-1].append((stack[-2], stack[-1]))
        elif tok == b"re":
            x, y, w, h = stack[-4:]
            subpaths.append([(x, y), (x + w, y), (x + w, y + h), (x, y + h)])
        elif tok == b"g":
            grey = stack[-1]
        elif tok == b"q":
            grey_stack.append(grey)
        elif tok == b"Q":
            grey = grey_stack.pop()
        elif tok in (b"f", b"f*", b"S", b"B", b"b", b"s"):
            out.append((tok, grey, [np.array(p) for p in subpaths]))
            subpaths = []
        elif tok == b"n":
            subpaths = []
        stack.clear()
    return out


def _bbox_mm(subpaths: list[np.ndarray]) -> np.ndarray:
    pts = np.vstack(subpaths)
    return (pts.max(axis=0) - pts.min(axis=0)) / PT_PER_MM


def test_layout_has_every_tag_once_on_the_page() -> None:
    for paper, (w, h) in PAPER_SIZES_MM.items():
        pages = layout_tag_sheets(paper=paper)
        placed = [t for p in pages for t in p.tags]
        assert sorted(t.tag_id for t in placed) == sorted(ALL_IDS)
        for t in placed:
            assert 5.0 <= t.face_x_mm and t.face_x_mm + FACE_SIDE_MM <= w - 5.0
            assert 5.0 <= t.face_y_mm and t.face_y_mm + FACE_SIDE_MM <= h - 5.0
        for p in pages:  # no two faces overlap
            xy = np.array([(t.face_x_mm, t.face_y_mm) for t in p.tags])
            d = np.abs(xy[:, None] - xy[None])
            apart = (d[..., 0] >= FACE_SIDE_MM) | (d[..., 1] >= FACE_SIDE_MM)
            assert apart[~np.eye(len(xy), dtype=bool)].all()


def test_tag_cells_are_opencvs_drawing() -> None:
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for tag_id in (0, 11, 22):
        big = cv2.aruco.generateImageMarker(dictionary, tag_id, 400, borderBits=1)
        np.testing.assert_array_equal(tag_cells(tag_id), big[25::50, 25::50] < 128)
    with pytest.raises(ConfigError):
        tag_cells(100000)


def test_pdf_is_exact_scale_and_every_tag_decodes(kit_a4) -> None:
    pdf = kit_a4.out_dir / "ficap_tags_a4.pdf"
    pages = _pdf_pages(pdf.read_bytes())
    assert len(pages) == len(kit_a4.pages) >= 2
    tag_mm = TAG_SIDE_MM
    found_ids: set[int] = set()
    for (w_pt, h_pt), content in pages:
        # A4 at 72 pt/inch.
        assert w_pt == pytest.approx(210.0 * 72 / 25.4, abs=1e-3)
        assert h_pt == pytest.approx(297.0 * 72 / 25.4, abs=1e-3)
        paths = _pdf_paths(content)
        black = [p for p in paths if p[0] == b"f" and p[1] == 0.0]
        sizes = np.array([_bbox_mm(p[2]) for p in black])
        # One black path per tag: its outer border measures exactly 32 mm by 32 mm.
        tags_here = np.all(np.abs(sizes - tag_mm) < 1e-3, axis=1)
        assert tags_here.sum() >= 7
        cuts = [p for p in paths if p[0] == b"S" and np.allclose(_bbox_mm(p[2]), FACE_SIDE_MM, atol=1e-3)]
        assert len(cuts) == tags_here.sum()
        bar = [p for p in paths if p[0] == b"S" and abs(_bbox_mm(p[2])[0] - SCALE_BAR_MM) < 1e-3]
        assert len(bar) == 1
        # Rasterise the filled paths as printed and decode them.
        hmm = h_pt / PT_PER_MM
        image = np.full((int(round(hmm * PX_PER_MM)), int(round(w_pt / PT_PER_MM * PX_PER_MM))),
                        255, np.uint8)
        for op, grey, subpaths in paths:
            if op != b"f":
                continue
            polys = [np.round(np.column_stack([s[:, 0] / PT_PER_MM, hmm - s[:, 1] / PT_PER_MM])
                              * PX_PER_MM * 16).astype(np.int32) for s in subpaths]
            cv2.fillPoly(image, polys, int(round(255 * grey)), shift=4)
        found = _detect(image)
        _check_decoded(found, set(found))
        assert len(found) == tags_here.sum()
        found_ids |= set(found)
        # Every id is written as text on the page.
        for tag_id in found:
            assert f"(id {tag_id})".encode() in content
    assert found_ids == ALL_IDS


def test_svg_is_mm_and_every_tag_decodes(kit_a4) -> None:
    svgs = sorted(kit_a4.out_dir.glob("ficap_tags_a4_p*.svg"))
    assert len(svgs) == len(kit_a4.pages)
    ids_text: set[int] = set()
    decoded: set[int] = set()
    tagged: set[int] = set()
    ns = {"s": "http://www.w3.org/2000/svg"}
    for svg in svgs:
        root = ET.parse(svg).getroot()
        assert root.get("width") == "210mm" and root.get("height") == "297mm"
        assert root.get("viewBox") == "0 0 210 297"
        image = np.full((2970, 2100), 255, np.uint8)
        for path in root.findall("s:path", ns):
            grey = int(path.get("fill")[1:3], 16)
            for m in re.finditer(r"M([-\d.]+) ([-\d.]+)h([-\d.]+)v([-\d.]+)h([-\d.]+)z", path.get("d")):
                x, y, w, h, _ = (float(v) for v in m.groups())
                poly = np.array([(x, y), (x + w, y), (x + w, y + h), (x, y + h)]) * PX_PER_MM * 16
                cv2.fillPoly(image, [np.round(poly).astype(np.int32)], grey, shift=4)
            tag = path.get("data-tag-id")
            if tag is not None:  # the black cells of one tag, as one path: bbox exactly 32 mm
                xy = np.array([float(v) for v in re.findall(r"[-\d.]+", path.get("d"))])
                r = xy.reshape(-1, 5)
                size = np.array([(r[:, 0] + r[:, 2]).max() - r[:, 0].min(),
                                 (r[:, 1] + r[:, 3]).max() - r[:, 1].min()])
                np.testing.assert_allclose(size, TAG_SIDE_MM, atol=1e-4)
                tagged.add(int(tag))
        cuts = [r for r in root.findall("s:rect", ns) if r.get("class") == "cut"]
        for r in cuts:
            assert float(r.get("width")) == FACE_SIDE_MM and float(r.get("height")) == FACE_SIDE_MM
        found = _detect(image)
        _check_decoded(found, set(found))
        assert len(found) == len(cuts)
        decoded |= set(found)
        ids_text |= {int(m) for t in root.findall("s:text", ns)
                     for m in re.findall(r"^id (\d+)$", t.text or "")}
    assert decoded == ALL_IDS
    assert ids_text == ALL_IDS
    assert tagged == ALL_IDS


def test_letter_paper_and_layout_raster(tmp_path: Path) -> None:
    pages = layout_tag_sheets(paper="letter")
    assert pages[0].width_mm == pytest.approx(215.9) and pages[0].height_mm == pytest.approx(279.4)
    decoded: set[int] = set()
    for page in pages:
        found = _detect(rasterize_page(page, PX_PER_MM))
        _check_decoded(found, {t.tag_id for t in page.tags})
        decoded |= set(found)
    assert decoded == ALL_IDS
    with pytest.raises(ConfigError):
        layout_tag_sheets(paper="a3")


def test_stl_shell_is_closed_and_on_the_cap(kit_a4) -> None:
    data = (kit_a4.out_dir / "ficap_shell.stl").read_bytes()
    (count,) = struct.unpack("<I", data[80:84])
    assert count == 23 * 12 and len(data) == 84 + 50 * count
    tris = cap_shell_triangles(nominal_model(), 2.0)
    r = np.linalg.norm(tris.reshape(-1, 3), axis=1)
    outer = np.sqrt(92.114 ** 2 + 2 * 20.0 ** 2)
    assert r.max() == pytest.approx(outer, abs=0.01)
    # Each plate is closed: every edge is used exactly twice, once in each direction.
    for plate in tris.reshape(23, 12, 3, 3):
        edges: dict[tuple, int] = {}
        for tri in plate:
            for a, b in ((0, 1), (1, 2), (2, 0)):
                key = (tuple(np.round(tri[a], 6)), tuple(np.round(tri[b], 6)))
                edges[key] = edges.get(key, 0) + 1
        for (a, b), n in edges.items():
            assert n == 1 and edges.get((b, a)) == 1
        # Outward winding: signed volume positive.
        vol = np.einsum("ij,ij->i", plate[:, 0], np.cross(plate[:, 1], plate[:, 2])).sum() / 6.0
        assert vol == pytest.approx(40 * 40 * 2.0, rel=0.05)
