"""A Cramer-Rao lower bound for tag-corner localisation, against what ``ficap edge`` achieves.

Issue 10 asks corner error median <= 0.15 px; on blender_dev 540p low (and replay's rms_px on 1080p
high) it is missed, and ``bench_corners.py --noise`` says the fit is mostly noise-limited. This puts a
number with a bound on that: for every clean tag our detector returns, the Fisher information of its
8 corner coordinates (plus 2 nuisance levels) under a photometric model of the tag, with per-pixel
noise measured from the frames; its inverse is the smallest covariance any unbiased estimator using
those pixels can reach.

The model (per tag, at the TRUE corners): the printed pattern (OpenCV's tag36h11 drawing, 8x8 cells,
white quiet zone) mapped into the image by the corners' homography, supersampled 8x per pixel axis,
blurred in linear light by the set's Gaussian PSF sigma, integrated over the pixel (box), between a
black and a white linear level, through the set's tone curve (``ficap_ros.tools.synth.tone_curve``:
``srgb``, ``gamma`` 1.8, ``filmic``; clipping at 1 makes f' = 0 there) to 8-bit:

    I(x) = 255 f(Lb + (Lw - Lb) C(x; corners)),  Lb, Lw = f^-1(the tag's flat black / white medians)

(blender_dev's ``filmic`` is taken as synth's S-curve: its render block names the curve only.)

A corner perturbation moves the pattern by a smooth displacement field v(x) (the homography's
derivative), so dC/dtheta = -grad C . v (v is constant over the PSF's support to well under 1 %).
Nuisance parameters (Schur complement): both levels, each as a plane over the tag (shading). Where
the white is clipped (flat median >= 250) its linear level is fitted to the edge pixels (a clipped
edge keeps only its dark part). Per-pixel noise: the sd of neighbouring-pixel differences / sqrt(2)
in the tags' flat areas (model coverage 0 or 1), by grey-level bin, taken to linear light and fitted
with var = a + b L + c L^2 (read, shot, and noise in proportion: a path tracer's few samples), so
grey levels no flat area shows get the same sensor's noise ('noise sd by grey level': measured /
model; the lag-2 / lag-1 variance ratio printed per set is 1 for uncorrelated noise). Pixels used:
every pixel whose centre lies on the tag's 10x10-cell face (tag + quiet zone), not only our sample
lines; noise is taken as independent between pixels.

From each tag's 8x8 corner covariance, 400 Gaussian draws per tag give the corner-error distance
distribution of an efficient unbiased estimator: its median and p95 pooled over tags, beside ours
(``TagDetector().detect``, the corners ``ficap detect --json`` returns) on the same tags. Columns
besides: the bound with the tone curve's exponent unknown too (I = 255 (f/255)^kappa); the bound
from only the pixels our cell-edge fit's sample lines read (bilinear footprints of every profile,
``_cell_edge_samples``); 'model chi2' = mean (observed - model)^2 / sd^2 over the tag's unclipped
edge pixels (1 = the model explains the pixels to the noise; more = what it lacks: geometry, PSF
shape, glare, JPEG); 'misfit as noise' = each tag's bound covariance times its chi2 (not a bound:
what an efficient estimator would reach if the misfit were noise-like).

Also per set the bound on replay's ``rms_px`` for frames whose corners are as good as the bound:
sqrt(mean trace(corner cov) * (1 - 6 / (2 N))) for N corners and a 6-dof pose (the clean tags' part).

``--fit``: also a prototype estimator that uses the pixels as the bound does (``photometric_fit``:
the same model fitted by Gauss-Newton to the face pixels from our corners, with corners, levels,
shading planes and the tone exponent free; the set's tone family and PSF sigma given). Benchmark only:
40-300 ms CPU per tag (540p-1080p), and it needs the tone family and blur, which the detector does not know.

Usage: .venv/bin/python benchmarks/bench_corner_bound.py [--sets a,b] [--no-synth] [--fit] [--record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blender_dev  # noqa: E402
from _common import load_avg, machine_line, md_table, record_section  # noqa: E402
from bench_corners import blender_frames, synth_frames  # noqa: E402

from ficap_ros.geometry.metrics import corner_errors_px  # noqa: E402
from ficap_ros.geometry.tag36h11 import TAG_CELLS, tag_cells, tag_homographies
from ficap_ros.tools.synth import tone_curve  # noqa: E402
from ficap_ros.vision.corners import _FIT_PROFILE_SAMPLES, _cell_edge_samples
from ficap_ros.vision.detector import DetectorConfig, TagDetector

SUPERSAMPLE = 8
#: The sets of the table and the synth condition matching each (resolution, tone, gamma, PSF, lighting).
DEFAULT_SETS = ("dev_540p_low", "dev_1080p_high", "dev_540p_neutral", "dev_1080p_neutral")
_TONES = {"srgb": ("srgb", 2.2), "filmic": ("filmic", 2.2), "gamma18": ("gamma", 1.8)}
DRAWS = 400
#: Bounds computed per tag: every face pixel with the tone curve known; ... with its exponent unknown;
#: only the pixels our fit's sample lines read (tone curve known).
VARIANTS = ("all", "tone", "ours", "misfit")


def _tone(tone: str, gamma: float):  # noqa: ANN202
    """(f, f^-1) on linear [0, 1] <-> 8-bit grey, by a dense table (f is monotone)."""
    lin = np.linspace(0.0, 1.0, 200001)
    enc = 255.0 * tone_curve(lin, tone, gamma)
    return (lambda x: np.interp(x, lin, enc, right=255.0),
            lambda g: np.interp(g, enc, lin))


def _face_pixels(H: np.ndarray, shape: tuple[int, int], margin_px: float):
    """Bounding box of the 10x10-cell face in the image, expanded by margin_px and clipped."""
    face = np.array([[-1, -1, 1], [9, -1, 1], [9, 9, 1], [-1, 9, 1]], float) @ H.T
    xy = face[:, :2] / face[:, 2:]
    x0, y0 = np.floor(xy.min(axis=0) - margin_px).astype(int)
    x1, y1 = np.ceil(xy.max(axis=0) + margin_px).astype(int)
    h, w = shape
    return max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)


def tag_model(image: np.ndarray, corners: np.ndarray, tag_id: int, psf_sigma_px: float):
    """Per-pixel coverage, its gradient and the displacement fields of one tag's face.

    Returns (observed grey (P,), coverage C (P,), dC/dtheta (P, 8), on-face mask (P,) bool,
    flat-pair differences [(level, diff)] for the noise table), or None when off the image."""
    H = tag_homographies(corners[None])[0]
    x0, y0, x1, y1 = _face_pixels(H, image.shape, 3.0 * psf_sigma_px + 2.0)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    s = SUPERSAMPLE
    xs = x0 - 0.5 + (np.arange((x1 - x0 + 1) * s) + 0.5) / s
    ys = y0 - 0.5 + (np.arange((y1 - y0 + 1) * s) + 0.5) / s
    gx, gy = np.meshgrid(xs, ys)
    Hi = np.linalg.inv(H)
    p = np.stack([gx, gy, np.ones_like(gx)], -1) @ Hi.T
    u, v = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    cells = tag_cells(int(tag_id))
    inside = (u >= 0) & (u < TAG_CELLS) & (v >= 0) & (v < TAG_CELLS)
    ui = np.clip(np.floor(u).astype(int), 0, TAG_CELLS - 1)
    vi = np.clip(np.floor(v).astype(int), 0, TAG_CELLS - 1)
    white = np.where(inside & cells[vi, ui], 0.0, 1.0).astype(np.float32)
    # Lens blur in linear light, at the supersampled scale.
    blurred = cv2.GaussianBlur(white, (0, 0), psf_sigma_px * s, borderType=cv2.BORDER_REPLICATE)
    gyy, gxx = np.gradient(blurred.astype(np.float64), 1.0 / s)  # per image px
    hh, ww = (y1 - y0 + 1), (x1 - x0 + 1)

    def box(a: np.ndarray) -> np.ndarray:  # the pixel's area
        return a.reshape(hh, s, ww, s).mean(axis=(1, 3))

    C, Cx, Cy = box(blurred.astype(np.float64)), box(gxx), box(gyy)
    # Pixel centres: cell coordinates and the displacement field of each corner coordinate.
    px, py = np.meshgrid(np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float))
    q = np.stack([px, py, np.ones_like(px)], -1) @ Hi.T
    uv1 = np.stack([q[..., 0] / q[..., 2], q[..., 1] / q[..., 2], np.ones_like(px)], -1)
    on_face = ((uv1[..., 0] >= -1) & (uv1[..., 0] <= TAG_CELLS + 1)
               & (uv1[..., 1] >= -1) & (uv1[..., 1] <= TAG_CELLS + 1))
    step = 1e-4
    dC = np.empty(C.shape + (8,))
    for j in range(8):
        c2 = corners.astype(np.float64).copy()
        c2[j // 2, j % 2] += step
        r = uv1 @ tag_homographies(c2[None])[0].T
        vx = (r[..., 0] / r[..., 2] - px) / step
        vy = (r[..., 1] / r[..., 2] - py) / step
        dC[..., j] = -(Cx * vx + Cy * vy)
    obs = image[y0:y1 + 1, x0:x1 + 1].astype(np.float64)
    # Flat pairs (model coverage exactly 0 or 1 on both, same phase), horizontal and vertical.
    pairs = []
    flat0, flat1 = (C < 1e-4) & on_face, (C > 1 - 1e-4) & on_face
    for fl in (flat0, flat1):
        for a, b, ma, mb in ((obs[:, :-1], obs[:, 1:], fl[:, :-1], fl[:, 1:]),
                             (obs[:-1], obs[1:], fl[:-1], fl[1:])):
            m = ma & mb
            pairs.append(np.column_stack([(a[m] + b[m]) / 2.0, b[m] - a[m], np.ones(m.sum())]))
        # Lag 2 (flat through the middle pixel too): equal spread to lag 1 = uncorrelated noise.
        m = fl[:, :-2] & fl[:, 1:-1] & fl[:, 2:]
        a, b = obs[:, :-2][m], obs[:, 2:][m]
        pairs.append(np.column_stack([(a + b) / 2.0, b - a, np.full(m.sum(), 2.0)]))
    return (obs.ravel(), C.ravel(), dC.reshape(-1, 8), on_face.ravel(), np.concatenate(pairs),
            _our_pixels(H, tag_id, (x0, y0, x1, y1)).ravel(), uv1[..., :2].reshape(-1, 2) - 4.0)


def _our_pixels(H: np.ndarray, tag_id: int, box: tuple[int, int, int, int]) -> np.ndarray:
    """Mask of the pixels ``fit_tag_edges``' sample lines read (bilinear footprint of every profile
    sample of every cell boundary, at the true corners, before any contrast gate)."""
    x0, y0, x1, y1 = box
    uv, nu = _cell_edge_samples(int(tag_id))
    uvh = np.column_stack([uv, np.ones(len(uv))])
    p = uvh @ H.T
    den = p[:, 2]
    px, py = p[:, 0] / den, p[:, 1] / den
    j11, j12 = (H[0, 0] - H[2, 0] * px) / den, (H[0, 1] - H[2, 1] * px) / den
    j21, j22 = (H[1, 0] - H[2, 0] * py) / den, (H[1, 1] - H[2, 1] * py) / den
    det = j11 * j22 - j12 * j21
    gx, gy = (j22 * nu[:, 0] - j21 * nu[:, 1]) / det, (-j12 * nu[:, 0] + j11 * nu[:, 1]) / det
    gn = np.hypot(gx, gy)
    half = np.minimum(DetectorConfig().edge_search_px, 0.5 / gn)
    k = (_FIT_PROFILE_SAMPLES - 1) // 2
    t = np.arange(-k, k + 1) / k
    sx = px[:, None] + (gx / gn * half)[:, None] * t
    sy = py[:, None] + (gy / gn * half)[:, None] * t
    mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), bool)
    for ox in (0, 1):
        for oy in (0, 1):
            xi = np.floor(sx).astype(int) + ox - x0
            yi = np.floor(sy).astype(int) + oy - y0
            ok = (xi >= 0) & (xi <= x1 - x0) & (yi >= 0) & (yi <= y1 - y0)
            mask[yi[ok], xi[ok]] = True
    return mask


def noise_table(pairs: np.ndarray, f, finv, min_n: int = 200):  # noqa: ANN001
    """Level-dependent per-pixel noise sd.

    The robust sd of neighbouring-pixel differences / sqrt(2) in flat areas, by grey-level bin
    (unclipped bins only); each bin taken back to linear light through the tone curve's slope and
    fitted with var_linear = a + b L + c L^2 (read, shot, and noise in proportion to the light: a
    path tracer's few samples per pixel), non-negative, on relative errors, so levels no flat area shows (a clipped
    white's edge runs from the black level to 255 through grey levels no flat area has) get the
    noise of the same sensor. Returns (bin levels, bin sds, sd(grey) function)."""
    lev, d = pairs[:, 0], pairs[:, 1]
    order = np.argsort(lev)
    lev, d = lev[order], d[order]
    centres, sds = [], []
    for chunk in np.array_split(np.arange(len(lev)), max(1, len(lev) // max(min_n, len(lev) // 24))):
        if len(chunk) < 20:
            continue
        dd = d[chunk]
        centres.append(float(np.median(lev[chunk])))
        # A plain sd (8-bit differences of sd ~1 make a MAD useless), edges and specks trimmed.
        dd = dd - np.median(dd)
        dd = dd[np.abs(dd) <= max(6.0 * 1.4826 * np.median(np.abs(dd)), 4.0)]
        sds.append(max(float(np.std(dd)) / np.sqrt(2.0), 0.3))
    c, sd = np.array(centres), np.array(sds)
    ok = c < 250.0
    eps = 1e-4

    def slope(g: np.ndarray) -> np.ndarray:
        L = finv(g)
        return (f(L + eps) - f(L - eps)) / (2 * eps)

    L = finv(c[ok])
    var_lin = (sd[ok] / np.maximum(slope(c[ok]), 1e-9)) ** 2
    from scipy.optimize import nnls

    A = np.column_stack([np.ones_like(L), L, L * L])
    a, b, c2 = nnls(A / var_lin[:, None], np.ones_like(L))[0]  # relative errors

    def sd_of(g: np.ndarray) -> np.ndarray:
        g = np.asarray(g, dtype=np.float64)
        Lg = finv(np.minimum(g, 254.9))
        return np.sqrt((slope(np.minimum(g, 254.9)) ** 2) * (a + b * Lg + c2 * Lg * Lg) + 1.0 / 12.0)  # + 8-bit rounding

    return c, sd, sd_of


def bound_for(frames, psf_sigma_px: float, tone: str, gamma: float, seed: int = 0, fit: bool = False) -> dict:
    """Our corners, the bound's, and the model's check over every clean tag ours returns; with
    ``fit``, also ``photometric_fit`` from our corners (noise model from the flat areas at our
    corners: the fit sees no truth)."""
    f, finv = _tone(tone, gamma)
    eps = 1e-4
    tags, pairs, ours, ours_pairs, fit_jobs = [], [], [], [], []
    for image, truth, clean in frames:
        found = {d.tag_id: d.corners_px for d in TagDetector().detect(image) if d.tag_id in clean}
        for tid, est in found.items():
            if fit:
                mo = tag_model(image, np.asarray(est, float), tid, psf_sigma_px)
                if mo is not None:
                    ours_pairs.append(mo[4])
                fit_jobs.append((image, tid, np.asarray(est, float), np.asarray(truth[tid], float)))
            m = tag_model(image, np.asarray(truth[tid], float), tid, psf_sigma_px)
            if m is None:
                continue
            obs, C, dC, on_face, pr, mine, uv = m
            black = obs[(C < 1e-4) & on_face]
            white = obs[(C > 1 - 1e-4) & on_face]
            if black.size < 4 or white.size < 4:
                continue
            gw = float(np.median(white))
            tags.append([obs, C, dC, on_face, mine, finv(float(np.median(black))), finv(gw), gw >= 250.0, uv])
            pairs.append(pr)
            ours.append(np.linalg.norm(np.asarray(est) - np.asarray(truth[tid]), axis=1))
    pairs = np.concatenate(pairs)
    lag2 = pairs[:, 2] == 2.0
    levels, sds, sd_of = noise_table(pairs[~lag2], f, finv)
    spread = []
    for sel in (~lag2, lag2):
        dd = pairs[sel, 1] - np.median(pairs[sel, 1])
        spread.append(np.var(dd[np.abs(dd) <= max(6.0 * 1.4826 * np.median(np.abs(dd)), 4.0)]))
    lag_ratio = spread[1] / max(spread[0], 1e-9)
    # Clipped whites: the flat areas read 255 whatever the light, so the white level in linear light
    # is only bounded below there; take it from the edges (least squares over a grid), since the
    # share of each edge lost to the clip is what limits those tags.
    n_clipped, fitted_white = 0, []
    for t in tags:
        obs, C, on_face, Lb = t[0], t[1], t[3], t[5]
        if not t[7]:
            continue
        edge = on_face & (C > 0.02) & (C < 0.98) & (obs < 250.0)
        grid = np.geomspace(1.0, 16.0, 60)
        cost = [np.sum((obs[edge] - f(Lb + (lw - Lb) * C[edge])) ** 2) for lw in grid]
        t[6] = float(grid[int(np.argmin(cost))])
        fitted_white.append(t[6])
        n_clipped += 1
    if fitted_white:
        print(f"  clipped whites: {n_clipped} tags, fitted linear white median {np.median(fitted_white):.2f} "
              f"(p10 {np.percentile(fitted_white, 10):.2f}, p90 {np.percentile(fitted_white, 90):.2f})", flush=True)
    print(f"  noise lag-2 / lag-1 variance ratio {lag_ratio:.2f}", flush=True)
    fit_out = {}
    if fit:
        op = np.concatenate(ours_pairs)
        sd_fit = noise_table(op[op[:, 2] == 1.0], f, finv)[2]
        fe, fr, oe = [], [], []
        for image, tid, est, true in fit_jobs:
            c = photometric_fit(image, est, tid, psf_sigma_px, f, sd_fit)
            c = est if c is None else c
            e, r = corner_errors_px(c[None], true[None])
            fe.append(e.ravel())
            fr.append(r.ravel())
            oe.append(corner_errors_px(est[None], true[None])[1].ravel())
        fe, fr = np.concatenate(fe), np.concatenate(fr)
        fit_out = {"fit_med": float(np.median(fe)), "fit_p95": float(np.percentile(fe, 95)),
                   "fit_radial": float(fr.mean()), "ours_radial": float(np.concatenate(oe).mean())}
    rng = np.random.default_rng(seed)
    dist = {k: [] for k in VARIANTS}
    traces, chi2 = [], []
    for obs, C, dC, on_face, mine, Lb, Lw, _clipped, uv in tags:
        L = Lb + (Lw - Lb) * C
        model = f(L)
        fp = (f(L + eps) - f(L - eps)) / (2 * eps)  # 8-bit per unit linear light; 0 where clipped
        # Corners, the two levels, and the tone curve's exponent about the true curve
        # (I = 255 (f / 255) ** kappa, kappa = 1): d I / d kappa = I ln(I / 255).
        tone_col = model * np.log(np.clip(model, 0.5, 255.0) / 255.0)
        # Levels as planes over the tag (shading): a gradient of each level along tag x and y,
        # as relative changes of the linear level (nuisance, like the levels themselves).
        shade = np.column_stack([fp * (1 - C) * Lb * uv[:, 0], fp * (1 - C) * Lb * uv[:, 1],
                                 fp * C * Lw * uv[:, 0], fp * C * Lw * uv[:, 1]])
        J = np.column_stack([fp[:, None] * (Lw - Lb) * dC, fp * (1 - C), fp * C, shade, tone_col])
        wt = 1.0 / sd_of(model) ** 2
        covs = {}
        for key, (mask, cols) in {"all": (on_face, 14), "tone": (on_face, 15), "ours": (on_face & mine, 14)}.items():
            Jm = J[mask][:, :cols]
            F = Jm.T @ (Jm * wt[mask][:, None])
            try:
                cov = np.linalg.inv(F)[:8, :8]
            except np.linalg.LinAlgError:
                break
            covs[key] = 0.5 * (cov + cov.T)
        if len(covs) < 3:
            continue
        edge = on_face & (C > 0.02) & (C < 0.98) & (model < 250.0)  # sd is ~0 in the clip: left out
        tag_chi2 = float(np.mean((obs[edge] - model[edge]) ** 2 / sd_of(model[edge]) ** 2)) if edge.any() else 1.0
        chi2.append(tag_chi2)
        # What the model does not explain (geometry, PSF shape, glare, JPEG) counted as noise: not
        # a bound, the figure an efficient estimator would reach if the misfit were noise-like.
        covs["misfit"] = covs["all"] * max(tag_chi2, 1.0)
        for key, cov in covs.items():
            e = rng.multivariate_normal(np.zeros(8), cov, size=DRAWS).reshape(DRAWS, 4, 2)
            dist[key].append(np.linalg.norm(e, axis=2).ravel())
        traces.append(np.trace(covs["all"]) / 4.0)  # per corner: var x + var y
    dist = {k: np.concatenate(v) for k, v in dist.items()}
    ours = np.concatenate(ours)
    n_corners = 4 * len(tags) / max(len(frames), 1)
    rms_bound = np.sqrt(np.mean(traces) * max(1.0 - 6.0 / (2.0 * n_corners), 0.0))
    return fit_out | {"tags": len(tags), "ours_med": float(np.median(ours)), "ours_p95": float(np.percentile(ours, 95)),
            "crb_med": float(np.median(dist["all"])), "crb_p95": float(np.percentile(dist["all"], 95)),
            "tone_med": float(np.median(dist["tone"])), "ours_px_med": float(np.median(dist["ours"])),
            "misfit_med": float(np.median(dist["misfit"])), "misfit_p95": float(np.percentile(dist["misfit"], 95)),
            "chi2": float(np.median(chi2)), "lag_ratio": float(lag_ratio), "clipped": n_clipped, "rms_bound": float(rms_bound),
            "noise": ", ".join(f"{g:.0f}: {m:.1f} / {sd_of(np.array([g]))[0]:.1f}"
                               for g, m in zip(levels[::max(1, len(levels) // 4)], sds[::max(1, len(sds) // 4)]))}


def photometric_fit(image: np.ndarray, start: np.ndarray, tag_id: int, psf_sigma_px: float, f, sd_of,  # noqa: ANN001
                    iterations: int = 4) -> np.ndarray | None:
    """Prototype (benchmark only): the bound's own model fitted to a tag's face pixels by weighted
    Gauss-Newton from ``start`` (our corners): corners, both levels as planes (shading), and the
    tone curve's exponent about the set's curve; pixels more than 4 sd off the model are dropped
    (glare specks). Whether an estimator that uses the pixels as the bound does gets near it."""
    c = np.asarray(start, dtype=np.float64).copy()
    eps = 1e-4
    lin = np.linspace(0.0, 1.0, 200001)
    enc = f(lin)
    theta = None
    for _ in range(iterations):
        m = tag_model(image, c, tag_id, psf_sigma_px)
        if m is None:
            return None
        obs, C, dC, on_face, _pr, _mine, uv = m
        if theta is None:  # levels (linear) from the flat areas at the start
            gb = np.median(obs[(C < 1e-4) & on_face]) if np.any((C < 1e-4) & on_face) else 30.0
            gw = np.median(obs[(C > 1 - 1e-4) & on_face]) if np.any((C > 1 - 1e-4) & on_face) else 200.0
            theta = np.array([np.interp(gb, enc, lin), max(np.interp(gw, enc, lin), 1.2 if gw >= 250 else 0.0),
                              0, 0, 0, 0, 1.0])
        theta[6] = np.clip(theta[6], 0.5, 2.0)  # the exponent stays a tone curve near the family's
        Lb, Lw, sb1, sb2, sw1, sw2, kappa = theta
        lb = Lb * (1 + sb1 * uv[:, 0] + sb2 * uv[:, 1])
        lw = Lw * (1 + sw1 * uv[:, 0] + sw2 * uv[:, 1])
        L = lb + (lw - lb) * C
        g = f(L)
        model = 255.0 * (np.maximum(g, 1e-6) / 255.0) ** kappa
        fp = (f(L + eps) - f(L - eps)) / (2 * eps) * kappa * (np.maximum(g, 0.5) / 255.0) ** (kappa - 1.0)
        J = np.column_stack([fp[:, None] * (lw - lb)[:, None] * dC, fp * (1 - C), fp * C,
                             fp * (1 - C) * Lb * uv[:, 0], fp * (1 - C) * Lb * uv[:, 1],
                             fp * C * Lw * uv[:, 0], fp * C * Lw * uv[:, 1],
                             model * np.log(np.clip(g, 0.5, 255.0) / 255.0)])
        # Level columns are d/dLb, d/dLw at fixed relative shading; shading columns d/d(relative slope).
        J[:, 8] = fp * (1 - C) * (1 + sb1 * uv[:, 0] + sb2 * uv[:, 1])
        J[:, 9] = fp * C * (1 + sw1 * uv[:, 0] + sw2 * uv[:, 1])
        sd = sd_of(model)
        r = obs - model
        use = on_face & (np.abs(r) <= 4.0 * sd)
        w = 1.0 / sd[use] ** 2
        Ju = J[use]
        A = Ju.T @ (Ju * w[:, None])
        d = np.sqrt(np.maximum(np.diag(A), 1e-30))
        try:
            step = np.linalg.solve(A / d[:, None] / d[None, :], (Ju.T @ (r[use] * w)) / d) / d
        except np.linalg.LinAlgError:
            return None
        c = c + step[:8].reshape(4, 2)
        theta = theta + np.concatenate([step[8:10], step[10:14] / np.array([1, 1, 1, 1]), step[14:]])
        if np.abs(step[:8]).max() > 3.0:
            return None
    return c


def _row(label: str, psf: float, tone: str, r: dict) -> list[str]:
    return [label, f"{psf:.2f}", tone, str(r["tags"]), f"{r['ours_med']:.3f}", f"{r['ours_p95']:.3f}",
            f"{r['crb_med']:.3f}", f"{r['crb_p95']:.3f}", f"{r['ours_med'] / r['crb_med']:.2f}",
            f"{r['tone_med']:.3f}", f"{r['ours_px_med']:.3f}", f"{r['misfit_med']:.3f} / {r['misfit_p95']:.3f}",
            f"{r['chi2']:.2f}", f"{r['rms_bound']:.3f}", r["noise"]] + (
            [f"{r['fit_med']:.3f} / {r['fit_p95']:.3f} / {r['fit_radial']:+.3f} (ours {r['ours_radial']:+.3f})"]
            if "fit_med" in r else [])


HEADER = ["frames", "PSF px", "tone", "tags", "ours median px", "ours p95 px", "bound median px",
          "bound p95 px", "ours / bound (median)",
          "bound median, tone exponent unknown", "bound median, our lines' pixels only",
          "misfit as noise: median / p95 px", "model chi2", "rms_px bound", "noise sd by grey level: measured / model"]

READING = """Reading it: the bound is far below issue 10's targets on every set: blender_dev 540p low
median / p95 0.056 / 0.135 px against ours 0.170 / 0.488 (target 0.15 / 0.5), 1080p high 0.022 / 0.050
against 0.143 / 0.351, and the rms_px bound on 1080p high 0.027 px against replay's 0.237 (target 0.2).
Counting all the model's misfit as noise (chi2 2.35 on 540p low, 7.3 on 1080p high) still gives 0.084 /
0.210 and 0.059 / 0.139 px. So the misses are the estimator's, not the noise's. The pixels our sample lines
read hold nearly all the information (the bound from them alone: 0.058 vs 0.056 px on 540p low, 0.027 vs
0.022 on 1080p high), and the tone curve's exponent costs none (0.057): what is lost is in how each line
turns its pixels into an offset. The prototype (`photometric_fit`, given the set's tone family and PSF)
reaches the bound on synth 540p srgb low (0.043 vs 0.047 px) and takes blender_dev 540p low to 0.120 /
0.297 px; it is a benchmark, not the detector (see docs/detection.md "How far the noise lets corners go").
Where the model explains little (chi2 5-26: the low-noise neutral sets and synth 1080p high, where noise sd
is 1-3 grey levels and geometry, blur shape and JPEG dominate the residual), the bound is loose and the
misfit column is the better guide. blender_dev's filmic is taken as synth's S-curve (its render block names
the curve only); the lag-2 / lag-1 ratio of 2.7 on 1080p neutral says its flat areas carry shading or
correlated noise, which the neighbour differences do not see.
'tags': the clean tags ours returns that show flat black and white pixels (tags too small for a
flat cell drop out: 540p neutral 337 of 362, so its 'ours' differs from 'Corners on blender_dev')."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default=",".join(DEFAULT_SETS))
    ap.add_argument("--no-synth", action="store_true", help="blender_dev only")
    ap.add_argument("--fit", action="store_true",
                    help="also the photometric fit prototype from our corners (photometric_fit)")
    ap.add_argument("--record", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t0, rows = time.time(), []
    for name in [x for x in args.sets.split(",") if x]:
        s = blender_dev.load_set(name)
        tone, gamma = _TONES[s.tone]
        rows.append(_row(f"blender_dev {name}", s.psf_sigma_px, s.tone,
                         bound_for(blender_frames(name), s.psf_sigma_px, tone, gamma, fit=args.fit)))
        print(" | ".join(rows[-1]), flush=True)
        if not args.no_synth:
            res = "1080p" if "1080p" in name else "540p"
            r = bound_for(synth_frames(res, tone, gamma, s.psf_sigma_px, s.lighting), s.psf_sigma_px, tone, gamma,
                          fit=args.fit)
            rows.append(_row(f"synth {res} {s.tone} {s.lighting}", s.psf_sigma_px, s.tone, r))
            print(" | ".join(rows[-1]), flush=True)
    table = md_table(HEADER + (["photometric fit (prototype): median / p95 / mean radial px"] if args.fit else []),
                     rows)
    print(table)
    if args.record:
        body = (f"Machine: {machine_line()}; {load_avg()}; {time.time() - t0:.0f} s. "
                f"`benchmarks/bench_corner_bound.py{' --fit' if args.fit else ''} --record` (see its docstring): "
                "per clean tag that "
                "`ficap edge` returns, the Cramer-Rao bound of its 8 corner coordinates from every pixel "
                "of the tag and its quiet zone (photometric model at the true corners: pattern, PSF in "
                "linear light, pixel area, tone curve, the tag's flat levels; noise sd by grey level "
                "from neighbouring-pixel differences in the flat areas); 'bound' = the corner-error "
                "distance of an efficient unbiased estimator (400 draws per tag); synth rows: 6 "
                "`ficap synth` frames at the set's resolution, tone curve, PSF and lighting"
                + ("; last column: the photometric fit prototype from our corners (`photometric_fit`), with "
                   "the mean radial offset, ours beside it" if args.fit else "") + ".\n\n"
                + table + "\n\n" + READING)
        record_section("Corner error bound (Cramer-Rao)", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
