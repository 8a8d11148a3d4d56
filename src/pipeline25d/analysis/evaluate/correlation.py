"""One window: masked normalised cross-correlation for the integer shift, then a Gauss-Newton sub-pixel fit."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)




_SPLINE_ORDER = 5             # B-spline interpolation of the oblique window (quintic: little sub-pixel bias)


_ERODE_PX = 3                 # fitted oblique pixels lie this far inside its usable area (spline support)


_INTERP_MARGIN = _ERODE_PX    # oblique pixels read beyond the search range, for interpolation


_MIN_FIT_PX = 64              # fewer usable pixels than this after erosion: window fails


_LK_TOL_PX = 1e-3             # Gauss-Newton stops when the shift update is below this


_LK_MAX_ITER = 10


_FD_PX = 1e-3                 # step of the central differences of the spline interpolant


@dataclass
class WindowFit:
    """One window's registration (see :func:`measure_window`)."""

    d_col: float                  # oblique content sits at the nadir content's position + (d_col, d_row)
    d_row: float
    ncc: float                    # aligned usable pixels, -1..1 (NaN if not fitted)
    peak_ratio: float             # second / first local maximum of the masked NCC surface
    condition: float              # of the 2x2 shift normal matrix (inf: singular)
    sigma_px: float               # formal standard error of the shift (NaN if not fitted)
    n_px: int                     # pixels in the least-squares fit
    reason: str                   # '' or one of FAIL_REASONS (only the geometric ones set here)


def masked_ncc_surface(ref: np.ndarray, ref_ok: np.ndarray, mov: np.ndarray, mov_ok: np.ndarray,
                       min_overlap: float = 0.5) -> np.ndarray:
    """Masked normalised cross-correlation (Padfield 2012) of an n×n ``ref`` inside an
    (n+2m)×(n+2m) ``mov`` at every integer shift s in [−m, m]²: out[m + s_row, m + s_col] is the
    Pearson correlation of ref(x) with mov(x + m + s) over the x usable in both (``ref_ok``,
    ``mov_ok``); −inf where fewer than ``min_overlap`` × the largest overlap are usable, or no
    texture. Only usable pixels enter: nothing is zero-filled and correlated.
    """
    n, big = ref.shape[0], mov.shape[0]
    a_ok, b_ok = ref_ok.astype(np.float64), mov_ok.astype(np.float64)
    a = np.where(ref_ok, ref - ref[ref_ok].mean(), 0.0) if ref_ok.any() else np.zeros_like(ref)
    b = np.where(mov_ok, mov - mov[mov_ok].mean(), 0.0) if mov_ok.any() else np.zeros_like(mov)
    fa = [np.conj(np.fft.rfft2(v, (big, big))) for v in (a_ok, a, a * a)]
    fb = [np.fft.rfft2(v) for v in (b_ok, b, b * b)]

    def corr(i: int, j: int) -> np.ndarray:          # sum_x A_j(x) B_i(x + s), no wrap-around for s in [0, 2m]
        return np.fft.irfft2(fb[i] * fa[j], (big, big))[:big - n + 1, :big - n + 1]

    count = np.rint(corr(0, 0))
    valid = count >= max(min_overlap * count.max(), 1.0)
    count = np.where(valid, count, 1.0)
    sa, sb, saa, sbb, sab = corr(0, 1), corr(1, 0), corr(0, 2), corr(2, 0), corr(1, 1)
    num = sab - sa * sb / count
    den = np.maximum(saa - sa * sa / count, 0.0) * np.maximum(sbb - sb * sb / count, 0.0)
    valid &= den > 1e-9 * max(float(den[valid].max()) if valid.any() else 0.0, 1e-300)
    out = np.full(count.shape, -np.inf)
    out[valid] = np.minimum(num[valid] / np.sqrt(den[valid]), 1.0)
    return out


