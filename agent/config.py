"""The agent's configuration: typed sections, loaded from TOML, overridable on the command line.

Every field has a default that works on a companion computer with the usual paths; a config file
only names what differs. Example (``/etc/uavsim/agent.toml``)::

    [mavlink]
    url = "/dev/ttyTHS1:921600"      # or "udpin:0.0.0.0:14550", "tcp:127.0.0.1:5760"

    [camera]
    source = "0"                     # device index, /dev/videoN, rtsp://..., a GStreamer pipeline, or "sim"
    camera_json = "/etc/uavsim/camera.json"

    [detector]
    model = "/var/lib/uavsim/models/current.onnx"

Overrides: ``uavsim agent --set detector.rate_hz=5 --set http.bind=127.0.0.1:8080``.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path


class ConfigError(ValueError):
    """A configuration file or override that does not fit the schema."""


@dataclass(frozen=True)
class MavlinkConfig:
    #: pymavlink URL: serial "DEVICE:BAUD", "udpin:HOST:PORT", "udpout:HOST:PORT", "tcp:HOST:PORT"
    url: str = "udpin:0.0.0.0:14550"
    #: companion heartbeat rate, Hz
    heartbeat_hz: float = 1.0
    #: requested GLOBAL_POSITION_INT and ATTITUDE rates, Hz
    position_hz: float = 10.0
    attitude_hz: float = 20.0


@dataclass(frozen=True)
class CameraConfig:
    #: cv2.VideoCapture source (index, device path, URL, GStreamer pipeline) or "sim"
    source: str = "0"
    #: intrinsics and mount (camera.json); required for a real camera
    camera_json: str = "/etc/uavsim/camera.json"
    fps: float = 10.0
    jpeg_quality: int = 90


@dataclass(frozen=True)
class StorageConfig:
    root: str = "/var/lib/uavsim/flights"
    #: stop logging cleanly when the flights use more than this, GiB
    quota_gib: float = 20.0
    #: flush + fsync period of the flight log, s (what a power cut can lose at most)
    sync_interval_s: float = 1.0


@dataclass(frozen=True)
class DetectorConfig:
    #: ONNX model in ultralytics layout; empty: no in-flight detection
    model: str = "/var/lib/uavsim/models/current.onnx"
    #: frames per second sent to the detector (frames are logged at the camera rate regardless)
    rate_hz: float = 2.0
    imgsz: int = 320
    conf: float = 0.25
    iou: float = 0.7
    threads: int = 1


@dataclass(frozen=True)
class ProcessingConfig:
    #: "on_disarm" (after landing), "manual" (only on request: POST /api/flights/{id}/process), or "never"
    policy: str = "on_disarm"
    #: CPU niceness of the processing process (capture always wins)
    nice: int = 19
    #: replay options: field training budget, s; quick mode for small boards
    fit_budget_s: float = 300.0
    quick: bool = False
    #: detector checkpoint the new detectors are fine-tuned from: "auto" (the cached base of
    #: `uavsim detector pretrain`), "none" (from scratch) or a .pt path
    base_detector: str = "auto"


@dataclass(frozen=True)
class HttpConfig:
    enabled: bool = True
    bind: str = "0.0.0.0:8080"
    token_file: str = "/etc/uavsim/token"


@dataclass(frozen=True)
class SimConfig:
    """Used when ``camera.source`` or ``mavlink.url`` is "sim": the simulated world and flight."""

    seed: int = 0
    altitude_m: float = 15.0
    radius_m: float = 20.0
    width: int = 640
    height: int = 480
    #: the simulated autopilot arms this long after start and disarms after (negative: never)
    arm_after_s: float = 1.0
    disarm_after_s: float = -1.0


@dataclass(frozen=True)
class AgentConfig:
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    processing: ProcessingConfig = field(default_factory=ProcessingConfig)
    http: HttpConfig = field(default_factory=HttpConfig)
    sim: SimConfig = field(default_factory=SimConfig)

    def validate(self) -> AgentConfig:
        if self.processing.policy not in ("on_disarm", "manual", "never"):
            raise ConfigError(f"processing.policy must be on_disarm, manual or never, got {self.processing.policy!r}")
        for name, value in (("camera.fps", self.camera.fps), ("detector.rate_hz", self.detector.rate_hz),
                            ("storage.sync_interval_s", self.storage.sync_interval_s),
                            ("storage.quota_gib", self.storage.quota_gib)):
            if not value > 0:
                raise ConfigError(f"{name} must be positive, got {value}")
        if self.detector.rate_hz > self.camera.fps:
            raise ConfigError(f"detector.rate_hz ({self.detector.rate_hz}) exceeds camera.fps ({self.camera.fps})")
        host, sep, port = self.http.bind.rpartition(":")
        if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
            raise ConfigError(f"http.bind must be HOST:PORT, got {self.http.bind!r}")
        return self


def _coerce(section: str, key: str, value, target_type):
    try:
        if target_type is bool:
            if isinstance(value, str):
                if value.lower() in ("1", "true", "yes", "on"):
                    return True
                if value.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(value)
            return bool(value)
        if target_type is int and isinstance(value, float) and not value.is_integer():
            raise ValueError(value)
        return target_type(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{section}.{key} must be {target_type.__name__}, got {value!r}") from None


def _apply(config: AgentConfig, section: str, values: dict) -> AgentConfig:
    names = {f.name: f for f in fields(config)}
    if section not in names:
        raise ConfigError(f"unknown config section [{section}]; known: {', '.join(names)}")
    current = getattr(config, section)
    types = {f.name: f.type for f in fields(current)}
    updates = {}
    for key, value in values.items():
        if key not in types:
            raise ConfigError(f"unknown key {section}.{key}; known: {', '.join(types)}")
        t = {"str": str, "int": int, "float": float, "bool": bool}[str(types[key])]
        updates[key] = _coerce(section, key, value, t)
    return replace(config, **{section: replace(current, **updates)})


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> AgentConfig:
    """Defaults, then the TOML file (if given), then ``section.key=value`` overrides; validated."""
    config = AgentConfig()
    if path is not None:
        p = Path(path)
        try:
            data = tomllib.loads(p.read_text())
        except FileNotFoundError:
            raise ConfigError(f"{p}: config file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML ({exc})") from None
        for section, values in data.items():
            if not isinstance(values, dict):
                raise ConfigError(f"{p}: top-level key {section!r} must be a [section]")
            config = _apply(config, section, values)
    for item in overrides or []:
        key, sep, value = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot:
            raise ConfigError(f"override must be section.key=value, got {item!r}")
        config = _apply(config, section, {name: value.strip()})
    return config.validate()


def to_toml(config: AgentConfig) -> str:
    """The configuration as TOML (e.g. to show the effective settings)."""
    lines = []
    for f in fields(config):
        section = getattr(config, f.name)
        assert is_dataclass(section)
        lines.append(f"[{f.name}]")
        for sf in fields(section):
            v = getattr(section, sf.name)
            if isinstance(v, bool):
                lines.append(f"{sf.name} = {'true' if v else 'false'}")
            elif isinstance(v, str):
                lines.append(f'{sf.name} = "{v}"')
            else:
                lines.append(f"{sf.name} = {v}")
        lines.append("")
    return "\n".join(lines)
