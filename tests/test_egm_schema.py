"""ABB's published EGM layouts, compiled here from their own text with grpcio-tools (not the
project's egm.proto): RobotWare 7 datagrams carry the layer index in RAPIDfromRobot.dnum[k],
RobotWare 6 datagrams decode with ``schema="rw6"`` (layers then come from the toolpath)."""

import importlib.util
import sys

import numpy as np
import pytest

from dm2.core.messages import LayerMark, RobotState
from dm2.live.egm_source import EgmDecoder, encode_egm_robot

grpc_tools = pytest.importorskip("grpc_tools.protoc")

# The wire layout of EgmRobot as RobotWare 7 publishes it (field numbers and types), written
# out independently of dm2/live/egm.proto; a separate package keeps it out of dm2's descriptors.
COMMON = """
syntax = "proto2";
package PKG;
message EgmHeader { optional uint32 seqno = 1; optional uint32 tm = 2;
  enum MessageType { MSGTYPE_UNDEFINED = 0; MSGTYPE_COMMAND = 1; MSGTYPE_DATA = 2;
                     MSGTYPE_CORRECTION = 3; MSGTYPE_PATH_CORRECTION = 4; }
  optional MessageType mtype = 3 [default = MSGTYPE_UNDEFINED]; }
message EgmCartesian { required double x = 1; required double y = 2; required double z = 3; }
message EgmQuaternion { required double u0 = 1; required double u1 = 2; required double u2 = 3;
                        required double u3 = 4; }
message EgmEuler { required double x = 1; required double y = 2; required double z = 3; }
message EgmClock { required uint64 sec = 1; required uint64 usec = 2; }
message EgmPose { optional EgmCartesian pos = 1; optional EgmQuaternion orient = 2;
                  optional EgmEuler euler = 3; }
message EgmJoints { repeated double joints = 1; }
message EgmFeedBack { optional EgmJoints joints = 1; optional EgmPose cartesian = 2;
                      optional EgmJoints externalJoints = 3; optional EgmClock time = 4; }
message EgmPlanned { optional EgmJoints joints = 1; optional EgmPose cartesian = 2;
                     optional EgmJoints externalJoints = 3; optional EgmClock time = 4; }
message EgmTestSignals { repeated double signals = 1; }
"""
RW7 = COMMON + """
message EgmMeasuredForce { optional bool fcActive = 1; repeated double force = 2; }
message EgmCollisionInfo { optional bool collsionTriggered = 1; repeated double collDetQuota = 2; }
message EgmRAPIDdata { optional bool digVal = 1; repeated double dnum = 2; }
message EgmRobot { optional EgmHeader header = 1; optional EgmFeedBack feedBack = 2;
  optional EgmPlanned planned = 3; optional bool mciConvergenceMet = 6;
  optional EgmTestSignals testSignals = 7; optional EgmMeasuredForce measuredForce = 9;
  optional double utilizationRate = 10; optional uint32 moveIndex = 11;
  optional EgmCollisionInfo CollisionInfo = 12; optional EgmRAPIDdata RAPIDfromRobot = 13; }
"""
RW6 = COMMON + """
message EgmMeasuredForce { repeated double force = 1; }
message EgmRobot { optional EgmHeader header = 1; optional EgmFeedBack feedBack = 2;
  optional EgmPlanned planned = 3; optional bool mciConvergenceMet = 6;
  optional EgmTestSignals testSignals = 7; optional EgmMeasuredForce measuredForce = 9;
  optional double utilizationRate = 10; }
"""

JOINTS_DEG = [10.0, -20.0, 30.0, -40.0, 50.0, -60.0]
POS_MM = (1200.0, -150.0, 900.0)
QUAT = (0.5, 0.5, -0.5, 0.5)  # (u0 = w, u1, u2, u3)


