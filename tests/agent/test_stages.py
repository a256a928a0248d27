from agent.stages import StageRunner


def test_finished_stages_are_skipped_and_later_ones_rerun_after_a_change(tmp_path):
    calls = []

    def stage(name, value):
        def fn():
            calls.append(name)
            return {"value": value}
        return fn

    r = StageRunner(tmp_path)
    assert r.run("a", stage("a", 1)) == {"value": 1}
    r.run("b", stage("b", 2))
    assert calls == ["a", "b"]

    r2 = StageRunner(tmp_path)
    assert r2.run("a", stage("a", 9)) == {"value": 1}  # reused
    assert r2.run("b", stage("b", 9)) == {"value": 2}
    r2.run("c", stage("c", 3))  # new stage runs
    assert calls == ["a", "b", "c"]
    assert r2.seconds("a") is not None

    (tmp_path / "derived" / "stages" / "a.json").unlink()
    r3 = StageRunner(tmp_path)
    r3.run("a", stage("a", 4))
    r3.run("b", stage("b", 5))  # downstream of a re-run stage: runs again
    assert calls == ["a", "b", "c", "a", "b"]

    r4 = StageRunner(tmp_path, force=True)
    r4.run("a", stage("a", 6))
    assert calls[-1] == "a"


def test_a_failing_stage_leaves_no_marker(tmp_path):
    r = StageRunner(tmp_path)

    def boom():
        raise ValueError("bad input")

    try:
        r.run("x", boom)
    except ValueError:
        pass
    assert not r.marker("x").exists()
