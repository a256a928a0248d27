"""The systemd unit: required settings present, and systemd-analyze verify passes where available."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "uavsim-agent.service"


def test_unit_has_the_required_settings():
    text = UNIT.read_text()
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "SupplementaryGroups=dialout video",
                 "StateDirectory=uavsim", "NoNewPrivileges=yes", "DeviceAllow=char-ttyACM rw"):
        assert line in text, line


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify(tmp_path):
    unit = tmp_path / "uavsim-agent.service"
    unit.write_text(UNIT.read_text().replace("/opt/uavsim/.venv/bin/uavsim", sys.executable))
    proc = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    problems = [line for line in (proc.stdout + proc.stderr).splitlines() if "uavsim-agent.service" in line]
    assert proc.returncode == 0 and not problems, proc.stdout + proc.stderr
