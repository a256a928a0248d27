"""Fast encodings against their slow references: values and gradients (fields/encodings.py)."""

import pytest
import torch

from fields import encodings
from fields.encodings import HashGrid, HashGridConfig, TriPlaneConfig, TriPlanes, geometric_resolutions, make_encoding


def _points(n=500, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g)
    # points exactly on the bounds and corners
    x[:8] = torch.tensor([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=torch.float32)
    x[8] = torch.tensor([0.5, 1.0, 0.0])
    return x


def _hash(log2=10):
    # first level dense (fits), later levels hashed; anisotropic (flat slab)
    enc = HashGrid(HashGridConfig([(4, 4, 2), (16, 16, 4), (64, 64, 8), (300, 200, 20)], 2, log2))
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
    return enc


def test_hash_grid_levels_dense_then_hashed():
    enc = _hash()
    assert enc.dense == [True, False, False, False]
    assert enc.out_dim == 8


@pytest.mark.parametrize("make", [_hash, lambda: TriPlanes(TriPlaneConfig([(5, 6, 3), (17, 9, 4)], 4))])
def test_fast_matches_reference_values_and_gradients(make):
    enc = make()
    x = _points()
    fast = enc(x)
    ref = enc.reference_forward(x)
    assert torch.allclose(fast, ref, atol=1e-5), (fast - ref).abs().max()
    g = torch.randn_like(fast)
    (gf,) = torch.autograd.grad((fast * g).sum(), list(enc.parameters()) if isinstance(enc, HashGrid)
                                else [enc.planes[0]])
    (gr,) = torch.autograd.grad((ref * g).sum(), list(enc.parameters()) if isinstance(enc, HashGrid)
                                else [enc.planes[0]])
    assert torch.allclose(gf, gr, atol=1e-4), (gf - gr).abs().max()


def test_compiled_corners_equal_eager_exactly(monkeypatch):
    """The compiled corner kernel gives the eager indices bit for bit and the same weights, at any
    batch size after the first (one dynamic graph), and the gradient still reaches the table."""
    monkeypatch.setenv("UAVSIM_COMPILE", "1")
    enc = _hash()
    for n in (600, 777):
        x = _points(n, n)
        args = (x, enc.res, enc.res_i, enc.hash_mask, enc.offsets, enc.n_dense_prefix)
        idx_e, w_e = encodings._corners(*args)
        idx_c, w_c = enc._indices_weights(x)
        assert torch.equal(idx_c, idx_e)
        assert torch.allclose(w_c, w_e, atol=1e-6)
    assert encodings.compiled_corners()  # it compiled (a failure would have switched it off)
    fast = enc(x)
    assert torch.allclose(fast, enc.reference_forward(x), atol=1e-5)
    (g,) = torch.autograd.grad(fast.sum(), [enc.table])
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_compile_failure_falls_back_to_eager(monkeypatch, caplog):
    monkeypatch.setenv("UAVSIM_COMPILE", "1")
    monkeypatch.setitem(encodings._compiled, "failed", False)

    def broken(*args):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setitem(encodings._compiled, "fn", broken)
    enc = _hash()
    x = _points(300, 5)
    with caplog.at_level("WARNING"):
        out = enc(x)
    assert "eager" in caplog.text
    assert torch.allclose(out, enc.reference_forward(x), atol=1e-5)
    assert not encodings.compiled_corners()


def test_compile_on_by_default(monkeypatch):
    monkeypatch.delenv("UAVSIM_COMPILE", raising=False)
    monkeypatch.setitem(encodings._compiled, "failed", False)
    assert encodings.compiled_corners()


def test_compile_off_by_environment(monkeypatch):
    monkeypatch.setenv("UAVSIM_COMPILE", "0")
    assert not encodings.compiled_corners()
    assert encodings._compiled_corners() is None


def test_planes_all_gradients_match():
    enc = TriPlanes(TriPlaneConfig([(5, 6, 3), (9, 9, 4)], 3))
    x = _points(200, 1)
    g = torch.randn(200, enc.out_dim)
    gf = torch.autograd.grad((enc(x) * g).sum(), list(enc.parameters()))
    gr = torch.autograd.grad((enc.reference_forward(x) * g).sum(), list(enc.parameters()))
    for a, b in zip(gf, gr, strict=True):
        assert torch.allclose(a, b, atol=1e-4)


def test_points_outside_are_clamped_to_faces():
    enc = _hash()
    x = torch.tensor([[-0.5, 0.5, 2.0]])
    assert torch.allclose(enc(x), enc(torch.tensor([[0.0, 0.5, 1.0]])))


def test_hash_is_continuous_across_cells():
    enc = _hash()
    x = torch.tensor([[0.25, 0.5, 0.5]])
    eps = torch.tensor([[1e-6, 0, 0]])
    assert torch.allclose(enc(x - eps), enc(x + eps), atol=1e-3)


def test_make_encoding_and_bad_kind():
    assert make_encoding("hash", [(4, 4, 4)], 2, 8).out_dim == 2
    assert make_encoding("planes", [(4, 4, 4)], 8).out_dim == 8
    with pytest.raises(ValueError, match="unknown encoding"):
        make_encoding("voxels", [(4, 4, 4)], 2)


def test_geometric_resolutions_endpoints():
    r = geometric_resolutions((10, 10, 2), (1000, 1000, 50), 5)
    assert r[0] == (10, 10, 2) and r[-1] == (1000, 1000, 50)
    assert all(a[0] <= b[0] for a, b in zip(r, r[1:], strict=False))