def _compile(tmp_path, name: str, text: str):
    src = tmp_path / f"{name}.proto"
    src.write_text(text.replace("PKG", f"published.{name}"), encoding="utf-8")
    rc = grpc_tools.main(["protoc", f"-I{tmp_path}", f"--python_out={tmp_path}", str(src)])
    assert rc == 0
    spec = importlib.util.spec_from_file_location(f"{name}_pb2", tmp_path / f"{name}_pb2.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("egm_published")
    return {"rw7": _compile(tmp, "egm_rw7_published", RW7),
            "rw6": _compile(tmp, "egm_rw6_published", RW6)}


def _datagram(pb, seq: int, t_s: float, dnum=None) -> bytes:
    m = pb.EgmRobot()
    m.header.seqno, m.header.tm = seq, int(t_s * 1000)
    m.header.mtype = pb.EgmHeader.MSGTYPE_DATA
    m.feedBack.joints.joints.extend(JOINTS_DEG)
    m.feedBack.cartesian.pos.x, m.feedBack.cartesian.pos.y, m.feedBack.cartesian.pos.z = POS_MM
    o = m.feedBack.cartesian.orient
    o.u0, o.u1, o.u2, o.u3 = QUAT
    m.feedBack.time.sec, m.feedBack.time.usec = divmod(round(t_s * 1e6), 1_000_000)
    m.utilizationRate = 12.5
    m.measuredForce.force.extend([0.0] * 6)
    if dnum is not None:  # RobotWare 7 only
        m.moveIndex = 3
        m.CollisionInfo.collsionTriggered = False
        m.RAPIDfromRobot.digVal = True
        m.RAPIDfromRobot.dnum.extend(dnum)
    return m.SerializeToString()


def test_rw7_datagrams_give_pose_joints_stamp_and_dnum_layer_marks(published):
    pb = published["rw7"]
    dec = EgmDecoder("rw7", layer_dnum=2)
    out = []
    for i, layer in enumerate([0, 0, 1, 1, 1, 2]):  # the layer index sits in dnum[2]
        out += dec.decode(_datagram(pb, i, 10.0 + 0.004 * i, dnum=[7.0, -1.0, layer, 99.0]))
    marks = [m for m in out if isinstance(m, LayerMark)]
    states = [m for m in out if isinstance(m, RobotState)]
    assert [(m.layer, round(m.stamp_s, 6)) for m in marks] == [(0, 10.0), (1, 10.008),
                                                                (2, 10.02)]
    assert len(states) == 6 and states[3].seq == 3
    assert states[3].stamp_s == pytest.approx(10.012, abs=1e-9)
    np.testing.assert_allclose(np.degrees(states[0].joints_rad), JOINTS_DEG, atol=1e-12)
    np.testing.assert_allclose(states[0].T_B_F[:3, 3], POS_MM)
    # the flange axes of q = (0.5, 0.5, -0.5, 0.5): x_F = z_B, y_F = -x_B, z_F = -y_B
    np.testing.assert_allclose(states[0].T_B_F[:3, :3], [[0, -1, 0], [0, 0, -1], [1, 0, 0]],
                               atol=1e-12)


def test_rw6_datagrams_decode_without_layer_marks(published):
    pb = published["rw6"]
    dec = EgmDecoder("rw6")
    out = [m for i in range(3) for m in dec.decode(_datagram(pb, i, 5.0 + 0.004 * i))]
    assert all(isinstance(m, RobotState) for m in out) and len(out) == 3
    np.testing.assert_allclose(out[2].T_B_F[:3, 3], POS_MM)


def test_rw7_decoder_ignores_what_rw6_lacks_and_the_twin_sends_rw7(published):
    """An RW6 controller's datagram decodes with the RW7 default too (no layer marks); what
    serve-twin sends parses with the published RW7 layout, layer in dnum[0]."""
    out = EgmDecoder().decode(_datagram(published["rw6"], 1, 1.0))
    assert len(out) == 1 and isinstance(out[0], RobotState)
    T = np.eye(4)
    T[:3, 3] = POS_MM
    sent = encode_egm_robot(4, 16, np.radians(JOINTS_DEG), T, stamp_s=0.016, layer=5)
    m = published["rw7"].EgmRobot()
    m.ParseFromString(sent)
    assert list(m.RAPIDfromRobot.dnum) == [5.0] and m.header.seqno == 4
    assert list(m.feedBack.joints.joints) == pytest.approx(JOINTS_DEG)
