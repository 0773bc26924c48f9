"""The scene drawn into linear radiance by the ideal pinhole (K, no distortion): the car interior,
the neck and head ellipsoids, and every front-facing face of the cap, far to near.

Radiance is in units of the sensor's full well at the lighting's nominal exposure (a white face at
irradiance E collects the share E of the full well), before flare and spotlights. Faces are drawn
by a per-face homography, supersampled and box-filtered (each pixel integrates linear light over
its area), so a tag's outer corners sit exactly at their pinhole projection in OpenCV's pixel
convention. The head and neck hide faces behind them by a per-pixel depth test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth.config import RenderConfig
from ficap_ros.tools.synth.lighting import LIGHTS, Light, irradiance
from ficap_ros.tools.synth.scene import (
    BLACK_ALBEDO,
    HAIR_ALBEDO,
    NEAR_M,
    NECK_ALBEDO,
    NECK_CENTRE_M,
    NECK_SEMI_AXES_M,
    WHITE_ALBEDO,
    background,
    face_texture,
    hair_waves,
)

__all__ = ["HeadMaps", "render_head", "render_scene", "homography"]


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Exact 3x3 homography from 4 point pairs (float64 DLT; getPerspectiveTransform is float32)."""
    a = np.zeros((8, 8))
    b = np.zeros(8)
    for i, ((x, y), (u, v)) in enumerate(zip(src, dst)):
        a[2 * i] = [x, y, 1, 0, 0, 0, -u * x, -u * y]
        a[2 * i + 1] = [0, 0, 0, x, y, 1, -v * x, -v * y]
        b[2 * i], b[2 * i + 1] = u, v
    h = np.linalg.solve(a, b)
    return np.append(h, 1.0).reshape(3, 3)


