"""CDR (ROS 2 serialization, XCDR1 little endian) of dm2 recordings, through ``rosbags``.

:func:`typestore` is ``rosbags``' ROS 2 Humble type store with the project's own message types
registered from their ``.msg`` definitions (``dm2_msgs/msg/LayerMark``); :func:`serialize` and
:func:`deserialize` encode and decode any of its types, a payload that does not match its type
raising :class:`CdrError`. The message layouts and units are in :mod:`dm2.io.ros_messages`.
"""

from __future__ import annotations

from functools import cache

LAYERMARK = "dm2_msgs/msg/LayerMark"
LAYERMARK_DEF = "builtin_interfaces/Time stamp\nint32 layer\n"
OWN_TYPES = {LAYERMARK: LAYERMARK_DEF}


class CdrError(ValueError):
    """A CDR payload does not match the expected layout."""


@cache
def typestore():
    """``rosbags``' ROS 2 Humble type store plus the project's own message types."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in OWN_TYPES.items():
        store.register(get_types_from_msg(text, name))
    return store


def msg_class(typename: str):
    """The ``rosbags`` message class of ``typename`` (e.g. ``sensor_msgs/msg/PointCloud2``)."""
    return typestore().types[typename]


def serialize(msg, typename: str) -> bytes:
    """CDR payload (encapsulation header included) of a ``rosbags`` message."""
    return bytes(typestore().serialize_cdr(msg, typename))


def deserialize(data: bytes, typename: str):
    """The ``rosbags`` message of a CDR payload; :class:`CdrError` if it does not parse."""
    from rosbags.serde import SerdeError

    try:
        return typestore().deserialize_cdr(data, typename)
    except (SerdeError, ValueError, IndexError) as exc:
        raise CdrError(f"{typename}: {exc}") from None


def split_ns(stamp_ns: int) -> tuple[int, int]:
    """ROS ``builtin_interfaces/Time`` (sec, nanosec) of a nanosecond stamp."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    if not -(1 << 31) <= sec < (1 << 31):
        raise ValueError(f"stamp {stamp_ns} ns does not fit ROS Time")
    return sec, nsec


def ros_time(stamp_ns: int):
    """``builtin_interfaces/msg/Time`` of a nanosecond stamp."""
    sec, nsec = split_ns(stamp_ns)
    return msg_class("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)


def header(stamp_ns: int, frame_id: str):
    """``std_msgs/msg/Header`` of a stamp and a frame."""
    return msg_class("std_msgs/msg/Header")(stamp=ros_time(stamp_ns), frame_id=frame_id)


def stamp_ns(time) -> int:
    """Nanosecond stamp of a ``builtin_interfaces/msg/Time``."""
    return time.sec * 1_000_000_000 + time.nanosec
