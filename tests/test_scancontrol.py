"""scanCONTROL adapter against a fake `pyllt` module that behaves like the vendor's wrapper:
interface listing, connect, resolutions, features, a buffer callback fed with PROFILE buffers
(resolution x 64 bytes, four 16-byte reflections per point, trailing 16-byte timestamp block),
convert_profile_2_values and timestamp_2_time_and_count."""

import ctypes as ct
import struct
import sys
import types

import numpy as np
import pytest

from dm2.core.messages import COUNTER_MODULO
from dm2.live.inbox import Inbox
from dm2.live.scancontrol import (
    BYTES_PER_POINT,
    ScanControlError,
    ScanControlSource,
    ScanControlUnavailable,
    load_wrapper,
)

X_SCALE_MM = 0.005  # the fake sensor's raw -> mm scaling (exact in binary floating point)
Z_OFFSET_MM = 100.0
RES = 8


def make_fake_llt(interfaces=("218020093", "218020117"), resolutions=(RES, 160)):
    """A module with the wrapper's names and calling conventions, recording every call."""
    m = types.ModuleType("pyllt")
    m.calls = []
    m.devices = []
    m.buffer_cb_func = ct.CFUNCTYPE(None, ct.c_void_p, ct.c_uint, ct.c_void_p)
    m.TProfileConfig = types.SimpleNamespace(PROFILE=1, CONTAINER=6)
    m.TTransferProfileType = types.SimpleNamespace(NORMAL_TRANSFER=0)
    m.CONVERT_X, m.CONVERT_Z, m.CONVERT_MAXIMUM = 0x800, 0x1000, 0x200
    m.FEATURE_FUNCTION_TRIGGER = 0xF0F00830
    m.FEATURE_FUNCTION_SHUTTERTIME = 0xF0F0081C
    m.FEATURE_FUNCTION_IDLETIME = 0xF0F00800

    class Device:
        callback = None

        def emit(self, raw: bytes):
            buf = (ct.c_ubyte * len(raw)).from_buffer_copy(raw)
            self.callback(ct.addressof(buf), len(raw), None)

    def create_llt_device():
        d = Device()
        m.devices.append(d)
        return d

    def get_device_interfaces(names, n):
        addresses = ct.cast(names, ct.POINTER(ct.c_void_p))
        for i, name in enumerate(interfaces[:n]):
            ct.memmove(addresses[i], name.encode() + b"\0", len(name) + 1)
        return len(interfaces)

    def get_resolutions(h, out, n):
        for i, r in enumerate(resolutions[:n]):
            out[i] = r
        return len(resolutions)

    def get_llt_type(h, ref):
        ref._obj.value = 3001  # scanCONTROL29xx_100
        return 1

    def register_buffer_callback(h, cb, user):
        h.callback = cb
        return 1

    def logged(name, fn=lambda *a: 1):
        def call(*args):
            m.calls.append((name, args[1:]))
            return fn(*args)
        return call

    def convert_profile_2_values(data, size, resolution, config, scanner_type, reflection,
                                 width, intensity, threshold, x, z, m0, m1):
        assert config == m.TProfileConfig.PROFILE and scanner_type == 3001 and reflection == 0
        raw = bytes(data[:size])
        for i in range(resolution):
            _w, peak, _t, xr, zr = struct.unpack_from(">HHHHH", raw, i * BYTES_PER_POINT)
            x[i] = (xr - 32768) * X_SCALE_MM
            z[i] = 0.0 if zr == 0 else (zr - 32768) * X_SCALE_MM + Z_OFFSET_MM
            intensity[i] = peak
        return m.CONVERT_X | m.CONVERT_Z | m.CONVERT_MAXIMUM

    def timestamp_2_time_and_count(block, opened, closed, count, encoder):
        cnt, open_us, close_us, _ = struct.unpack("<IIII", bytes(block))
        opened._obj.value = open_us * 1e-6
        closed._obj.value = close_us * 1e-6
        count._obj.value = cnt

    m.create_llt_device = create_llt_device
    m.get_device_interfaces = logged("get_device_interfaces", get_device_interfaces)
    m.get_resolutions = get_resolutions
    m.get_llt_type = get_llt_type
    m.register_buffer_callback = register_buffer_callback
    m.convert_profile_2_values = convert_profile_2_values
    m.timestamp_2_time_and_count = timestamp_2_time_and_count
    for name in ("set_device_interface", "connect", "set_resolution", "set_profile_config",
                 "set_feature", "transfer_profiles", "disconnect", "del_device"):
        setattr(m, name, logged(name))
    m.connect = logged("connect", lambda h: 1)
    m.set_device_interface = logged("set_device_interface", lambda h, name: 1)
    m.disconnect = logged("disconnect", lambda h: 1)
    m.del_device = logged("del_device", lambda h: 1)
    return m


