"""The cell file: allow-lists resolved at load (``localhost`` works), errors show the bad value
and the nearest known key."""

import socket
import time

import pytest

from dm2.core.config import ConfigError
from dm2.live.config import load_cell_file
from dm2.live.egm_source import EgmSource, encode_egm_robot
from dm2.live.inbox import Inbox

CALIBRATION = """schema = 1
[T_B_N]
translation_mm = [1500.0, 0.0, 1000.0]
quaternion_wxyz = [1.0, 0.0, 0.0, 0.0]
[T_F_O]
translation_mm = [0.0, 0.0, 100.0]
quaternion_wxyz = [1.0, 0.0, 0.0, 0.0]
[sensors.S1]
translation_mm = [1500.0, 50.0, 1050.0]
quaternion_wxyz = [1.0, 0.0, 0.0, 0.0]
"""


def _cell(tmp_path, live: str):
    (tmp_path / "calibration.toml").write_text(CALIBRATION, encoding="utf-8")
    path = tmp_path / "cell.toml"
    path.write_text(f'schema = 1\ncalibration = "calibration.toml"\n[live]\n{live}\n',
                    encoding="utf-8")
    return path


def test_localhost_means_both_loopback_addresses_and_its_datagrams_are_used(tmp_path):
    cell = load_cell_file(_cell(tmp_path, 'controllers = ["localhost"]\nbridges = ["localhost"]'))
    assert set(cell.live.controllers) == {"127.0.0.1", "::1"}
    assert set(cell.live.bridges) == {"127.0.0.1", "::1"}
    assert cell.live.egm_schema == "rw7" and cell.live.egm_layer_dnum == 0
    inbox = Inbox(100)
    import numpy as np

    with EgmSource(inbox, "127.0.0.1", 0, controllers=cell.live.controllers) as src:
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for i in range(4):
                udp.sendto(encode_egm_robot(i, 4 * i, np.zeros(6), np.eye(4),
                                            stamp_s=0.004 * i), src.address)
            deadline = time.monotonic() + 5.0
            while inbox.accepted < 4 and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            udp.close()
    assert inbox.accepted == 4 and inbox.dropped == {}


def test_unresolvable_allow_list_entry_is_a_config_error_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"live\.controllers.*'no-such-host\.invalid'"):
        load_cell_file(_cell(tmp_path, 'controllers = ["no-such-host.invalid"]'))


@pytest.mark.parametrize("live, message", [
    ('egm_schema = "rw5"', r"live\.egm_schema.*\(got 'rw5'\)"),
    ('controlers = ["127.0.0.1"]', r"live\.controlers': unknown key \(did you mean "
                                   r"'controllers'\?\)"),
    ('bridge_idle_s = -1.0', r"live\.bridge_idle_s.*\(got -1\.0\)"),
])
def test_bad_values_are_shown_and_unknown_keys_get_the_nearest_known_one(tmp_path, live,
                                                                         message):
    with pytest.raises(ConfigError, match=message):
        load_cell_file(_cell(tmp_path, live))
