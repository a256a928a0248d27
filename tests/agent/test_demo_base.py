"""Which detector the demo fine-tunes from: the cached base, a trained-on-demand base, or none."""

import export.pretrain as pretrain
from agent.demo import demo_base


def test_quick_demo_uses_the_cache_and_never_trains(monkeypatch, tmp_path):
    monkeypatch.setenv("UAVSIM_CACHE", str(tmp_path))
    monkeypatch.setattr(pretrain, "pretrain_base", lambda cfg: (_ for _ in ()).throw(AssertionError("trained")))
    assert demo_base("auto", quick=True) is None  # nothing cached: from scratch, and said so
    (tmp_path / "detector-base").mkdir()
    (tmp_path / "detector-base" / "base.pt").write_bytes(b"x")
    assert demo_base("auto", quick=True) == str(tmp_path / "detector-base" / "base.pt")
    assert demo_base("none", quick=True) is None


def test_full_demo_trains_the_base_when_it_is_missing(monkeypatch, tmp_path):
    monkeypatch.setenv("UAVSIM_CACHE", str(tmp_path))
    trained = []

    def fake_pretrain(cfg):
        trained.append(cfg.out_dir())
        cfg.out_dir().mkdir(parents=True)
        (cfg.out_dir() / "base.pt").write_bytes(b"x")
        return {}

    monkeypatch.setattr(pretrain, "pretrain_base", fake_pretrain)
    assert demo_base("auto", quick=False) == str(tmp_path / "detector-base" / "base.pt")
    assert demo_base("auto", quick=False) == str(tmp_path / "detector-base" / "base.pt")
    assert trained == [tmp_path / "detector-base"]  # once: cached afterwards
