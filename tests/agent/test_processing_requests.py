"""Processing on request: which flights are accepted, and when the agent starts them."""

import pytest

from agent.config import load_config
from agent.daemon import Agent


def _flight(root, name):
    d = root / name
    d.mkdir(parents=True)
    (d / "frames.csv").write_text("frame,t_unix_us\n")
    return d


@pytest.fixture
def agent(tmp_path):
    return Agent(load_config(None, ["processing.policy=manual", f"storage.root={tmp_path}"]))


def test_requests_queue_once_and_refuse_what_cannot_be_processed(agent, tmp_path):
    a, b = _flight(tmp_path, "flight_0001"), _flight(tmp_path, "flight_0002")
    (tmp_path / "flight_0003").mkdir()
    assert agent.request_processing(a) == (202, {"queued": "flight_0001", "position": 0})
    assert agent.request_processing(b) == (202, {"queued": "flight_0002", "position": 1})
    assert agent.request_processing(a) == (200, {"queued": "flight_0001", "position": 0})  # not twice
    status, body = agent.request_processing(tmp_path / "flight_0003")
    assert status == 409 and "frames.csv" in body["error"]
    agent.flight_dir = b  # being recorded right now
    assert agent.request_processing(b)[0] == 409
    assert agent.status()["processing_queue"] == ["flight_0001", "flight_0002"]


def test_requests_wait_for_disarm_and_for_running_processing(agent, tmp_path, monkeypatch):
    started = []
    monkeypatch.setattr(agent, "_start_processing", lambda flight, requested=False: started.append((flight.name,
                                                                                                  requested)))
    agent.request_processing(_flight(tmp_path, "flight_0001"))
    agent.armed = True
    agent._start_requested()
    assert started == []  # capture first
    agent.armed = False
    agent.processing = object()
    agent._start_requested()
    assert started == []  # one processing at a time
    agent.processing = None
    agent._start_requested()
    assert started == [("flight_0001", True)] and agent.status()["processing_queue"] == []


def test_policy_never_refuses_requests(tmp_path):
    agent = Agent(load_config(None, ["processing.policy=never", f"storage.root={tmp_path}"]))
    status, body = agent.request_processing(_flight(tmp_path, "flight_0001"))
    assert status == 409 and "never" in body["error"]
