"""liNet connectivity: unit positions and k-nearest-neighbour receptive fields per layer (paper, IV.A).

All positions live in the 2D retinal domain (docs/ARCHITECTURE.md: the azimuthal-equidistant projection
of the retina around the fovea), in whatever units the caller's positions use; Euclidean distance there
is the paper's (rho, theta) domain. Layer 0 is the input (the ONV: element 3p + c sits at photoreceptor
p's position, :func:`onv_positions`); layers h = 1..H are hidden layers of N_h = floor(N_{h-1} / f)
units, each connected to its R_h nearest units of layer h - 1.

Plain numpy + scipy ``cKDTree``; deterministic for a seed (bit-identical on repeat).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from warp_vision.frames import check_positions, morton_order

__all__ = [
    "LayerConnectivity",
    "build_connectivity",
    "layer_sizes",
    "onv_positions",
    "receptive_field_radius",
]


@dataclass
class LayerConnectivity:
    """The connectivity of one hidden layer h (the paper's matrix C_h) and its units' positions.

    index:     [N_h, R_h] int64; row n holds the indexes (into layer h - 1, in its stored order) of
               unit n's receptive field, R_h distinct units, ascending.
    positions: [N_h, 2] float64; unit n's position in the retinal domain (same units as the input
               positions) = the mean position of its receptive field.
    """

    index: np.ndarray
    positions: np.ndarray

    @property
    def num_units(self) -> int:
        """N_h."""
        return int(self.index.shape[0])

    @property
    def receptive_field(self) -> int:
        """R_h."""
        return int(self.index.shape[1])

    def radius(self, layer_prev_positions: np.ndarray) -> np.ndarray:
        """[N_h] radius of each unit's receptive field: :func:`receptive_field_radius`."""
        return receptive_field_radius(layer_prev_positions, self)


def onv_positions(photoreceptor_xy: np.ndarray) -> np.ndarray:
    """Positions of the ONV elements: element 3p + c (channel c of photoreceptor p) sits at p's position.

    Args:
        photoreceptor_xy: [P, 2] photoreceptor positions in the retinal domain.

    Returns:
        [3P, 2] float64, each row of ``photoreceptor_xy`` repeated 3 times in place.
    """
    xy = check_positions("photoreceptor_xy", photoreceptor_xy)
    return np.repeat(xy, 3, axis=0)


