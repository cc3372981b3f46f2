"""Lewiner's marching-cubes case logic, as scikit-image runs it: the face and interior tests
that resolve a cube's ambiguities and the choice of tiling (its "big switch"), on the tables of
:mod:`dm2.fusion.marching_cubes_luts`. Used by :mod:`dm2.fusion.marching_cubes`.

A cube's values ``v[0..7]`` are in skimage's corner order: ``v0 (x, y, z)``, ``v1 (x+1, y, z)``,
``v2 (x+1, y+1, z)``, ``v3 (x, y+1, z)``, then ``v4..v7`` the same at ``z+1`` (x is the volume's
last axis).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion import marching_cubes_luts as L

FLT_EPSILON = float(np.spacing(1.0))


@njit(cache=True, nogil=True, inline="always")
def get(t, i0, i1, i2):
    """Entry ``(i0, i1, i2)`` of table ``t`` (see :mod:`dm2.fusion.marching_cubes_luts`)."""
    return L.LUT[L.LUT_OFF[t] + i0 * L.LUT_S1[t] + i1 * L.LUT_S2[t] + i2]


@njit(cache=True, nogil=True)
def _test_face(v, face):
    """Lewiner's face test on face ``face`` (signed, 1..6) of the cube values ``v``."""
    af = face if face >= 0 else -face
    if af == 1:
        a, b, c, d = v[0], v[4], v[5], v[1]
    elif af == 2:
        a, b, c, d = v[1], v[5], v[6], v[2]
    elif af == 3:
        a, b, c, d = v[2], v[6], v[7], v[3]
    elif af == 4:
        a, b, c, d = v[3], v[7], v[4], v[0]
    elif af == 5:
        a, b, c, d = v[0], v[3], v[2], v[1]
    else:
        a, b, c, d = v[4], v[7], v[6], v[5]
    acbd = a * c - b * d
    if acbd > -FLT_EPSILON and acbd < FLT_EPSILON:
        return face >= 0
    return face * a * acbd >= 0


# per reference edge of test_internal: the corner whose value sets t, the far end, then the
# three edges (start, end) interpolated at t for Bt, Ct, Dt
_INTERNAL = np.array([
    (0, 1, 3, 2, 7, 6, 4, 5), (1, 2, 0, 3, 4, 7, 5, 6), (2, 3, 1, 0, 5, 4, 6, 7),
    (3, 0, 2, 1, 6, 5, 7, 4), (4, 5, 7, 6, 3, 2, 0, 1), (5, 6, 4, 7, 0, 3, 1, 2),
    (6, 7, 5, 4, 1, 0, 2, 3), (7, 4, 6, 5, 2, 1, 3, 0), (0, 4, 3, 7, 2, 6, 1, 5),
    (1, 5, 0, 4, 3, 7, 2, 6), (2, 6, 1, 5, 0, 4, 3, 7), (3, 7, 2, 6, 1, 5, 0, 4)], np.int64)


@njit(cache=True, nogil=True)
def _test_internal(v, case, config, subconfig, s):
    """Lewiner's interior test (cases 4, 6, 7, 10, 12, 13)."""
    at = bt = ct = dt = 0.0
    if case == 4 or case == 10:
        a = (v[4] - v[0]) * (v[6] - v[2]) - (v[7] - v[3]) * (v[5] - v[1])
        b = v[2] * (v[4] - v[0]) + v[0] * (v[6] - v[2]) - v[1] * (v[7] - v[3]) \
            - v[3] * (v[5] - v[1])
        t = -b / (2 * a + FLT_EPSILON)
        if t < 0 or t > 1:
            return s > 0
        at = v[0] + (v[4] - v[0]) * t
        bt = v[3] + (v[7] - v[3]) * t
        ct = v[2] + (v[6] - v[2]) * t
        dt = v[1] + (v[5] - v[1]) * t
    else:
        if case == 6:
            edge = get(L.T_TEST6, config, 2, 0)
        elif case == 7:
            edge = get(L.T_TEST7, config, 4, 0)
        elif case == 12:
            edge = get(L.T_TEST12, config, 3, 0)
        else:
            edge = get(L.T_TILING13_5_1, config, subconfig, 0)
        r = _INTERNAL[edge]
        t = v[r[0]] / (v[r[0]] - v[r[1]] + FLT_EPSILON)
        bt = v[r[2]] + (v[r[3]] - v[r[2]]) * t
        ct = v[r[4]] + (v[r[5]] - v[r[4]]) * t
        dt = v[r[6]] + (v[r[7]] - v[r[6]]) * t
    test = (at >= 0) + 2 * (bt >= 0) + 4 * (ct >= 0) + 8 * (dt >= 0)
    if test == 5:
        return s > 0 if at * ct - bt * dt < FLT_EPSILON else False
    if test == 10:
        return s > 0 if at * ct - bt * dt >= FLT_EPSILON else False
    if test == 7 or test == 11 or test >= 13:
        return s < 0
    return s > 0


