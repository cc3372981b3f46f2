"""Message equality for the tests: every field, bit for bit, arrays read-only on both sides."""

from __future__ import annotations

import numpy as np


def assert_same_message(a, b) -> None:
    assert type(a) is type(b)
    for name, va in vars(a).items():
        vb = getattr(b, name)
        if isinstance(va, np.ndarray):
            assert va.dtype == vb.dtype and va.shape == vb.shape, name
            np.testing.assert_array_equal(va, vb, err_msg=name)
            assert not va.flags.writeable and not vb.flags.writeable
        else:
            assert type(va) is type(vb) and va == vb, name
