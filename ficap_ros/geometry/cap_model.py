"""The Fi-Cap geometry: 23 tag36h11 tags on the faces of a partial sphere.

The nominal cap is built from the parameters of ``shared/design/cap-spec.md``; an as-built model
(measured, with every tag a fraction of a millimetre off) replaces it through the same YAML file.

Frames and units:
    cap frame C: origin at the centre of the sphere the faces are tangent to, x forward (toward the
    wearer's nose), y to the wearer's left, z up. Every length in this module is in millimetres.

Corner order (per tag, as seen from outside the cap): top-left, top-right, bottom-right,
bottom-left of the printed tag, i.e. OpenCV ArUco's order c0..c3.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import yaml

from ficap_ros.errors import ModelError
from ficap_ros.files import OutputFile, load_yaml, write_atomic

__all__ = [
    "TAG_SIDE_MM",
    "FACE_SIDE_MM",
    "ROW_ANGLE_DEG",
    "SPHERE_RADIUS_MM",
    "ROWS",
    "CapModel",
    "nominal_model",
    "load_model",
    "write_atomic",
]

#: Ids of the tag36h11 family (0 to 586): a cap of other ids could never be detected.
TAG_FAMILY_SIZE = 587
#: Farthest a corner may lie from the cap origin, mm: the cap is a head's size; a model beyond
#: this is a typo or a file of another unit.
MAX_CORNER_MM = 1000.0
#: Shortest side a tag may have in a model, mm (its four corners must span a square).
MIN_TAG_SIDE_MM = 1.0

#: Side of the tag's black square (8 cells of 4 mm), mm.
TAG_SIDE_MM = 32.0
#: Side of the square face the tag is printed on (tag plus its 1-cell white quiet zone), mm.
FACE_SIDE_MM = 40.0
#: Angle between the normals of adjacent faces, deg.
ROW_ANGLE_DEG = 24.5
#: Radius of the sphere the faces are tangent to: adjacent 40 mm faces 24.5 deg apart meet edge to
#: edge, so half a face (20 mm) subtends half the angle at the centre.
SPHERE_RADIUS_MM = (FACE_SIDE_MM / 2.0) / math.tan(math.radians(ROW_ANGLE_DEG / 2.0))


def _in_row_step_deg(elevation_deg: float, angle_deg: float) -> float:
    """Azimuth step that puts normals at ``elevation_deg`` exactly ``angle_deg`` apart."""
    el = math.radians(elevation_deg)
    cos_step = (math.cos(math.radians(angle_deg)) - math.sin(el) ** 2) / math.cos(el) ** 2
    return math.degrees(math.acos(cos_step))


#: Rows as (elevation of the face normal deg, number of faces, in-row azimuth step deg), top first.
#: cap-spec gives 26.968 deg for the +-24.5 deg rows, the rounded value of the step that makes
#: in-row normals exactly 24.5 deg apart; we use the exact value so the 24.5 deg self-check holds
#: to 1e-6. The outer rows use 42 deg so no tag is covered by a neighbouring face.
ROWS: tuple[tuple[float, int, float], ...] = (
    (49.0, 3, 42.0),
    (24.5, 5, _in_row_step_deg(24.5, ROW_ANGLE_DEG)),
    (0.0, 7, ROW_ANGLE_DEG),
    (-24.5, 5, _in_row_step_deg(-24.5, ROW_ANGLE_DEG)),
    (-49.0, 3, 42.0),
)


@dataclass(frozen=True)
class CapModel:
    """A cap: tag ids with the four 3-D corners of each, in the cap frame, mm.

    Attributes:
        ids: tag ids, in model order (unique).
        corners_mm: array (N, 4, 3): corners of tag ``ids[i]`` in cap-spec order (top-left,
            top-right, bottom-right, bottom-left seen from outside), cap frame C, mm.
    """

    ids: tuple[int, ...]
    corners_mm: np.ndarray
    _index: dict[int, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        corners = np.asarray(self.corners_mm, dtype=np.float64)
        if corners.ndim != 3 or corners.shape[1:] != (4, 3):
            raise ModelError(f"cap model corners must have shape (N, 4, 3), got {corners.shape}")
        if len(self.ids) != corners.shape[0]:
            raise ModelError(f"cap model has {len(self.ids)} ids but {corners.shape[0]} corner sets")
        if corners.shape[0] == 0:
            raise ModelError("cap model has no tags")
        if not np.all(np.isfinite(corners)):
            raise ModelError("cap model corners contain NaN or infinity")
        far = float(np.max(np.abs(corners)))
        if far > MAX_CORNER_MM:
            raise ModelError(f"cap model corners lie up to {far:.6g} mm from the cap origin "
                             f"(a cap lies within {MAX_CORNER_MM:g} mm; units must be mm)")
        sides = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).min(axis=1)
        if np.any(sides < MIN_TAG_SIDE_MM):
            i = int(np.argmin(sides))
            raise ModelError(f"cap model tag {self.ids[i]!r} has corners {sides[i]:.3g} mm apart "
                             "(a tag's four corners span a square)")
        seen: dict[int, int] = {}
        for i, tag_id in enumerate(self.ids):
            if isinstance(tag_id, bool) or not isinstance(tag_id, (int, np.integer)) \
                    or not 0 <= tag_id < TAG_FAMILY_SIZE:
                raise ModelError(f"cap model tag id {tag_id!r} is not a tag36h11 id "
                                 f"(0 to {TAG_FAMILY_SIZE - 1})")
            if int(tag_id) in seen:
                raise ModelError(f"cap model has duplicate tag id {int(tag_id)}")
            seen[int(tag_id)] = i
        corners.setflags(write=False)
        object.__setattr__(self, "ids", tuple(int(i) for i in self.ids))
        object.__setattr__(self, "corners_mm", corners)
        object.__setattr__(self, "_index", seen)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CapModel):
            return NotImplemented
        return self.ids == other.ids and np.array_equal(self.corners_mm, other.corners_mm)

    def __hash__(self) -> int:
        return hash((self.ids, self.corners_mm.tobytes()))

    # -- lookups -------------------------------------------------------------------------------
    def __contains__(self, tag_id: object) -> bool:
        return tag_id in self._index

    def __len__(self) -> int:
        return len(self.ids)

    def index_of(self, tag_id: int) -> int:
        """Row of ``tag_id`` in ``corners_mm``; raises ``KeyError`` for an id not in the model."""
        return self._index[tag_id]

    def corners_of(self, tag_id: int) -> np.ndarray:
        """Corners (4, 3) of one tag, cap frame, mm."""
        return self.corners_mm[self._index[tag_id]]

    @property
    def centres_mm(self) -> np.ndarray:
        """Tag centres (N, 3), cap frame, mm (a copy of the ones computed once: the tracker asks
        for them several times a frame; a copy, as scipy's Rotation.apply refuses read-only
        arrays and a caller may write to it)."""
        return self._centres_mm.copy()

    @cached_property
    def _centres_mm(self) -> np.ndarray:
        return self.corners_mm.mean(axis=1)

    @property
    def normals(self) -> np.ndarray:
        """Outward unit normals (N, 3) of the tag planes, cap frame (a copy of the ones computed
        once: the tracker's view angles ask for them every frame, ~0.05 ms each to compute).

        From the corner order (TL, TR, BR, BL seen from outside): right x down = inward, so the
        outward normal is down x right.
        """
        return self._normals.copy()

    @cached_property
    def _normals(self) -> np.ndarray:
        c = self.corners_mm
        right = (c[:, 1] - c[:, 0]) + (c[:, 2] - c[:, 3])
        down = (c[:, 3] - c[:, 0]) + (c[:, 2] - c[:, 1])
        n = np.cross(down, right)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def face_corners_mm(self, face_side_mm: float = FACE_SIDE_MM) -> np.ndarray:
        """Corners (N, 4, 3) of the square face each tag is printed on, same order, mm.

        The face is the tag square scaled about its centre by ``face_side_mm / TAG_SIDE_MM``: the
        white quiet zone around the black border.
        """
        centres = self.centres_mm[:, None, :]
        return centres + (self.corners_mm - centres) * (face_side_mm / TAG_SIDE_MM)

    # -- serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The ``{"frame": "cap", "units": "mm", "tags": [...]}`` form of YAML and JSON."""
        return {
            "frame": "cap",
            "units": "mm",
            "tags": [
                {"id": tag_id, "corners_mm": [[float(v) for v in p] for p in self.corners_mm[i]]}
                for i, tag_id in enumerate(self.ids)
            ],
        }

    @classmethod
    def from_dict(cls, data: Any, source: str = "cap model") -> CapModel:
        """Build a model from the ``to_dict`` form; raises ``ModelError`` naming ``source``."""
        if not isinstance(data, dict) or not isinstance(data.get("tags"), list):
            raise ModelError(f"{source}: expected a mapping with a 'tags' list")
        if data.get("units", "mm") != "mm":
            raise ModelError(f"{source}: units must be 'mm', got {data.get('units')!r}")
        if data.get("frame", "cap") != "cap":
            raise ModelError(f"{source}: frame must be 'cap', got {data.get('frame')!r}")
        ids: list[int] = []
        corners: list[Any] = []
        for k, tag in enumerate(data["tags"]):
            if not isinstance(tag, dict) or "id" not in tag or "corners_mm" not in tag:
                raise ModelError(f"{source}: tag entry {k} needs 'id' and 'corners_mm'")
            ids.append(tag["id"])
            corners.append(tag["corners_mm"])
        if not all(_numbers(c) for c in corners):
            raise ModelError(f"{source}: corners_mm must be 4 corners of 3 numbers per tag")
        try:
            array = np.asarray(corners, dtype=np.float64)
        except (TypeError, ValueError, OverflowError) as err:
            raise ModelError(f"{source}: corners are not numbers: {err}") from err
        try:
            return cls(tuple(ids), array)
        except ModelError as err:
            raise ModelError(f"{source}: {err}") from err

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def to_yaml(self) -> str:
        header = (
            "# Fi-Cap model: tag ids and the four corners of each (top-left, top-right,\n"
            "# bottom-right, bottom-left seen from outside), cap frame C (x forward, y left, z up), mm.\n"
        )
        return header + yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None)

    def save(self, path: str | os.PathLike[str] | OutputFile, inputs: tuple[Any, ...] = ()) -> None:
        """Write the model as YAML under the output rule (``files.OutputFile``: checked and
        locked, written beside its target and renamed into place).

        Args:
            path: the file, or an ``OutputFile`` taken when the verb started.
            inputs: the verb's inputs (never overwritten).

        Raises:
            OutputError: ``path`` breaks the output rule or cannot be written.
        """
        if isinstance(path, OutputFile):
            path.write(self.to_yaml())
            return
        with OutputFile(path, inputs, "cap model") as out:
            out.write(self.to_yaml())


