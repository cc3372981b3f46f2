"""A mirror kept by HeightField.copy_changes_to equals its field bit for bit."""

import numpy as np
import pytest

from dm2.core.config import ProcessConfig
from twin.world.deposition import SprayModel
from twin.world.heightfield import HeightField


def _same(a: HeightField, b: HeightField) -> bool:
    return (np.array_equal(a._h, b._h) and np.array_equal(a._bmax, b._bmax)
            and a._zmax[0] == b._zmax[0])


def test_mirror_follows_deposition_and_whole_field_edits():
    hf = HeightField((40.0, 30.0), 0.25, 6.0)
    mirror = hf.copy()
    spray = SprayModel(ProcessConfig(), seed=7)
    down = np.array([0.0, 0.0, -1.0])
    spray.deposit(hf, np.array([20.0, 15.0, 0.0]), down, 0.05)
    assert not _same(hf, mirror)
    hf.copy_changes_to(mirror)
    assert _same(hf, mirror)
    before = mirror._h.copy()
    hf.copy_changes_to(mirror)  # nothing changed: nothing copied, still equal
    assert np.array_equal(mirror._h, before)
    # a packet stream along the border (splats clipped by the plate edge)
    spray.deposit_samples(hf, np.array([[0.1, 0.1, 0.0], [39.9, 29.9, 0.0]]),
                          np.array([down, down]), 0.05)
    hf.copy_changes_to(mirror)
    assert _same(hf, mirror)
    hf.add_heights(np.full(hf.shape, 0.5))  # whole-field edit marks every cell
    hf.copy_changes_to(mirror)
    assert _same(hf, mirror)
    # changes taken now and applied later, in order, on another copy
    late = hf.copy()
    spray.deposit(hf, np.array([10.0, 10.0, 0.0]), down, 0.05)
    first = hf.take_changes()
    spray.deposit(hf, np.array([11.0, 10.0, 0.0]), down, 0.05)
    second = hf.take_changes()
    assert not _same(hf, late)
    late.apply_changes(first)
    late.apply_changes(second)
    assert _same(hf, late)
    late.apply_changes(hf.take_changes())  # nothing changed since
    assert _same(hf, late)
    with pytest.raises(ValueError, match="mirror shape"):
        hf.copy_changes_to(HeightField((20.0, 30.0), 0.25, 6.0))
