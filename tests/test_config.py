"""Scenario loading: typed, versioned, unknown keys rejected with file and field named."""

import pytest

from dm2.core.config import ConfigError, Scenario, load_scenario, parse_scenario, scenario_model
from dm2.core.toml_write import dump_toml
from scenarios import list_scenarios, resolve_scenario
from twin.schema import CellConfig, FaultConfig, TwinScenario


def write(tmp_path, text):
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


def test_minimal_scenario_gets_documented_defaults(tmp_path):
    s = load_scenario(write(tmp_path, 'name = "x"\n[part]\ngenerator = "pad"\n'))
    assert s.toolpath.layer_mm == 0.8 and s.toolpath.line_spacing_mm == 2.0
    assert s.toolpath.speed_mm_s.overhang == 12.0 and s.process.nozzle_exit_mm == 6.55
    assert s.sensors.points == 640 and s.sensors.cascade_s == 0.02


@pytest.mark.parametrize("text, field", [
    ('name = "x"\n[part]\ngenerator = "pad"\n[toolpath]\nlayer_mm = 0.0\n', "toolpath.layer_mm"),
    ('name = "x"\n[part]\ngenerator = "pad"\n[toolpath]\nlayer_mm = -1\n', "toolpath.layer_mm"),
    ('name = "x"\nbogus = 1\n[part]\ngenerator = "pad"\n', "bogus"),
    ('name = "x"\n[part]\ngenerator = "pad"\n[process]\nfeed_g_min = "lots"\n',
     "process.feed_g_min"),
    ('name = "x"\n[part]\ngenerator = "pad"\n[cell]\nwheels = 4\n', "cell.wheels"),
    ('schema = 9\nname = "x"\n[part]\ngenerator = "pad"\n', "schema"),
])
def test_bad_scenarios_name_file_and_field(tmp_path, text, field):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_scenario(p)
    assert str(p) in str(err.value) and f"'{field}'" in str(err.value)


def test_bad_twin_sections_name_field_value_and_nearest_key(tmp_path):
    """The twin's sections, typed in twin.schema, fail as clearly as the monitor's."""
    p = write(tmp_path, 'name = "x"\n[part]\ngenerator = "pad"\n[cell]\nplate_sise_mm = [1, 2, 3]\n'
                        '[twin_process]\nporosity = 0.9\n[[faults]]\nkind = "meteor"\n')
    with pytest.raises(ConfigError) as err:
        load_scenario(p)
    text = str(err.value)
    assert str(p) in text
    assert "field 'cell.plate_sise_mm': unknown key (did you mean 'plate_size_mm'?)" in text
    assert "field 'twin_process.porosity'" in text and "(got 0.9)" in text
    assert "field 'faults.0.kind'" in text and "'meteor'" in text


def test_twin_registers_its_scenario_model():
    """Importing the twin makes every scenario a TwinScenario (the twin's sections typed);
    dm2's own Scenario keeps them as plain tables and still rejects unknown top-level keys."""
    assert scenario_model() is TwinScenario and issubclass(TwinScenario, Scenario)
    s = parse_scenario({"name": "x", "part": {"generator": "pad"},
                        "faults": [{"kind": "bump", "layers": [3, 3], "height_mm": 1.0}]})
    assert isinstance(s, TwinScenario) and s.cell == CellConfig()
    assert s.faults == (FaultConfig(kind="bump", layers=(3, 3), height_mm=1.0),)
    plain = Scenario.model_validate({"name": "x", "part": {"generator": "pad"},
                                     "cell": {"plate_size_mm": [50, 60, 4]}})
    assert plain.cell == {"plate_size_mm": [50, 60, 4]}
    with pytest.raises(ValueError, match="bogus"):
        Scenario.model_validate({"name": "x", "part": {"generator": "pad"}, "bogus": 1})


def test_unreadable_and_invalid_toml(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(write(tmp_path, "name = \n"))


def test_resolved_config_round_trips_through_toml(tmp_path):
    s = parse_scenario({"name": "x", "part": {"generator": "pad"},
                        "faults": [{"kind": "bump", "layers": [3, 3], "height_mm": 1.0}]})
    again = load_scenario(write(tmp_path, dump_toml(s.to_toml_dict())))
    assert again == s


def test_every_shipped_scenario_loads():
    names = list_scenarios()
    for name in names:
        load_scenario(resolve_scenario(name))
    with pytest.raises(FileNotFoundError, match="neither a file nor a shipped scenario"):
        resolve_scenario("no_such_scenario")


def test_toml_writer_round_trips_awkward_values():
    """Strings with quotes, backslashes and control characters, keys that are not bare,
    numpy scalars, nan and inf: written TOML reads back equal."""
    import math
    import tomllib

    import numpy as np

    data = {
        "name": 'tower "B"\\v2\nsecond line\ttab\x01',
        "count": np.int64(7),
        "scale": np.float64(0.25),
        "flag": np.bool_(True),
        "limits": [np.float32(1.5), -2, math.inf],
        "odd key.with dot": 1,
        "part": {"stl": "C:\\parts\\tower.stl", "size mm": [60.0, 60.0], "nested": {"a": 1}},
        "sensor": [{"id": "S1", "noise": 0.05}, {"id": "S2", "noise": math.nan}],
    }
    back = tomllib.loads(dump_toml(data))
    assert back["name"] == data["name"]
    assert back["count"] == 7 and isinstance(back["count"], int)
    assert back["scale"] == 0.25 and back["flag"] is True
    assert back["limits"] == [1.5, -2, math.inf]
    assert back["odd key.with dot"] == 1
    assert back["part"] == {"stl": "C:\\parts\\tower.stl", "size mm": [60.0, 60.0],
                            "nested": {"a": 1}}
    assert back["sensor"][0] == {"id": "S1", "noise": 0.05}
    assert math.isnan(back["sensor"][1]["noise"])