def _numbers(corners: Any) -> bool:
    """Four corners of three real numbers (booleans and text are no coordinates)."""
    return (isinstance(corners, (list, tuple)) and len(corners) == 4 and all(
        isinstance(p, (list, tuple)) and len(p) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in p) for p in corners))


def load_model(path: str | os.PathLike[str]) -> CapModel:
    """Load a cap model from YAML (or JSON, a subset of YAML) through the guarded loader
    (``files.load_yaml``); raises ``ModelError`` naming the file."""
    return CapModel.from_dict(load_yaml(path, "cap model", ModelError), source=f"cap model {path}")


def nominal_model() -> CapModel:
    """The nominal cap of cap-spec.md, built from its parameters."""
    half = TAG_SIDE_MM / 2.0
    z_up = np.array([0.0, 0.0, 1.0])
    ids: list[int] = []
    corners: list[np.ndarray] = []
    for elevation_deg, count, step_deg in ROWS:
        el = math.radians(elevation_deg)
        for k in range(count):
            az = math.radians(((count - 1) / 2.0 - k) * step_deg)
            n = np.array([-math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            c = SPHERE_RADIUS_MM * n
            u = np.cross(z_up, n)
            u /= np.linalg.norm(u)
            v = np.cross(u, n)
            corners.append(
                np.array(
                    [c - half * u - half * v, c + half * u - half * v,
                     c + half * u + half * v, c - half * u + half * v]
                )
            )
            ids.append(len(ids))
    return CapModel(tuple(ids), np.array(corners))
