"""The host-built BVH and the packet queries that traverse it."""

import numpy as np
import pytest
import trimesh

from warp_vision.frames import translation
from warp_vision.kernels import render as rt
from warp_vision.kernels.render import reference as ref
from warp_vision.kernels.render.bvh import MAX_LEAF, build_bvh
from warp_vision.scene import Material, Scene


def soup(n=3000, seed=0):
    """Random small triangles in a unit cube plus a large ground quad (mixed sizes stress the SAH)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-1, 1, (n, 1, 3))
    V = (c + rng.normal(scale=0.05, size=(n, 3, 3))).reshape(-1, 3)
    F = np.arange(3 * n).reshape(n, 3)
    V = np.vstack([V, [[-3, -3, -1.5], [3, -3, -1.5], [3, 3, -1.5], [-3, 3, -1.5]]])
    F = np.vstack([F, [[3 * n, 3 * n + 1, 3 * n + 2], [3 * n, 3 * n + 2, 3 * n + 3]]])
    return V, F


def test_bvh_structure():
    V, F = soup()
    b = build_bvh(V, F)
    leaves = b.node_left < 0
    assert b.node_count[leaves].max() <= MAX_LEAF and b.node_count[leaves].min() >= 1
    # every triangle in exactly one leaf
    covered = np.concatenate([np.arange(s, s + c) for s, c in zip(b.node_start[leaves], b.node_count[leaves])])
    assert np.array_equal(np.sort(covered), np.arange(len(F)))
    assert np.array_equal(np.sort(b.tri_face), np.arange(len(F)))
    # triangles in leaf order reproduce the faces
    tri = V[F[b.tri_face]]
    np.testing.assert_allclose(b.tri_v0, tri[:, 0], atol=1e-6)
    np.testing.assert_allclose(b.tri_v0 + b.tri_e1, tri[:, 1], atol=1e-6)
    np.testing.assert_allclose(b.tri_v0 + b.tri_e2, tri[:, 2], atol=1e-6)
    # boxes contain their leaves' triangles and their children
    for i in np.nonzero(leaves)[0]:
        t = tri[b.node_start[i] : b.node_start[i] + b.node_count[i]].reshape(-1, 3)
        assert np.all(t >= b.node_lo[i] - 1e-6) and np.all(t <= b.node_hi[i] + 1e-6)
    inner = np.nonzero(~leaves)[0]
    for ch in (b.node_left[inner], b.node_left[inner] + 1):
        assert np.all(b.node_lo[ch] >= b.node_lo[inner] - 1e-6) and np.all(b.node_hi[ch] <= b.node_hi[inner] + 1e-6)
    assert b.depth() < 40


def test_bvh_bad_faces():
    with pytest.raises(ValueError, match="faces"):
        build_bvh(np.zeros((3, 3)), np.array([[0, 1, 5]]))
    with pytest.raises(ValueError, match="faces"):
        build_bvh(np.zeros((3, 3)), np.zeros((0, 3), dtype=int))


def test_packet_closest_hit_matches_brute_force(device):
    V, F = soup(2000, seed=1)
    sc = Scene()
    sc.add("soup", trimesh.Trimesh(V, F, process=False), Material(), static=True)
    sc.add_sphere("ball", 0.3, (0.2, 0.1, 0.0))
    rng = np.random.default_rng(2)
    n = 4001  # not a multiple of the packet width
    o = rng.normal(size=(n, 3)) * 3
    d = rng.uniform(-1, 1, size=(n, 3)) - o / 3
    d[:50, 0] = 0.0  # axis-parallel rays (zero direction components)
    d[50:100, :2] = 0.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, obj, face = rt.closest_hit(sc, o, d, device=device)
    tr, objr, facer, _, _ = ref.closest_hit_ref(sc, o, d)
    hit = np.isfinite(tr)
    assert 0.3 < hit.mean() < 0.95
    assert np.array_equal(np.isfinite(t), hit)
    np.testing.assert_allclose(t[hit], tr[hit], rtol=1e-5, atol=1e-5)
    assert np.mean((obj == objr) & (face == facer)) > 0.998
    # a moved dynamic object: the same answer as the reference after set_transform
    sc.set_transform("ball", translation([-0.5, 0.4, 0.3]))
    t2, obj2, _ = rt.closest_hit(sc, o, d, device=device)
    tr2, objr2, *_ = ref.closest_hit_ref(sc, o, d)
    assert np.array_equal(np.isfinite(t2), np.isfinite(tr2))
    assert np.mean(obj2 == objr2) > 0.998


def test_large_meshes_keep_their_bvh_on_disk(tmp_path, monkeypatch, unclose_npz_headers):
    """The second build of the same mesh is a load (the builder is never called), equal to the first; a
    corrupt file is rebuilt; small meshes and WARP_VISION_CACHE=off never touch the disk."""
    import trimesh

    from warp_vision.kernels.render import bvh as B

    mesh = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces)
    monkeypatch.setenv("WARP_VISION_CACHE", str(tmp_path))
    monkeypatch.setattr(B, "DISK_CACHE_MIN_TRIANGLES", 100)
    first = B.build_bvh_cached(V, F)
    files = list((tmp_path / "bvh").glob("*.npz"))
    assert len(files) == 1
    real = B.build_bvh
    monkeypatch.setattr(B, "build_bvh", lambda *a: (_ for _ in ()).throw(AssertionError("rebuilt")))
    again = B.build_bvh_cached(V, F)
    for f in ("node_lo", "node_left", "tri_v0", "tri_face"):
        np.testing.assert_array_equal(getattr(again, f), getattr(first, f))
    monkeypatch.setattr(B, "build_bvh", real)
    for damage in (lambda p: p.write_bytes(b"not a zip"), unclose_npz_headers):
        damage(files[0])
        rebuilt = B.build_bvh_cached(V, F)
        np.testing.assert_array_equal(rebuilt.tri_face, first.tri_face)
        with np.load(files[0]) as z:  # replaced by a good file
            assert len(z["tri_face"]) == len(F)
    monkeypatch.setattr(B, "DISK_CACHE_MIN_TRIANGLES", 10**9)
    B.build_bvh_cached(V * 2, F)
    monkeypatch.setattr(B, "DISK_CACHE_MIN_TRIANGLES", 100)
    monkeypatch.setenv("WARP_VISION_CACHE", "off")
    B.build_bvh_cached(V * 3, F)
    assert len(list((tmp_path / "bvh").glob("*.npz"))) == 1
