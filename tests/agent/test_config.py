import tomllib

import pytest

from agent.config import AgentConfig, ConfigError, load_config, to_toml


def test_defaults_work_and_round_trip_through_toml(tmp_path):
    cfg = load_config()
    assert cfg == AgentConfig()
    (tmp_path / "a.toml").write_text(to_toml(cfg))
    assert load_config(tmp_path / "a.toml") == cfg
    assert tomllib.loads(to_toml(cfg))["detector"]["imgsz"] == 320


def test_file_then_overrides(tmp_path):
    (tmp_path / "a.toml").write_text('[mavlink]\nurl = "/dev/ttyACM0:57600"\n[detector]\nrate_hz = 1\n')
    cfg = load_config(tmp_path / "a.toml", ["detector.rate_hz=4", "http.enabled=false", "camera.source=sim"])
    assert cfg.mavlink.url == "/dev/ttyACM0:57600"
    assert cfg.detector.rate_hz == 4.0 and cfg.http.enabled is False and cfg.camera.source == "sim"


@pytest.mark.parametrize("text, overrides, message", [
    ("[nope]\nx = 1\n", [], "unknown config section"),
    ("[detector]\nspeed = 1\n", [], "unknown key detector.speed"),
    ("[detector]\nimgsz = 'big'\n", [], "detector.imgsz must be int"),
    ("[detector]\nimgsz = 1.5\n", [], "detector.imgsz must be int"),
    ("x = 1\n", [], "must be a \\[section\\]"),
    ("[processing]\npolicy = 'sometimes'\n", [], "processing.policy"),
    ("", ["detector.rate_hz=50"], "exceeds camera.fps"),
    ("", ["http.bind=8080"], "HOST:PORT"),
    ("", ["detector"], "section.key=value"),
    ("[camera\n", [], "not valid TOML"),
])
def test_bad_configs_give_clear_errors(tmp_path, text, overrides, message):
    (tmp_path / "c.toml").write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(tmp_path / "c.toml", overrides)


def test_missing_file():
    with pytest.raises(ConfigError, match="not found"):
        load_config("/nonexistent/agent.toml")
