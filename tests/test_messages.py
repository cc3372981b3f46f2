"""Validation of the pipeline's message contracts."""

import numpy as np
import pytest

from dm2.core.messages import (
    COUNTER_MODULO,
    Calibration,
    LayerMark,
    MessageError,
    Profile,
    RobotState,
    Toolpath,
)


def profile(**kw):
    n = 4
    args = dict(sensor_id="S1", stamp_s=1.0, counter=5, xz_S=np.zeros((n, 2)),
                valid=np.ones(n, bool), intensity=np.ones(n, np.float32))
    args.update(kw)
    return Profile(**args)


def test_profile_is_frozen_and_readonly():
    p = profile()
    with pytest.raises(AttributeError):
        p.stamp_s = 2.0
    with pytest.raises(ValueError):
        p.xz_S[0, 0] = 1.0
    assert p.n_points == 4


@pytest.mark.parametrize("kw, field", [
    (dict(sensor_id="S9"), "sensor_id"),
    (dict(counter=COUNTER_MODULO), "counter"),
    (dict(counter=-1), "counter"),
    (dict(stamp_s=float("nan")), "stamp_s"),
    (dict(xz_S=np.zeros((4, 3))), "xz_S"),
    (dict(valid=np.ones(3, bool)), "valid"),
    (dict(intensity=np.ones(5)), "intensity"),
])
def test_profile_errors_name_the_field(kw, field):
    with pytest.raises(MessageError, match=f"Profile.{field}"):
        profile(**kw)


def test_robot_state_rejects_non_rigid_pose():
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(MessageError, match="RobotState.T_B_F"):
        RobotState(0.0, 0, np.zeros(6), T)
    with pytest.raises(MessageError, match="RobotState.joints_rad"):
        RobotState(0.0, 0, np.array([np.nan] * 6), np.eye(4))


def test_layer_mark_and_calibration_validation():
    assert LayerMark(1.5, 3).layer == 3
    with pytest.raises(MessageError, match="LayerMark.layer"):
        LayerMark(1.5, -1)
    with pytest.raises(MessageError, match="unknown sensor"):
        Calibration({"S7": np.eye(4)}, np.eye(4), np.eye(4))


def toolpath(n=3, **kw):
    args = dict(position_O=np.zeros((n, 3)), axis_O=np.tile([0, 0, -1.0], (n, 1)),
                speed_mm_s=np.full(n, 30.0), kind=np.zeros(n), layer=np.arange(n),
                spray_on=np.ones(n, bool), zone_mm=np.ones(n))
    args.update(kw)
    return Toolpath(**args)


def test_toolpath_validation_and_select():
    tp = toolpath()
    assert len(tp) == 3 and tp.n_layers == 3
    assert list(tp.select(tp.layer > 0).layer) == [1, 2]
    assert list(tp.kind_names()) == ["infill"] * 3
    with pytest.raises(MessageError, match="axis_O"):
        toolpath(axis_O=np.tile([0, 0, -2.0], (3, 1)))
    with pytest.raises(MessageError, match="speed_mm_s"):
        toolpath(speed_mm_s=np.array([30.0, 0.0, 30.0]))
    with pytest.raises(MessageError, match="layer"):
        toolpath(layer=np.array([0, 2, 1]))
    with pytest.raises(MessageError, match="kind"):
        toolpath(kind=np.array([0, 1, 7]))