def profile_buffer(x_mm, z_mm, peak, counter, open_s, close_s) -> bytes:
    """A PROFILE buffer in the fake sensor's raw units; z None = no point found."""
    raw = bytearray(len(x_mm) * BYTES_PER_POINT)
    for i, (x, z, p) in enumerate(zip(x_mm, z_mm, peak, strict=True)):
        zr = 0 if z is None else round((z - Z_OFFSET_MM) / X_SCALE_MM) + 32768
        struct.pack_into(">HHHHH", raw, i * BYTES_PER_POINT, 3, p, 10,
                         round(x / X_SCALE_MM) + 32768, zr)
    raw[-16:] = struct.pack("<IIII", counter, round(open_s * 1e6), round(close_s * 1e6), 0)
    return bytes(raw)


X = [-10.0, -7.5, -5.0, -2.5, 0.0, 2.5, 5.0, 7.5]
Z = [101.25, 102.5, None, 103.75, 104.0, 99.995, 100.5, 101.0]
PEAK = [1023, 512, 0, 300, 0, 1, 700, 900]  # the 5th point: a distance but no intensity


@pytest.fixture
def fake(monkeypatch):
    llt = make_fake_llt()
    monkeypatch.setitem(sys.modules, "pyllt", llt)
    return llt


def test_profiles_convert_exactly_with_counter_stamp_and_invalid_points(fake):
    inbox = Inbox(100)
    src = ScanControlSource(inbox, "S2", "218020117", RES, exposure_us=500,
                            idle_us=3500).start()
    (dev,) = fake.devices
    dev.emit(profile_buffer(X, Z, PEAK, counter=4242, open_s=12.5, close_s=12.5005))
    p, source, _arrival = inbox.get(timeout_s=0)
    assert (source, p.sensor_id, p.counter) == ("scancontrol", "S2", 4242)
    assert p.stamp_s == pytest.approx(12.50025, abs=1e-9)
    valid = np.array([True, True, False, True, False, True, True, True])
    np.testing.assert_array_equal(p.valid, valid)
    assert np.isnan(p.xz_S[~valid]).all()
    np.testing.assert_allclose(p.xz_S[valid, 0], np.array(X)[valid], atol=1e-12)
    np.testing.assert_allclose(p.xz_S[valid, 1], [101.25, 102.5, 103.75, 99.995, 100.5, 101.0],
                               atol=1e-9)
    np.testing.assert_allclose(p.intensity, np.array(PEAK) / 1023.0, rtol=1e-6)
    src.close()
    names = [c[0] for c in fake.calls]
    assert names[:2] == ["get_device_interfaces", "set_device_interface"]
    assert ("set_resolution", (RES,)) in fake.calls
    assert ("set_profile_config", (fake.TProfileConfig.PROFILE,)) in fake.calls
    assert ("set_feature", (fake.FEATURE_FUNCTION_TRIGGER, 0)) in fake.calls
    assert ("set_device_interface", (b"218020117",)) in fake.calls
    # the sensor takes times in 10 us steps: 500 us -> 50, 3500 us -> 350
    assert ("set_feature", (fake.FEATURE_FUNCTION_SHUTTERTIME, 50)) in fake.calls
    assert ("set_feature", (fake.FEATURE_FUNCTION_IDLETIME, 350)) in fake.calls
    assert names[-3:] == ["transfer_profiles", "disconnect", "del_device"]
    assert fake.calls[-3][1] == (0, 0)  # NORMAL_TRANSFER, stop


def test_counter_wraps_at_24_bits_and_sensor_clock_unwraps_at_128_s(fake):
    inbox = Inbox(100)
    with ScanControlSource(inbox, "S1", "218020093", RES):
        (dev,) = fake.devices
        for counter, t in [(COUNTER_MODULO - 1, 127.9), (COUNTER_MODULO, 127.95), (1, 0.0)]:
            dev.emit(profile_buffer(X, Z, PEAK, counter, t, t))
        got = [inbox.get(timeout_s=0)[0] for _ in range(3)]
    assert [p.counter for p in got] == [COUNTER_MODULO - 1, 0, 1]
    np.testing.assert_allclose([p.stamp_s for p in got], [127.9, 127.95, 128.0], atol=1e-9)


