"""The pre-fusion point filter (:func:`dm2.fusion.point_filter.line_outliers`) stated plainly:
whole-array numpy per candidate run, the line fitted by the covariance's eigenvectors
(``np.linalg.eigh``) rather than the kernel's closed-form angle. The decisions must agree."""

from __future__ import annotations

import numpy as np

from dm2.fusion.point_filter import BURST, GAP_SLACK, SIDE, SINGLE


def _fit(p):
    """Centroid (2,) and unit normal (2,) of the total-least-squares line through ``p``."""
    c = p.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((p - c).T, bias=True))
    return c, vecs[:, 0]  # the direction of least spread


def _run_is_off(xz, i, r, a, b, reject_mm, agree_mm, max_step_mm):
    lo, hi = i - SIDE, i + r + SIDE
    if lo < a or hi > b:
        return False
    if abs(xz[i + r, 0] - xz[i - 1, 0]) > max_step_mm * (r + 1):
        return False
    left, right = np.arange(lo, i), np.arange(i + r, hi)
    if (np.abs(np.diff(xz[left, 0])) > max_step_mm).any() or \
            (np.abs(np.diff(xz[right, 0])) > max_step_mm).any():
        return False
    anchors = np.concatenate([left, right])
    use = np.ones(anchors.size, bool)
    for _attempt in range(2):
        c, n = _fit(xz[anchors[use]])
        resid = np.where(use, np.abs((xz[anchors] - c) @ n), -1.0)
        worst = int(np.argmax(resid))
        if resid[worst] <= agree_mm:
            along = np.array([n[1], -n[0]])
            pairs = [(s, t) for s, t in zip(anchors[:-1], anchors[1:], strict=True)
                     if t == s + 1 and use[anchors == s][0] and use[anchors == t][0]]
            if not pairs:
                return False
            step = np.mean([abs((xz[t] - xz[s]) @ along) for s, t in pairs])
            gap = abs((xz[i + r] - xz[i - 1]) @ along)
            if gap > GAP_SLACK * (r + 1) * step + 0.5 * agree_mm:
                return False
            return bool(np.all(np.abs((xz[i:i + r] - c) @ n) > reject_mm))
        if anchors[worst] in (i - 1, i + r):
            return False
        use[worst] = False
    return False


def line_outliers_numpy(xz_S, offsets, reject_mm, agree_mm, max_step_mm, max_run):
    """The reasons (n,) int8 that :func:`dm2.fusion.point_filter.line_outliers` gives."""
    xz = np.asarray(xz_S, dtype=np.float64)
    out = np.zeros(xz.shape[0], dtype=np.int8)
    jump = np.linalg.norm(np.diff(xz, axis=0), axis=1)  # jump[q]: point q to q + 1
    thr = reject_mm - 0.5 * agree_mm

    def chord(j, k, p):
        d = xz[k] - xz[j]
        norm = np.linalg.norm(d)
        e = xz[p] - xz[j]
        return 0.0 if norm == 0 else abs(d[0] * e[1] - d[1] * e[0]) / norm

    for a, b in zip(offsets[:-1], offsets[1:], strict=True):
        i = a + SIDE
        while i < b - SIDE:
            found = 0
            if jump[i - 1] > thr:
                for r in range(1, max_run + 1):
                    if i + r + SIDE > b:
                        break
                    if jump[i + r - 1] > thr and chord(i - 1, i + r, i) > thr and \
                            _run_is_off(xz, i, r, a, b, reject_mm, agree_mm, max_step_mm):
                        found = r
                        break
            if found:
                out[i:i + found] = SINGLE if found == 1 else BURST
                i += found
            else:
                i += 1
    return out
