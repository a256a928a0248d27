import json

import numpy as np
import pytest

from agent.cli import main
from sim.autopilot import GaussMarkov, Orbit, StraightLine, true_cam_from_world
from sim.flight import SimFlightConfig, load_truth, pose_errors, run_sim_flight, truth_path
from telemetry.flightlog import read_flight
from telemetry.frames import look_at
from telemetry.posesfile import PosesFile

T0 = 1_750_000_000_000_000
FAST = {"texture_size": 512, "texel_m": 0.05, "n_trees": 2, "n_structures": 1}


def test_gauss_markov_has_the_configured_std_and_correlation_time():
    gm = GaussMarkov(2.0, 5.0, np.random.default_rng(0), dim=1)
    xs = np.array([gm.at(t * 0.1)[0] for t in range(200_000)])
    assert np.std(xs) == pytest.approx(2.0, rel=0.1)
    lag = 50  # 5 s = tau: correlation 1/e
    c = np.corrcoef(xs[:-lag], xs[lag:])[0, 1]
    assert c == pytest.approx(np.exp(-1), abs=0.06)
    # slowly varying, unlike white noise: consecutive samples 0.1 s apart are close
    assert np.std(np.diff(xs)) < 0.3 * np.std(xs)


def test_orbit_with_gimbal_looks_at_the_centre():
    orbit = Orbit(altitude_m=30.0, radius_m=25.0, speed_mps=5.0)
    for t in (0.0, 3.3, 11.0):
        s = orbit.state(t)
        np.testing.assert_allclose(true_cam_from_world(s, None), look_at(s.position_enu, [0, 0, 0]), atol=1e-9)


def test_level_orbit_with_fixed_mount_looks_at_the_centre():
    orbit = Orbit(altitude_m=15.0, radius_m=20.0, tilt=False)
    s = orbit.state(2.0)
    T = true_cam_from_world(s, (0.0, orbit.look_pitch_deg(), 0.0))
    np.testing.assert_allclose(T, look_at(s.position_enu, [0, 0, 0]), atol=1e-9)


def test_straight_line_nadir():
    s = StraightLine().state(1.0)
    T = true_cam_from_world(s, (0.0, -90.0, 0.0))
    assert (T[:3, :3].T @ [0, 0, 1])[2] == pytest.approx(-1.0)


def flight(tmp_path, name="f", **kw):
    cfg = SimFlightConfig(frames=kw.pop("frames", 6), width=48, height=36, supersample=1, start_unix_us=T0,
                          world=FAST, **kw)
    out = tmp_path / name
    summary = run_sim_flight(out, cfg)
    return out, summary


@pytest.mark.parametrize("transport,gimbal", [("pty", False), ("udp", True)])
def test_sim_flight_zero_noise_poses_match_truth(tmp_path, transport, gimbal):
    out, summary = flight(tmp_path, transport=transport, gimbal=gimbal, fps=4.0)
    assert summary["frames"] == 6 and summary["messages"] > 100
    assert truth_path(out).parent == out.parent and not (out / "truth.json").exists()
    fl = read_flight(out, decode_images=True)
    assert fl.problems == [] and len(fl.frames) == 6
    assert (out / "classes.txt").read_text().split() == ["standing", "kneeling", "prone"]
    assert len(list((out / "labels").glob("*.txt"))) == 6
    assert main(["poses", str(out), "--no-sfm"]) == 0
    err = pose_errors(PosesFile.load(out / "derived" / "poses.json"), load_truth(truth_path(out)))
    assert err["n"] == 6 and err["unposed"] == 0
    assert err["pos_median_m"] < 0.02 and err["rot_median_deg"] < 0.05


def test_sim_flight_gimbal_and_realistic_noise(tmp_path):
    out, _ = flight(tmp_path, gimbal=True, noise="realistic", seed=3, frames=8, fps=4.0)
    assert main(["poses", str(out), "--no-sfm"]) == 0
    err = pose_errors(PosesFile.load(out / "derived" / "poses.json"), load_truth(truth_path(out)))
    assert err["n"] == 8
    # injected: 0.5 m, 0.5 m, 0.8 m (1 sigma) position drift; 0.3 deg attitude (gimbal: yaw only)
    assert 0.05 < err["pos_median_m"] < 3.0
    assert 0.005 < err["rot_median_deg"] < 1.5


def test_sim_flight_refuses_to_overwrite(tmp_path):
    out, _ = flight(tmp_path, frames=1)
    with pytest.raises(FileExistsError):
        flight(tmp_path, frames=1)
    assert main(["sim-flight", str(out), "--frames", "1"]) == 2


def test_poses_with_sfm_on_a_too_short_flight_keeps_telemetry_poses_with_a_reason(tmp_path, capsys):
    out, _ = flight(tmp_path, frames=2)
    assert main(["poses", str(out)]) == 0
    poses = PosesFile.load(out / "derived" / "poses.json")
    assert len(poses.frames) == 2
    for e in poses.frames:
        assert e.cam_from_world is not None
        assert e.source == "sfm" or (e.source == "telemetry" and e.reason)
    assert "not refined" in capsys.readouterr().out


def test_tlog_command_summary(tmp_path, capsys):
    out, _ = flight(tmp_path, frames=2)
    capsys.readouterr()
    assert main(["tlog", str(out / "telemetry.tlog"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["time_source"] == "timesync" and s["autopilot"] == [1, 1]
    assert s["by_type"]["ATTITUDE"] > s["by_type"]["GLOBAL_POSITION_INT"] > 0
    assert s["position_gaps"] == []
    assert main(["tlog", str(out / "telemetry.tlog")]) == 0
    assert "GLOBAL_POSITION_INT" in capsys.readouterr().out
    assert main(["tlog", str(tmp_path / "missing.tlog")]) == 2
    (tmp_path / "junk.tlog").write_bytes(b"\x00" * 100)
    assert main(["tlog", str(tmp_path / "junk.tlog")]) == 2
