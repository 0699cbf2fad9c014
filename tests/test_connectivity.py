"""warp_vision.nn.connectivity (kNN receptive fields, unit positions and ordering of liNet layers) on a
log-polar retina, and warp_vision.frames.morton_order."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from warp_vision.eye.retina import Retina
from warp_vision.frames import morton_order
from warp_vision.nn.connectivity import (
    LayerConnectivity,
    build_connectivity,
    layer_sizes,
    onv_positions,
    receptive_field_radius,
)


@pytest.fixture(scope="module")
def retina() -> np.ndarray:
    """The photoreceptor positions [2000, 2] (retinal domain, rad) of the paper's noisy log-polar retina:
    a foveal disk and rings whose density falls as 1/rho^2, Morton-ordered."""
    return Retina.log_polar(2000, seed=0).domain_xy


@pytest.fixture(scope="module")
def onv_pos(retina) -> np.ndarray:
    return onv_positions(retina)  # [6000, 2]


@pytest.fixture(scope="module")
def conns(onv_pos) -> list[LayerConnectivity]:
    return build_connectivity(onv_pos, layers=3, receptive_field=20, reduction=5, seed=0)


def _previous(onv_pos, conns, h):
    """Positions of layer h - 1 (h >= 1)."""
    return onv_pos if h == 1 else conns[h - 2].positions


def test_onv_positions_repeat_each_photoreceptor_three_times():
    xy = np.array([[0.0, 1.0], [2.0, 3.0]])
    out = onv_positions(xy)
    assert out.shape == (6, 2) and out.dtype == np.float64
    np.testing.assert_array_equal(out, [[0, 1], [0, 1], [0, 1], [2, 3], [2, 3], [2, 3]])
    with pytest.raises(ValueError, match="photoreceptor_xy"):
        onv_positions(np.zeros((4, 3)))


def test_a_retina_given_for_positions_is_told_which_to_pass():
    # it was "in_positions: expected shape [N, 2] with N >= 1, got shape ()"
    from warp_vision.eye.retina import Retina
    from warp_vision.nn import LiNet

    retina = Retina.log_polar(100)
    with pytest.raises(ValueError, match=r"in_positions: expected positions \[N, 2\], got a Retina: pass "
                                         r"retina.domain_xy .* or onv_positions\(retina.domain_xy\)"):
        LiNet(retina, layers=2)
    with pytest.raises(ValueError, match="photoreceptor_xy: expected positions"):
        onv_positions(retina)
    assert LiNet(onv_positions(retina.domain_xy), layers=2, receptive_field=4).in_features == 300


def test_layer_sizes_are_floor_of_previous_over_f(onv_pos):
    conns = build_connectivity(onv_pos, layers=4, receptive_field=[7, 6, 5, 4], reduction=3.5, seed=2)
    sizes = [len(onv_pos)]
    for c in conns:
        sizes.append(c.num_units)
    # 6000 / 3.5 = 1714.28 -> 1714; 1714 / 3.5 = 489.7 -> 489; 489 / 3.5 = 139.7 -> 139; 139 / 3.5 -> 39
    assert sizes == [6000, 1714, 489, 139, 39]
    assert layer_sizes(6000, 4, [7, 6, 5, 4], 3.5) == sizes  # the arithmetic the training configs check first
    assert [c.receptive_field for c in conns] == [7, 6, 5, 4]
    for c in conns:
        assert c.index.dtype == np.int64 and c.positions.dtype == np.float64
        assert c.positions.shape == (c.num_units, 2)


def test_indices_in_range_and_distinct_per_row(onv_pos, conns):
    for h, c in enumerate(conns, start=1):
        n_prev = len(_previous(onv_pos, conns, h))
        assert c.index.shape == (c.num_units, 20)
        assert c.index.min() >= 0 and c.index.max() < n_prev
        srt = np.sort(c.index, axis=1)
        assert (np.diff(srt, axis=1) > 0).all(), f"layer {h}: a row repeats an index"


def test_receptive_fields_are_the_nearest_neighbours_of_a_member(retina):
    """Without repeated positions (no jitter), each unit's centre is one of its previous-layer units, so
    its receptive field is exactly the R nearest neighbours of one of its own members."""
    conns = build_connectivity(retina, layers=2, receptive_field=6, reduction=4, seed=3)
    prev = retina
    for c in conns:
        r = c.receptive_field
        _, knn = cKDTree(prev).query(prev[c.index.reshape(-1)], k=r)  # [N_h * R, R]
        knn = np.sort(knn.reshape(c.num_units, r, r), axis=2)
        is_knn_of_member = (knn == np.sort(c.index, axis=1)[:, None, :]).all(axis=2).any(axis=1)
        assert is_knn_of_member.all()
        prev = c.positions


def test_unit_position_is_mean_of_its_receptive_field(onv_pos, conns):
    for h, c in enumerate(conns, start=1):
        prev = _previous(onv_pos, conns, h)
        np.testing.assert_allclose(c.positions, prev[c.index].mean(axis=1), rtol=0, atol=1e-15)


def test_deterministic_for_a_seed_and_different_across_seeds(onv_pos, conns):
    again = build_connectivity(onv_pos, layers=3, receptive_field=20, reduction=5, seed=0)
    for a, b in zip(conns, again):
        np.testing.assert_array_equal(a.index, b.index)
        np.testing.assert_array_equal(a.positions, b.positions)  # bit-identical
    other = build_connectivity(onv_pos, layers=3, receptive_field=20, reduction=5, seed=1)
    for a, b in zip(conns, other):
        assert a.index.shape == b.index.shape
        assert not np.array_equal(a.positions, b.positions)


def test_duplicated_onv_positions_do_not_give_identical_receptive_fields(conns):
    # Sampling 1200 of the 6000 ONV elements (2000 positions x 3) picks the same position more than once
    # about 2000 * 3 * 0.2^2 = 240 times; unjittered, each of those would duplicate a receptive field.
    # The jitter must leave (nearly) every layer-1 unit with its own field: allow 1 %.
    c = conns[0]
    distinct_rows = len(np.unique(c.index, axis=0))
    assert distinct_rows >= 0.99 * c.num_units


def test_foveated_density_is_kept(onv_pos, conns):
    """The fraction of units inside the central disc holding half the inputs stays about one half.

    Unit centres are a uniform sample without replacement of the previous layer, so the count inside
    the disc is hypergeometric with standard deviation <= sqrt(p (1 - p) / N_h); unit positions are then
    receptive-field means, which a 1/rho^2 density pulls inwards by ~2 % of rho (a <0.5 % change of the
    fraction here). Tolerance: 4 standard deviations + 0.02. A layer of uniform density would put only
    (r_c / r_max)^2 ~ 0.7 % of its units there.
    """
    ecc0 = np.linalg.norm(onv_pos, axis=1)
    r_c = np.median(ecc0)
    p = float((ecc0 < r_c).mean())
    assert abs(p - 0.5) < 0.01
    assert (r_c / ecc0.max()) ** 2 < 0.05
    for c in conns:
        frac = float((np.linalg.norm(c.positions, axis=1) < r_c).mean())
        tol = 4 * math.sqrt(p * (1 - p) / c.num_units) + 0.02
        assert abs(frac - p) < tol, (c.num_units, frac, tol)


def test_receptive_field_radius_grows_with_eccentricity(onv_pos, conns):
    for h, c in enumerate(conns, start=1):
        radius = receptive_field_radius(_previous(onv_pos, conns, h), c)
        ecc = np.linalg.norm(c.positions, axis=1)
        assert spearmanr(ecc, radius).statistic > 0.9, f"layer {h}"
        # and binned: the outer third's median radius is several times the inner third's
        third = np.argsort(ecc)
        k = len(ecc) // 3
        assert np.median(radius[third[-k:]]) > 4 * np.median(radius[third[:k]])


def test_receptive_field_radius_by_hand():
    prev = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 4.0]])
    conn = LayerConnectivity(index=np.array([[0, 1], [0, 2]]), positions=np.array([[1.0, 0.0], [0.0, 2.0]]))
    np.testing.assert_allclose(receptive_field_radius(prev, conn), [1.0, 2.0])


def test_morton_order_gives_locality(onv_pos, conns):
    """Consecutive units read nearby inputs: the mean jump of the index-row mean (and of the position)
    between consecutive units is far below that of a random unit order."""
    rng = np.random.default_rng(123)
    for h, c in enumerate(conns, start=1):
        row_mean = c.index.mean(axis=1)
        perm = rng.permutation(c.num_units)
        ordered = np.abs(np.diff(row_mean)).mean()
        shuffled = np.abs(np.diff(row_mean[perm])).mean()
        assert ordered < 0.3 * shuffled, f"layer {h}: {ordered} vs {shuffled}"
        step = np.linalg.norm(np.diff(c.positions, axis=0), axis=1).mean()
        step_shuffled = np.linalg.norm(np.diff(c.positions[perm], axis=0), axis=1).mean()
        assert step < 0.5 * step_shuffled, f"layer {h}"
        np.testing.assert_array_equal(morton_order(c.positions), np.arange(c.num_units))


def test_morton_order_on_a_grid():
    # A 4x4 grid listed row by row; Z-order visits 2x2 blocks: (0,0) (1,0) (0,1) (1,1) (2,0) ...
    y, x = np.divmod(np.arange(16), 4)
    order = morton_order(np.stack([x, y], axis=1).astype(float))
    np.testing.assert_array_equal(order, [0, 1, 4, 5, 2, 3, 6, 7, 8, 9, 12, 13, 10, 11, 14, 15])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(in_positions=np.zeros((10, 3))), "in_positions"),
        (dict(in_positions=np.zeros((10,))), "in_positions"),
        (dict(in_positions=np.array([[0.0, np.nan]] * 10)), "in_positions"),
        (dict(layers=0), "layers"),
        (dict(layers=3, reduction=5), "layers"),  # 10 -> 2 -> 0 units
        (dict(receptive_field=11), "receptive_field"),  # R_1 > N_0 = 10
        (dict(layers=2, reduction=2, receptive_field=[3, 6]), "receptive_field"),  # R_2 > N_1 = 5
        (dict(layers=2, receptive_field=[3]), "receptive_field"),
        (dict(receptive_field=0), "receptive_field"),
        (dict(reduction=0.5), "reduction"),
        (dict(reduction=float("nan")), "reduction"),
        (dict(seed=1.5), "seed"),
    ],
)
def test_value_errors(kwargs, match):
    args = dict(in_positions=np.random.default_rng(0).random((10, 2)), layers=1, receptive_field=3, reduction=2)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        build_connectivity(**args)
