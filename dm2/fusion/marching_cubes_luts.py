"""Lewiner's marching-cubes tables, read from scikit-image's table module and packed for numba.

Each table is stored flat in :data:`LUT` at ``LUT_OFF[t]``; entry ``(i0, i1, i2)`` of table
``t`` is ``LUT[LUT_OFF[t] + i0 * LUT_S1[t] + i1 * LUT_S2[t] + i2]`` (a 2-D table has ``i2 = 0``,
a 1-D one ``i1 = i2 = 0``). ``T_<NAME>`` is the table id of skimage's ``<NAME>``.
"""

from __future__ import annotations

import base64

import numpy as np
from skimage.measure import _marching_cubes_lewiner_luts as _skimage_luts

NAMES = ("CASES", "TILING1", "TILING2", "TILING3_1", "TILING3_2", "TILING4_1", "TILING4_2",
         "TILING5", "TILING6_1_1", "TILING6_1_2", "TILING6_2", "TILING7_1", "TILING7_2",
         "TILING7_3", "TILING7_4_1", "TILING7_4_2", "TILING8", "TILING9", "TILING10_1_1",
         "TILING10_1_1_", "TILING10_1_2", "TILING10_2", "TILING10_2_", "TILING11",
         "TILING12_1_1", "TILING12_1_1_", "TILING12_1_2", "TILING12_2", "TILING12_2_",
         "TILING13_1", "TILING13_1_", "TILING13_2", "TILING13_2_", "TILING13_3", "TILING13_3_",
         "TILING13_4", "TILING13_5_1", "TILING13_5_2", "TILING14", "TEST3", "TEST4", "TEST6",
         "TEST7", "TEST10", "TEST12", "TEST13", "SUBCONFIG13")
(T_CASES, T_TILING1, T_TILING2, T_TILING3_1, T_TILING3_2, T_TILING4_1, T_TILING4_2, T_TILING5,
 T_TILING6_1_1, T_TILING6_1_2, T_TILING6_2, T_TILING7_1, T_TILING7_2, T_TILING7_3,
 T_TILING7_4_1, T_TILING7_4_2, T_TILING8, T_TILING9, T_TILING10_1_1, T_TILING10_1_1_,
 T_TILING10_1_2, T_TILING10_2, T_TILING10_2_, T_TILING11, T_TILING12_1_1, T_TILING12_1_1_,
 T_TILING12_1_2, T_TILING12_2, T_TILING12_2_, T_TILING13_1, T_TILING13_1_, T_TILING13_2,
 T_TILING13_2_, T_TILING13_3, T_TILING13_3_, T_TILING13_4, T_TILING13_5_1, T_TILING13_5_2,
 T_TILING14, T_TEST3, T_TEST4, T_TEST6, T_TEST7, T_TEST10, T_TEST12, T_TEST13,
 T_SUBCONFIG13) = range(len(NAMES))

# edge e of a cube joins the corners at relative (x, y, z) = EDGE_REL[:, e, 0] and [:, e, 1]
# (skimage's EDGETORELATIVEPOSX/Y/Z; x is the volume's last axis)
EDGE_REL = np.array([
    [[0, 1], [1, 1], [1, 0], [0, 0], [0, 1], [1, 1], [1, 0], [0, 0], [0, 0], [1, 1], [1, 1],
     [0, 0]],
    [[0, 0], [0, 1], [1, 1], [1, 0], [0, 0], [0, 1], [1, 1], [1, 0], [0, 0], [0, 0], [1, 1],
     [1, 1]],
    [[0, 0], [0, 0], [0, 0], [0, 0], [1, 1], [1, 1], [1, 1], [1, 1], [0, 1], [0, 1], [0, 1],
     [0, 1]]], np.int64)


def _table(name: str) -> np.ndarray:
    shape, text = getattr(_skimage_luts, name)
    return np.frombuffer(base64.decodebytes(text.encode("utf-8")), np.int8).reshape(shape)


def _pack():
    parts, off, s1, s2, at = [], [], [], [], 0
    for name in NAMES:
        a = _table(name)
        shape = a.shape + (1,) * (3 - a.ndim)
        off.append(at)
        s1.append(shape[1] * shape[2])
        s2.append(shape[2])
        parts.append(a.ravel())
        at += a.size
    return (np.concatenate(parts).astype(np.int64), np.array(off, np.int64),
            np.array(s1, np.int64), np.array(s2, np.int64))


LUT, LUT_OFF, LUT_S1, LUT_S2 = _pack()