# -- the head and neck ---------------------------------------------------------------------------
@dataclass(frozen=True)
class HeadMaps:
    """Head coverage and depth over its bounding box (x0, y0) .. (x1, y1) of the image."""

    box: tuple[int, int, int, int]
    alpha: np.ndarray  # (h, w) float32 coverage in [0, 1]
    depth_m: np.ndarray  # (h, w) float32 depth of the near surface, inf where no head

    def crop(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, depth) over an image ROI (zeros / inf outside the head box)."""
        alpha = np.zeros((y1 - y0, x1 - x0), np.float32)
        depth = np.full((y1 - y0, x1 - x0), np.inf, np.float32)
        hx0, hy0, hx1, hy1 = self.box
        ix0, iy0, ix1, iy1 = max(x0, hx0), max(y0, hy0), min(x1, hx1), min(y1, hy1)
        if ix1 > ix0 and iy1 > iy0:
            alpha[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] = self.alpha[iy0 - hy0:iy1 - hy0, ix0 - hx0:ix1 - hx0]
            depth[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] = self.depth_m[iy0 - hy0:iy1 - hy0, ix0 - hx0:ix1 - hx0]
        return alpha, depth


@dataclass(frozen=True)
class _Ellipsoid:
    """An ellipsoid seen by the camera: centre (camera frame, m), semi-axes (its own frame, m) and
    the rotation R_cam_ellipsoid (the cap's)."""

    centre_cam: np.ndarray
    axes: np.ndarray
    r: np.ndarray


@dataclass(frozen=True)
class _RayHits:
    """The pixel rays t * K^-1 [u v 1] against the ellipsoid, in unit-sphere coordinates
    o + t * d: ``of`` = o, ``d`` the ray directions, ``a`` = |d|^2, ``b`` = o . d, ``dist`` the
    signed distance (px, positive inside) to the silhouette, ``t`` the depth of the near hit."""

    of: list[float]
    d: list[np.ndarray]
    a: np.ndarray
    b: np.ndarray
    dist: np.ndarray
    t: np.ndarray


def _ellipsoid_box(e: _Ellipsoid, k: np.ndarray, w_img: int,
                   h_img: int) -> tuple[int, int, int, int]:
    """The image box (x0, y0, x1, y1) the ellipsoid's silhouette can cover (the whole image when
    part of it is nearer than ``NEAR_M``)."""
    g = np.linspace(0.0, math.pi, 13)
    th, ph = np.meshgrid(g, np.linspace(0.0, 2 * math.pi, 25))
    sphere = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    pts = e.centre_cam + (sphere * e.axes) @ e.r.T
    if np.any(pts[:, 2] < NEAR_M):
        return 0, 0, w_img, h_img
    # Surface samples miss the silhouette by under a few px at these sizes: 6 px margin.
    uv = (pts / pts[:, 2:3]) @ k.T
    x0 = int(max(0, math.floor(uv[:, 0].min()) - 6))
    y0 = int(max(0, math.floor(uv[:, 1].min()) - 6))
    x1 = int(min(w_img, math.ceil(uv[:, 0].max()) + 7))
    y1 = int(min(h_img, math.ceil(uv[:, 1].max()) + 7))
    return x0, y0, x1, y1


def _ray_hits(e: _Ellipsoid, k: np.ndarray, u: np.ndarray, v: np.ndarray) -> _RayHits:
    """Where the rays of pixels (u, v) meet the ellipsoid, and their distance to its silhouette.

    In unit-sphere coordinates the ray is o + t * M [u v 1]; it meets the sphere where
    a t^2 + 2 b t + (o . o - 1) = 0. The silhouette is the conic disc = b^2 - (o . o - 1) a = 0.
    """
    m = np.diag(1.0 / e.axes) @ e.r.T @ np.linalg.inv(k)
    o = np.diag(1.0 / e.axes) @ e.r.T @ (-e.centre_cam)
    cc = float(o @ o - 1.0)
    mf = [[float(m[i, j]) for j in range(3)] for i in range(3)]
    of = [float(x) for x in o]
    d = [mf[i][0] * u + mf[i][1] * v + mf[i][2] for i in range(3)]
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = of[0] * d[0] + of[1] * d[1] + of[2] * d[2]
    disc = b * b - cc * a
    # Signed distance (px, positive inside) to the silhouette conic disc = 0: disc / |grad disc|.
    db_du, db_dv = float(o @ m[:, 0]), float(o @ m[:, 1])
    da_du = 2.0 * (mf[0][0] * d[0] + mf[1][0] * d[1] + mf[2][0] * d[2])
    da_dv = 2.0 * (mf[0][1] * d[0] + mf[1][1] * d[1] + mf[2][1] * d[2])
    gu = (2.0 * db_du) * b - cc * da_du
    gv = (2.0 * db_dv) * b - cc * da_dv
    dist = disc / np.maximum(np.sqrt(gu * gu + gv * gv), np.float32(1e-12))
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return _RayHits(of, d, a, b, dist, t)


def _head_radiance(e: _Ellipsoid, hits: _RayHits, k: np.ndarray, u: np.ndarray, v: np.ndarray,
                   light: Light, seed: int, albedo: float) -> np.ndarray:
    """Radiance of the ellipsoid's surface at each ray's hit: Lambert shading of the ambient and
    directional light, the lamp at the camera, and the hair texture attached to the head."""
    r, t, d, of = e.r, hits.t, hits.d, hits.of
    # Shading: the ellipsoid normal is A^-1 x (x on the unit sphere), turned into the camera frame.
    xs = [of[i] + t * d[i] for i in range(3)]
    ne = [xs[i] * float(1.0 / e.axes[i]) for i in range(3)]
    l_vec = np.asarray(light.toward_light_cam, np.float64)
    l_vec = (r.T @ (l_vec / np.linalg.norm(l_vec)))  # light direction in the cap frame
    dot = float(l_vec[0]) * ne[0] + float(l_vec[1]) * ne[1] + float(l_vec[2]) * ne[2]
    lam = np.maximum(dot / (np.sqrt(ne[0] * ne[0] + ne[1] * ne[1] + ne[2] * ne[2]) + 1e-12), 0.0)
    waves, phases = hair_waves(seed)
    tex = np.zeros_like(hits.a)
    for kv, ph_ in zip(waves, phases):
        tex += np.sin(float(kv[0]) * xs[0] + float(kv[1]) * xs[1] + float(kv[2]) * xs[2] + float(ph_))
    irradiance_ = light.ambient + light.diffuse * lam
    if light.camera_lamp > 0.0:
        # The lamp at the camera (``Light``), metered at the head centre's distance: cos(incidence)
        # = -n . q / (|n| |q|) with q = R^T K^-1 [u v 1] the pixel's ray in the cap frame.
        rk = r.T @ np.linalg.inv(k)
        q = [float(rk[i, 0]) * u + float(rk[i, 1]) * v + float(rk[i, 2]) for i in range(3)]
        qn = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
        cos_cam = -(ne[0] * q[0] + ne[1] * q[1] + ne[2] * q[2]) / (
            np.sqrt(ne[0] * ne[0] + ne[1] * ne[1] + ne[2] * ne[2]) * qn + 1e-12)
        r_head = float(np.linalg.norm(e.centre_cam))
        irradiance_ = irradiance_ + light.camera_lamp * np.maximum(cos_cam, 0.0) * (
            r_head / np.maximum(t * qn, 1e-3)) ** 2
    return (albedo * (1.0 + 0.1 * tex)) * irradiance_


def render_head(
    img: np.ndarray, k: np.ndarray, T_cam_cap: Transform, cfg: RenderConfig, light: Light,
    hair_tint: np.ndarray, centre_m: tuple[float, float, float] | None = None,
    semi_axes_m: tuple[float, float, float] | None = None, albedo: float = HAIR_ALBEDO,
) -> HeadMaps | None:
    """Draw the head ellipsoid (or another one: the neck) into ``img`` in place; return its
    coverage and depth maps (None when it misses the image).

    The silhouette distance, depth and shading are smooth, so they are computed on a half-resolution
    grid and upsampled; the anti-aliased edge comes from the upsampled signed distance (px) to the
    silhouette conic.
    """
    h_img, w_img = img.shape[:2]
    e = _Ellipsoid(T_cam_cap.apply(np.asarray(centre_m or cfg.head_centre_m, np.float64)),
                   np.asarray(semi_axes_m or cfg.head_semi_axes_m, np.float64),
                   T_cam_cap.rotation.as_matrix())
    x0, y0, x1, y1 = _ellipsoid_box(e, k, w_img, h_img)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    w, h = x1 - x0, y1 - y0
    wh, hh = (w + 1) // 2, (h + 1) // 2
    # Half-res pixel j covers full-res pixels 2j, 2j + 1 of the box: centre at x0 + 2j + 0.5.
    u = (x0 + 0.5 + 2.0 * np.arange(wh, dtype=np.float32))[None, :]
    v = (y0 + 0.5 + 2.0 * np.arange(hh, dtype=np.float32))[:, None]
    hits = _ray_hits(e, k, u, v)
    rad = _head_radiance(e, hits, k, u, v, light, cfg.background_seed, albedo)
    valid = (hits.t > 0) & (hits.b < 0)
    dist = np.where(valid, hits.dist, -10.0)
    t = np.where(valid, hits.t, 1e3)  # 1e3 m: "far", never in front of a face
    fields = cv2.merge([dist.astype(np.float32), t.astype(np.float32), rad.astype(np.float32)])
    # Upsample: half-res sample j sits at full-res coordinate 2j + 0.5, which is what resize's
    # pixel-centre mapping with an exact factor 2 assumes.
    full = cv2.resize(fields, (2 * wh, 2 * hh), interpolation=cv2.INTER_LINEAR)[:h, :w]
    alpha = np.clip(full[..., 0] + 0.5, 0.0, 1.0)
    depth = np.where(alpha > 0, full[..., 1], np.inf).astype(np.float32)
    roi = img[y0:y1, x0:x1]
    al = alpha[..., None]
    roi *= 1.0 - al
    roi += (al * full[..., 2:3]) * hair_tint
    return HeadMaps((x0, y0, x1, y1), alpha, depth)


# -- the cap's faces -----------------------------------------------------------------------------
@dataclass(frozen=True)
class _Faces:
    """The cap's faces in the camera frame (m): face squares (N, 4, 3), tag squares (N, 4, 3),
    outward normals (N, 3), the front-facing ones far to near (``order``), the ambient and
    directional irradiance of each, and the cap's distance (the lamp's metering point)."""

    faces_cam: np.ndarray
    tags_cam: np.ndarray
    normals_cam: np.ndarray
    order: list[int]
    irr: np.ndarray
    r_cap: float


def _faces(model: CapModel, T_cam_cap: Transform, light: Light) -> _Faces:
    rot = T_cam_cap.rotation.as_matrix()
    faces_cam = T_cam_cap.apply(model.face_corners_mm().reshape(-1, 3) / 1000.0).reshape(-1, 4, 3)
    tags_cam = T_cam_cap.apply(model.corners_mm.reshape(-1, 3) / 1000.0).reshape(-1, 4, 3)
    normals_cam = model.normals @ rot.T
    centres_cam = tags_cam.mean(axis=1)
    front = (np.einsum("ij,ij->i", normals_cam, centres_cam) < 0.0) & np.all(
        faces_cam[:, :, 2] > NEAR_M, axis=1
    )
    order = sorted(np.flatnonzero(front), key=lambda i: -np.linalg.norm(centres_cam[i]))
    # The lamp at the camera is metered on the cap: its irradiance at the cap's distance is fixed.
    r_cap = float(np.linalg.norm(centres_cam.mean(axis=0)))
    return _Faces(faces_cam, tags_cam, normals_cam, order, irradiance(light, normals_cam), r_cap)


@dataclass(frozen=True)
class _FaceCover:
    """A face drawn over its image box (x0, y0, x1, y1): coverage of the face, of the tag square
    and blackness per pixel (each the pixel's share, linear)."""

    box: tuple[int, int, int, int]
    cov: np.ndarray
    tsq: np.ndarray
    blk: np.ndarray


def _face_cover(tag_id: int, pf: np.ndarray, pt: np.ndarray, width: int, height: int,
                s_max: int) -> _FaceCover | None:
    """Face ``tag_id`` with projected face corners ``pf`` and tag corners ``pt`` (px), drawn by a
    homography into a supersampled box and box-filtered; None when the box misses the image."""
    x0 = int(max(0, math.floor(pf[:, 0].min()) - 1))
    y0 = int(max(0, math.floor(pf[:, 1].min()) - 1))
    x1 = int(min(width, math.ceil(pf[:, 0].max()) + 2))
    y1 = int(min(height, math.ceil(pf[:, 1].max()) + 2))
    if x1 <= x0 or y1 <= y0:
        return None
    w, h = x1 - x0, y1 - y0
    sides_px = np.linalg.norm(pt - np.roll(pt, -1, axis=0), axis=1)
    edge_px = max(float(sides_px.max()), 1.0)
    # Big faces cost area: cap the supersampled edge near 320 px, but never below 3x.
    s = int(min(s_max, max(3, round(320.0 / edge_px))))
    # Texture resolution: one texel spans 1-2 supersamples along every side (the shortest
    # sets it). Bilinear lookup then draws each cell edge as a ramp at least one supersample
    # wide, and a ramp that wide, point-sampled and box-filtered, puts the edge within 0.09
    # supersample of the truth at any sub-pixel phase (a sharper texture would be off by up
    # to 0.25 supersample); the ramp is symmetric, so it only adds a little blur.
    texel_px = max(float(sides_px.min()), 1.0) * s / TAG_CELLS
    cell = int(min(64, max(2, 2 ** math.floor(math.log2(max(texel_px, 2.0))))))
    tex = face_texture(tag_id, cell)
    c = float(cell)
    src = np.array([[c - 0.5, c - 0.5], [9 * c - 0.5, c - 0.5], [9 * c - 0.5, 9 * c - 0.5],
                    [c - 0.5, 9 * c - 0.5]])
    # Image pixel x (centre convention) is supersampled pixel (x - x0 + 0.5) * s - 0.5.
    dst = (pt - [x0, y0] + 0.5) * s - 0.5
    hom = homography(src, dst)
    big = cv2.warpPerspective(tex, hom, (w * s, h * s), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    small = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) * (1 / 255)
    return _FaceCover((x0, y0, x1, y1), small[..., 0], small[..., 1], small[..., 2])


def _face_light(i: int, f: _Faces, cover: _FaceCover, k_inv: np.ndarray, light: Light,
                occluders: list[HeadMaps]) -> tuple[float | np.ndarray, np.ndarray]:
    """(irradiance, occlusion) of face ``i`` over its box: the lamp at the camera varies across
    the face; the head hides the pixels where it is nearer than the face plane."""
    x0, y0, x1, y1 = cover.box
    occl = np.zeros_like(cover.cov)
    lamp = light.camera_lamp > 0.0
    if occluders or lamp:
        # Depth of the face plane along each pixel's ray (t with K^-1 [u v 1], z = 1).
        n = f.normals_cam[i]
        d0 = float(n @ f.faces_cam[i][0])
        coef = n @ k_inv
        uu = np.arange(x0, x1, dtype=np.float32)[None, :]
        vv = np.arange(y0, y1, dtype=np.float32)[:, None]
        denom = coef[0] * uu + coef[1] * vv + coef[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z_face = d0 / denom
        z_face = np.where(z_face > 0, z_face, np.inf)
    irr_i: float | np.ndarray = f.irr[i]
    if lamp:
        # The lamp at the camera centre, at each pixel's point P of the face plane:
        # cos(incidence) / |P|^2 = |d0| / |P|^3 (d0 = n . P, the plane's distance).
        ray = [k_inv[j, 0] * uu + k_inv[j, 1] * vv + k_inv[j, 2] for j in range(3)]
        norm = np.sqrt(ray[0] ** 2 + ray[1] ** 2 + ray[2] ** 2)
        dist = np.where(np.isfinite(z_face), z_face * norm, np.inf)
        irr_i = (f.irr[i] + light.camera_lamp * abs(d0) * f.r_cap**2 / dist**3).astype(np.float32)
    if occluders:
        for occluder in occluders:
            h_alpha, h_depth = occluder.crop(x0, y0, x1, y1)
            occl = np.maximum(occl, h_alpha * (h_depth < z_face))
    return irr_i, occl


def _draw_faces(img: np.ndarray, model: CapModel, k: np.ndarray, f: _Faces, light: Light,
                occluders: list[HeadMaps], s_max: int
                ) -> tuple[np.ndarray, dict[int, tuple[tuple[int, int, int, int], np.ndarray]],
                           dict[int, float]]:
    """Paint the front faces far to near into ``img``; return the id buffer (model index of the
    face that covers each pixel most, -1 none), each drawn tag's box and tag-square coverage, and
    each front tag's projected area (px^2)."""
    height, width = img.shape[:2]
    k_inv = np.linalg.inv(k)
    id_buf = np.full((height, width), -1, np.int16)
    tag_cov: dict[int, tuple[tuple[int, int, int, int], np.ndarray]] = {}
    tag_area: dict[int, float] = {}
    for i in f.order:
        tag_id = model.ids[i]
        pf = f.faces_cam[i] / f.faces_cam[i][:, 2:3] @ k.T
        pt = f.tags_cam[i] / f.tags_cam[i][:, 2:3] @ k.T
        pf, pt = pf[:, :2], pt[:, :2]
        x_, y_ = pt[:, 0], pt[:, 1]
        tag_area[tag_id] = 0.5 * abs(
            float(np.dot(x_, np.roll(y_, -1)) - np.dot(y_, np.roll(x_, -1)))
        )
        cover = _face_cover(tag_id, pf, pt, width, height, s_max)
        if cover is None:
            continue
        irr_i, occl = _face_light(i, f, cover, k_inv, light, occluders)
        keep = 1.0 - occl
        eff = cover.cov * keep
        # Coverage-weighted (premultiplied) radiance: the box filter of the supersampled texture
        # integrates linear light over each pixel, as a sensor pixel does.
        premult = irr_i * (WHITE_ALBEDO * cover.cov - (WHITE_ALBEDO - BLACK_ALBEDO) * cover.blk) * keep
        x0, y0, x1, y1 = cover.box
        roi = img[y0:y1, x0:x1]
        roi *= (1.0 - eff)[..., None]
        roi += premult[..., None]
        id_buf[y0:y1, x0:x1][eff > 0.5] = i
        tag_cov[tag_id] = (cover.box, cover.tsq)
    return id_buf, tag_cov, tag_area


def _visible_fractions(model: CapModel, order: list[int], id_buf: np.ndarray,
                       tag_cov: dict[int, tuple[tuple[int, int, int, int], np.ndarray]],
                       tag_area: dict[int, float]) -> dict[int, float]:
    """Share of each front tag's square that ends up in the image and in front (its pixels in
    the id buffer, weighted by tag-square coverage, over its projected area)."""
    visible: dict[int, float] = {}
    for i in order:
        tag_id = model.ids[i]
        if tag_id not in tag_cov or tag_area[tag_id] <= 0:
            visible[tag_id] = 0.0
            continue
        (x0, y0, x1, y1), tsq = tag_cov[tag_id]
        seen = float(tsq[id_buf[y0:y1, x0:x1] == i].sum())
        visible[tag_id] = float(min(1.0, seen / tag_area[tag_id]))
    return visible


def _canvas(width: int, height: int, cfg: RenderConfig, light: Light,
            rows: tuple[int, int]) -> np.ndarray:
    """The car interior's radiance (or a flat grey) over image rows [r0, r1), float32
    (r1 - r0, W, C), writable."""
    channels = 3 if cfg.color else 1
    r0, r1 = rows
    if cfg.background:
        img = (background(width, height, cfg.background_seed, cfg.color)[r0:r1]
               * np.float32(light.background))
    else:
        img = np.full((r1 - r0, width, channels), 0.06 * light.background, np.float32)
    return np.ascontiguousarray(img, dtype=np.float32)


def render_scene(
    model: CapModel, k: np.ndarray, width: int, height: int, T_cam_cap: Transform,
    cfg: RenderConfig, rows: tuple[int, int] | None = None,
) -> tuple[np.ndarray, dict[int, float], list[int]]:
    """Float32 (H, W, C) linear radiance (share of the full well at the lighting's nominal
    exposure) of the ideal pinhole (K, no distortion), before flare and spotlights; visible
    fractions; front-facing ids, far to near.

    ``rows`` = (r0, r1): only image rows r0 <= y < r1, an (r1 - r0, W, C) band (what a rolling
    shutter's sub-step needs: ``synth.shutter``): the pinhole's principal point moves up by r0,
    so the band holds those rows of the whole image; visible fractions are then of the band.
    """
    light = LIGHTS[cfg.lighting]
    r0, r1 = (0, height) if rows is None else (int(rows[0]), int(rows[1]))
    img = _canvas(width, height, cfg, light, (r0, r1))
    if r0:
        k = k.copy()
        k[1, 2] -= r0
    hair_tint = (np.array([0.75, 0.9, 1.15], np.float32) if cfg.color else np.ones(1, np.float32))
    occluders: list[HeadMaps] = []
    if cfg.head:
        # Neck first (the head is in front of it seen from behind), then the head.
        neck = render_head(img, k, T_cam_cap, cfg, light, hair_tint * 1.15, NECK_CENTRE_M,
                           NECK_SEMI_AXES_M, albedo=NECK_ALBEDO)
        head = render_head(img, k, T_cam_cap, cfg, light, hair_tint)
        occluders = [o for o in (neck, head) if o is not None]
    f = _faces(model, T_cam_cap, light)
    id_buf, tag_cov, tag_area = _draw_faces(img, model, k, f, light, occluders, int(cfg.supersample))
    visible = _visible_fractions(model, f.order, id_buf, tag_cov, tag_area)
    return img, visible, [model.ids[i] for i in f.order]