def _jitter_duplicates(centres: np.ndarray, prev: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Move every repeat of an already-seen centre by half its nearest-distinct-neighbour distance.

    The ONV repeats each photoreceptor position 3 times, so sampled centres can coincide; left as they
    are, such units would get identical receptive fields. ``centres`` [M, 2] are rows of ``prev``
    [N, 2]; each repeat (not the first occurrence) is moved in a uniformly random direction by 0.5 x
    the distance from its position to the nearest *different* position in ``prev``.
    """
    _, first = np.unique(centres, axis=0, return_index=True)
    repeat = np.ones(len(centres), dtype=bool)
    repeat[first] = False
    if not repeat.any():
        return centres
    distinct = np.unique(prev, axis=0)
    if len(distinct) < 2:  # every position is the same point: nothing to move towards
        return centres
    # k=2: the first neighbour is the centre itself (distance 0), the second the nearest distinct one.
    dist, _ = cKDTree(distinct).query(centres[repeat], k=2, workers=-1)
    step = 0.5 * dist[:, 1]
    angle = rng.uniform(0.0, 2.0 * np.pi, size=int(repeat.sum()))
    out = centres.copy()
    out[repeat] += step[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return out


def _receptive_fields(receptive_field: int | Sequence[int], layers: int) -> list[int]:
    if isinstance(receptive_field, (int, np.integer)) and not isinstance(receptive_field, bool):
        rfs = [int(receptive_field)] * layers
    elif isinstance(receptive_field, Sequence) and not isinstance(receptive_field, str):
        if len(receptive_field) != layers:
            raise ValueError(
                f"receptive_field: expected an int or a sequence of length layers={layers}, "
                f"got a sequence of length {len(receptive_field)}"
            )
        rfs = list(receptive_field)
    else:
        raise ValueError(f"receptive_field: expected an int or a sequence of ints, got {receptive_field!r}")
    for h, r in enumerate(rfs, start=1):
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 1:
            raise ValueError(f"receptive_field: expected R_{h} to be an int >= 1, got {r!r}")
    return [int(r) for r in rfs]


def layer_sizes(n_in: int, layers: int, receptive_field: int | Sequence[int], reduction: float) -> list[int]:
    """[N_0 = n_in, N_1, ..., N_H] of a liNet of H = ``layers`` hidden layers with the receptive fields
    ``receptive_field`` (one int, or R_1..R_H): N_h = floor(N_(h-1) / f). A ValueError names the layer left
    empty, or the receptive field larger than the layer it reads (checked by the training configs before
    any data is rendered: arithmetic only)."""
    sizes = [int(n_in)]
    for h, r in enumerate(_receptive_fields(receptive_field, layers), start=1):
        n = math.floor(sizes[-1] / reduction)
        if n < 1:
            raise ValueError(
                f"layers: expected every layer to keep N_h = floor(N_(h-1) / f) >= 1, got N_{h} = "
                f"floor({sizes[-1]} / {reduction}) = {n}"
            )
        if r > sizes[-1]:
            raise ValueError(
                f"receptive_field: expected R_{h} <= N_{h - 1} = {sizes[-1]} (units in layer {h - 1}), got {r}"
            )
        sizes.append(n)
    return sizes


def build_connectivity(
    in_positions: np.ndarray,
    layers: int,
    receptive_field: int | Sequence[int],
    reduction: float,
    seed: int = 0,
) -> list[LayerConnectivity]:
    """Build the H connectivity matrices of a liNet over irregular, foveated inputs.

    For each hidden layer h = 1..H:

    1. N_h = floor(N_{h-1} / f) unit centres are drawn without replacement from layer h - 1's units
       (a seeded ``numpy`` Generator), so the layer keeps the foveated density in expectation; repeats
       of one position (the ONV holds each photoreceptor's position 3 times) are jittered by half the
       local nearest-distinct-neighbour distance in a random direction.
    2. Each unit's receptive field = the R_h nearest (Euclidean, 2D) units of layer h - 1 to its centre
       (``cKDTree.query``), and its position = the mean position of its receptive field (paper, IV.A).
    3. The units are ordered along a Morton (Z-order) curve of their positions (rows of index and
       positions permuted together), so consecutive units read nearby inputs; layer h + 1's indexes
       refer to this order.

    Args:
        in_positions:    [N_0, 2] positions of the input units in the retinal domain (for an ONV input,
                         :func:`onv_positions` of the photoreceptors). Any units; outputs use the same.
        layers:          H >= 1, the number of hidden layers.
        receptive_field: R_h, one int for every layer or a sequence of H ints; 1 <= R_h <= N_{h-1}.
        reduction:       f >= 1, the size ratio N_{h-1} / N_h before flooring.
        seed:            seeds the sampling and jitter; the same seed gives bit-identical results.

    Returns:
        H :class:`LayerConnectivity` objects, for layers 1..H.

    Raises:
        ValueError: naming the argument, what was expected and what came (bad shapes, non-finite
            positions, H < 1, f < 1, a receptive field larger than its previous layer, an empty layer).
    """
    prev = check_positions("in_positions", in_positions)
    if isinstance(layers, bool) or not isinstance(layers, (int, np.integer)) or layers < 1:
        raise ValueError(f"layers: expected an int >= 1, got {layers!r}")
    rfs = _receptive_fields(receptive_field, int(layers))
    if isinstance(reduction, bool) or not isinstance(reduction, (int, float, np.integer, np.floating)):
        raise ValueError(f"reduction: expected a finite number >= 1, got {reduction!r}")
    if not math.isfinite(reduction) or reduction < 1:
        raise ValueError(f"reduction: expected a finite number >= 1, got {reduction!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed: expected an int, got {seed!r}")

    sizes = layer_sizes(len(prev), int(layers), rfs, reduction)

    rng = np.random.default_rng(int(seed))
    out: list[LayerConnectivity] = []
    for h, r in enumerate(rfs, start=1):
        n = sizes[h]
        chosen = rng.choice(len(prev), size=n, replace=False)
        centres = _jitter_duplicates(prev[chosen], prev, rng)
        _, index = cKDTree(prev).query(centres, k=r, workers=-1)
        index = np.sort(index.reshape(n, r).astype(np.int64), axis=1)  # ascending: monotone gathers
        positions = prev[index].mean(axis=1)
        order = morton_order(positions)
        index, positions = index[order], positions[order]
        out.append(LayerConnectivity(index=np.ascontiguousarray(index), positions=np.ascontiguousarray(positions)))
        prev = positions
    return out


def receptive_field_radius(layer_prev_positions: np.ndarray, conn: LayerConnectivity) -> np.ndarray:
    """Radius of each unit's receptive field: the largest distance from the unit to one of its members.

    Args:
        layer_prev_positions: [N_{h-1}, 2] positions of layer h - 1's units (in their stored order).
        conn:                 layer h's connectivity (index into ``layer_prev_positions``).

    Returns:
        [N_h] float64, in the units of the positions.
    """
    prev = check_positions("layer_prev_positions", layer_prev_positions)
    index = np.asarray(conn.index)
    if index.size and (index.min() < 0 or index.max() >= len(prev)):
        raise ValueError(
            f"conn: expected index values in [0, {len(prev)}) (rows of layer_prev_positions), "
            f"got values in [{index.min()}, {index.max()}]"
        )
    members = prev[index]  # [N_h, R_h, 2]
    return np.linalg.norm(members - np.asarray(conn.positions)[:, None, :], axis=-1).max(axis=1)