def test_bad_buffers_are_counted_and_arrival_stamps_used_on_request(fake):
    inbox = Inbox(100)
    with ScanControlSource(inbox, "S3", "218020093", RES, stamp="arrival"):
        (dev,) = fake.devices
        dev.emit(b"\0" * 100)  # not resolution x 64 bytes
        dev.emit(profile_buffer(X, Z, PEAK, 7, 3.0, 3.0))
        p, _, arrival = inbox.get(timeout_s=0)
    assert inbox.dropped == {"scancontrol_bad_profile": 1}
    assert p.counter == 7 and p.stamp_s == arrival


def test_setup_errors_name_the_sensor_and_release_the_device(fake):
    with pytest.raises(ScanControlError, match=r"S1: serial number 192\.168\.0\.11 not found "
                       r"\(the SDK lists \['218020093', '218020117'\]\)"):
        ScanControlSource(Inbox(10), "S1", "192.168.0.11", RES).start()
    with pytest.raises(ValueError, match="exposure_us = 505: the sensor takes times in 10 us"):
        ScanControlSource(Inbox(10), "S1", "218020093", RES, exposure_us=505)
    with pytest.raises(ScanControlError, match="resolution 1280 not offered"):
        ScanControlSource(Inbox(10), "S1", "218020093", 1280).start()
    assert [c[0] for c in fake.calls].count("del_device") == 2


def test_missing_wrapper_gives_setup_instructions(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyllt", None)  # None: import raises ImportError
    monkeypatch.setitem(sys.modules, "pylinllt", None)
    with pytest.raises(ScanControlUnavailable, match="scanCONTROL Linux SDK") as exc:
        load_wrapper()
    assert "PYTHONPATH" in str(exc.value) and isinstance(exc.value, OSError)


def _cell(tmp_path):
    from dm2.core.calibration_io import write_calibration_toml
    from dm2.core.messages import Calibration
    from dm2.live.config import load_cell_file

    T = np.eye(4)
    write_calibration_toml(Calibration({"S1": T, "S2": T, "S3": T}, T, T),
                           tmp_path / "calibration.toml")
    (tmp_path / "cell.toml").write_text(
        'schema = 1\ncalibration = "calibration.toml"\n[live]\negm = "127.0.0.1:0"\n'
        'profiles = "127.0.0.1:0"\n[[live.scancontrol]]\nsensor_id = "S2"\n'
        f'serial = "218020093"\nresolution = {RES}\n')
    return load_cell_file(tmp_path / "cell.toml")


def test_live_runner_opens_the_listed_sensors(fake, tmp_path):
    from dm2.live.runner import LiveRunner

    runner = LiveRunner(_cell(tmp_path), tmp_path / "out", record=False)
    try:
        addresses = runner.open_sources()
        assert addresses["scancontrol S2"] == ("218020093", "S2")
        fake.devices[0].emit(profile_buffer(X, Z, PEAK, 9, 1.0, 1.0))
        p, source, _ = runner.inbox.get(timeout_s=0)
        assert (p.sensor_id, p.counter, source) == ("S2", 9, "scancontrol")
    finally:
        runner.close()
    assert [c[0] for c in fake.calls][-2:] == ["disconnect", "del_device"]


def test_live_runner_without_the_wrapper_fails_clearly_and_closes_sockets(monkeypatch, tmp_path):
    from dm2.live.runner import LiveRunner

    monkeypatch.setitem(sys.modules, "pyllt", None)
    monkeypatch.setitem(sys.modules, "pylinllt", None)
    runner = LiveRunner(_cell(tmp_path), tmp_path / "out", record=False)
    with pytest.raises(ScanControlUnavailable, match="live.scancontrol"):
        runner.open_sources()
    assert runner.sources == []


def test_cell_file_selects_sensors_by_serial_number_in_10_us_steps(tmp_path):
    from dm2.core.config import ConfigError

    _cell(tmp_path)  # writes calibration.toml and a valid cell.toml
    from dm2.live.config import load_cell_file

    text = (tmp_path / "cell.toml").read_text()
    for bad, expect in (('serial = "218020093"', "selects sensors by serial number"),
                        (f"resolution = {RES}", "multiple of 10")):
        new = 'interface = "192.168.0.11"' if "serial" in bad else \
            f"resolution = {RES}\nexposure_us = 505"
        (tmp_path / "bad.toml").write_text(text.replace(bad, new))
        with pytest.raises(ConfigError, match=expect):
            load_cell_file(tmp_path / "bad.toml")