@njit(cache=True, nogil=True)
def tiling(v, case, config):
    """Lewiner's big switch: ``(table, index, triangles)`` for the cube; ``index`` is the
    second index of a 3-D tiling table, -1 for a 2-D one."""
    if case == 1:
        return L.T_TILING1, -1, 1
    if case == 2:
        return L.T_TILING2, -1, 2
    if case == 3:
        if _test_face(v, get(L.T_TEST3, config, 0, 0)):
            return L.T_TILING3_2, -1, 4
        return L.T_TILING3_1, -1, 2
    if case == 4:
        if _test_internal(v, case, config, 0, get(L.T_TEST4, config, 0, 0)):
            return L.T_TILING4_1, -1, 2
        return L.T_TILING4_2, -1, 6
    if case == 5:
        return L.T_TILING5, -1, 3
    if case == 6:
        if _test_face(v, get(L.T_TEST6, config, 0, 0)):
            return L.T_TILING6_2, -1, 5
        if _test_internal(v, case, config, 0, get(L.T_TEST6, config, 1, 0)):
            return L.T_TILING6_1_1, -1, 3
        return L.T_TILING6_1_2, -1, 9
    if case == 7:
        sub = 0
        for k in range(3):
            if _test_face(v, get(L.T_TEST7, config, k, 0)):
                sub += 1 << k
        if sub == 0:
            return L.T_TILING7_1, -1, 3
        if sub == 1 or sub == 2:
            return L.T_TILING7_2, sub - 1, 5
        if sub == 4:
            return L.T_TILING7_2, 2, 5
        if sub == 3 or sub == 5 or sub == 6:
            return L.T_TILING7_3, (sub - 3) // 2 + (sub == 6), 9
        if _test_internal(v, case, config, sub, get(L.T_TEST7, config, 3, 0)):
            return L.T_TILING7_4_2, -1, 9
        return L.T_TILING7_4_1, -1, 5
    if case == 8:
        return L.T_TILING8, -1, 2
    if case == 9:
        return L.T_TILING9, -1, 4
    if case == 10 or case == 12:
        test = L.T_TEST10 if case == 10 else L.T_TEST12
        first = L.T_TILING10_1_1 if case == 10 else L.T_TILING12_1_1
        # first + 0..4: _1_1, _1_1_, _1_2, _2, _2_ (the table order of NAMES)
        if _test_face(v, get(test, config, 0, 0)):
            if _test_face(v, get(test, config, 1, 0)):
                return first + 1, -1, 4
            return first + 3, -1, 8
        if _test_face(v, get(test, config, 1, 0)):
            return first + 4, -1, 8
        if _test_internal(v, case, config, 0, get(test, config, 2, 0)):
            return first, -1, 4
        return first + 2, -1, 8
    if case == 11:
        return L.T_TILING11, -1, 4
    if case == 13:
        sub = 0
        for k in range(6):
            if _test_face(v, get(L.T_TEST13, config, k, 0)):
                sub += 1 << k
        sub = get(L.T_SUBCONFIG13, sub, 0, 0)
        if sub < 0:  # impossible by the tables; skimage adds nothing
            return L.T_TILING13_1, -1, 0
        if sub == 0:
            return L.T_TILING13_1, -1, 4
        if sub <= 6:
            return L.T_TILING13_2, sub - 1, 6
        if sub <= 18:
            return L.T_TILING13_3, sub - 7, 10
        if sub <= 22:
            return L.T_TILING13_4, sub - 19, 12
        if sub <= 26:
            if _test_internal(v, case, config, sub - 23, get(L.T_TEST13, config, 6, 0)):
                return L.T_TILING13_5_1, sub - 23, 6
            return L.T_TILING13_5_2, sub - 23, 10
        if sub <= 38:
            return L.T_TILING13_3_, sub - 27, 10
        if sub <= 44:
            return L.T_TILING13_2_, sub - 39, 6
        return L.T_TILING13_1_, -1, 4
    return L.T_TILING14, -1, 4