def _second_peak_ratio(surface: np.ndarray, peak: tuple[int, int]) -> float:
    """Highest local maximum other than ``peak`` / the value at ``peak`` (1 if the peak is not > 0)."""
    from scipy import ndimage

    p1 = surface[peak]
    if not p1 > 0:
        return 1.0
    s = np.where(np.isfinite(surface), surface, -np.inf)
    local = (s == ndimage.maximum_filter(s, size=3, mode="constant", cval=-np.inf)) & np.isfinite(s)
    local[peak] = False
    if not local.any():
        return 0.0
    return float(max(s[local].max(), 0.0) / p1)


def _schur_shift(hess: np.ndarray) -> np.ndarray:
    """The 2x2 shift block of a 4x4 normal matrix with gain and offset eliminated."""
    hss, hsg, hgg = hess[:2, :2], hess[:2, 2:], hess[2:, 2:]
    return hss - hsg @ np.linalg.solve(hgg, hsg.T)


def measure_window(nadir_grey: np.ndarray, nadir_ok: np.ndarray, oblique_grey: np.ndarray, oblique_ok: np.ndarray,
                   search_px: int, max_condition: float = 25.0, min_ncc: float = 0.5) -> WindowFit:
    """Offset of the oblique map's content relative to the nadir window, from usable pixels only.

    ``nadir_grey``/``nadir_ok``: an n×n window and its usable pixels; ``oblique_grey``/
    ``oblique_ok``: the same map cells with a border of ``search_px`` + 3 pixels on every side.
    Integer shift: the peak of :func:`masked_ncc_surface` within ±``search_px`` (a peak on the
    border of that range fails as 'shift_too_large'; a peak below ``min_ncc``/2 fails as
    'low_correlation' at once). Sub-pixel: Gauss–Newton on ``oblique(x + s) = gain·nadir(x) +
    offset`` over the nadir-usable pixels x whose oblique position lies at least 3 px inside the
    oblique's usable area, with quintic B-spline interpolation of the oblique (its unusable pixels
    filled from the nearest usable one, never zero) and the interpolant's own derivatives, until
    the shift update < 1e-3 px (re-choosing the pixels if the shift moves by more than 1 px).
    Fails 'ill_conditioned' when the shift normal matrix (gain/offset eliminated) has condition
    number > ``max_condition`` (texture in one direction only), 'too_few_pixels' with < 64 pixels
    to fit, 'no_convergence' after 10 iterations. Thresholds on the shift's length, the aligned
    NCC and the peak ratio are the caller's (see :func:`ground_offsets`).
    """
    from scipy import ndimage

    n = nadir_grey.shape[0]
    m = search_px
    margin = (oblique_grey.shape[0] - n) // 2
    if margin < m + _ERODE_PX or oblique_grey.shape[0] != n + 2 * margin:
        raise ValueError("oblique block must be the window plus search_px + 3 (or more) on every side")
    crop = slice(margin - m, margin + n + m)
    surface = masked_ncc_surface(nadir_grey, nadir_ok, oblique_grey[crop, crop], oblique_ok[crop, crop])
    if not np.isfinite(surface).any():
        return WindowFit(0.0, 0.0, float("nan"), 1.0, float("inf"), float("nan"), 0, "too_few_pixels")
    peak = np.unravel_index(int(np.argmax(surface)), surface.shape)
    ratio = _second_peak_ratio(surface, peak)
    s0 = np.array(peak, dtype=float) - m                   # (row, col)
    if surface[peak] < min_ncc / 2:                        # hopeless: even half a pixel off would do better
        return WindowFit(s0[1], s0[0], float(surface[peak]), ratio, float("nan"), float("nan"), 0,
                         "low_correlation")

    # fill unusable oblique pixels from the nearest usable one (no zero steps for the spline to ring on)
    idx = ndimage.distance_transform_edt(~oblique_ok, return_distances=False, return_indices=True)
    filled = oblique_grey[tuple(idx)]
    coef = ndimage.spline_filter(filled, order=_SPLINE_ORDER, mode="mirror")
    inside = ndimage.binary_erosion(oblique_ok, structure=np.ones((3, 3), bool), iterations=_ERODE_PX)
    rows, cols = np.nonzero(nadir_ok)

    def sample(rr, cc):
        return ndimage.map_coordinates(coef, [rr, cc], order=_SPLINE_ORDER, mode="mirror", prefilter=False)

    s = s0.copy()
    fit = None
    for _ in range(2):                                     # second round only if s left s0's pixel set
        base = np.rint(s).astype(int)
        pr, pc = rows + margin + base[0], cols + margin + base[1]
        keep = (pr >= 0) & (pr < inside.shape[0]) & (pc >= 0) & (pc < inside.shape[1])
        keep[keep] = inside[pr[keep], pc[keep]]
        r, c = rows[keep] + margin, cols[keep] + margin
        ref = nadir_grey[rows[keep], cols[keep]]
        if len(ref) < _MIN_FIT_PX:
            return WindowFit(s[1], s[0], float("nan"), ratio, float("inf"), float("nan"), int(len(ref)),
                             "too_few_pixels")
        warped = sample(r + s[0], c + s[1])
        # least-squares line warped ≈ gain·ref + offset (closed form: no RankWarning on flat windows)
        var = float(ref.var())
        gain = float(((ref - ref.mean()) * (warped - warped.mean())).mean() / var) if var > 1e-12 else 1.0
        offset = float(warped.mean() - gain * ref.mean())
        converged = False
        for it in range(_LK_MAX_ITER):
            # derivatives of the spline interpolant itself (exact Jacobian: quadratic convergence)
            jr = (sample(r + s[0] + _FD_PX, c + s[1]) - sample(r + s[0] - _FD_PX, c + s[1])) / (2 * _FD_PX)
            jc = (sample(r + s[0], c + s[1] + _FD_PX) - sample(r + s[0], c + s[1] - _FD_PX)) / (2 * _FD_PX)
            resid = warped - gain * ref - offset
            jac = np.column_stack([jr, jc, -ref, -np.ones_like(ref)])
            hess = jac.T @ jac
            if it == 0:
                try:
                    ev = np.linalg.eigvalsh(_schur_shift(hess))
                except np.linalg.LinAlgError:
                    ev = np.zeros(2)
                cond = float(ev[1] / ev[0]) if ev[0] > 1e-12 * max(ev[1], 1e-300) else float("inf")
                if cond > max_condition:
                    return WindowFit(s[1], s[0], float("nan"), ratio, cond, float("nan"), int(len(ref)),
                                     "ill_conditioned")
            step = np.linalg.solve(hess, -(jac.T @ resid))
            s += step[:2]
            gain += step[2]
            offset += step[3]
            warped = sample(r + s[0], c + s[1])
            if np.hypot(step[0], step[1]) < _LK_TOL_PX:
                converged = True
                break
            if np.abs(s).max() > m + 1:                   # wandered off: the integer peak was wrong
                break
        fit = (r, c, ref, warped, gain, offset, hess, converged, cond)
        if np.abs(s - base).max() <= 1 or not converged:
            break
    r, c, ref, warped, gain, offset, hess, converged, cond = fit
    resid = warped - gain * ref - offset
    try:
        cov = np.linalg.inv(_schur_shift(hess)) * float(resid @ resid) / max(len(ref) - 4, 1)
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(cov)[1], 0.0)))
    except np.linalg.LinAlgError:
        sigma = float("nan")
    ncc = float(np.corrcoef(ref, warped)[0, 1]) if ref.std() > 0 and warped.std() > 0 else float("nan")
    reason = "" if converged else "no_convergence"
    if not reason and max(abs(peak[0] - m), abs(peak[1] - m)) >= m:
        reason = "shift_too_large"                          # integer peak on the border of the search range
    return WindowFit(float(s[1]), float(s[0]), ncc, ratio, cond, sigma, int(len(ref)), reason)
