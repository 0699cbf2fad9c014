"""Figures (matplotlib, no pyplot: every function draws on a ``matplotlib.figure.Figure``, so no GUI
backend is ever needed; save with ``fig.savefig(path)``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from warp_vision.nn.connectivity import receptive_field_radius

__all__ = ["plot_receptive_fields"]


def _spread_units(positions: np.ndarray, radius: np.ndarray, count: int, seed: int) -> np.ndarray:
    """Pick ``count`` units spread over the retina at every scale: farthest-point sampling under the
    distance |p_i - p_j| / (r_i + r_j), so the small foveal fields are sampled as well as the large
    peripheral ones. The first unit is drawn with ``seed``. Returns [count] int64 unit indexes."""
    n = len(positions)
    count = min(count, n)
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(n))]
    scale = np.maximum(radius, np.finfo(np.float64).tiny)
    nearest = np.full(n, np.inf)
    for _ in range(count - 1):
        last = chosen[-1]
        d = np.linalg.norm(positions - positions[last], axis=1) / (scale + scale[last])
        nearest = np.minimum(nearest, d)
        nearest[chosen] = -1.0
        chosen.append(int(np.argmax(nearest)))
    return np.asarray(chosen, dtype=np.int64)


def plot_receptive_fields(
    linet_or_connectivity,
    layer: int = 1,
    units: int | Sequence[int] = 40,
    ax: Axes | None = None,
    seed: int = 0,
    in_positions: np.ndarray | None = None,
) -> Figure:
    """Draw the receptive fields of some units of one liNet layer over its input units (paper, Fig. 3).

    The previous layer's units are small black dots; for each drawn unit, a circle of its receptive-field
    radius (:func:`warp_vision.nn.connectivity.receptive_field_radius`) is centred at the unit's
    position, with thin lines from the unit to its R_h members. On a foveated layout the circles
    overlap and grow with eccentricity.

    Args:
        linet_or_connectivity: a :class:`warp_vision.nn.LiNet`, or the list of
            :class:`~warp_vision.nn.connectivity.LayerConnectivity` from ``build_connectivity``.
        layer:        h in [1, H], the hidden layer whose receptive fields are drawn.
        units:        how many units to draw (spread over the retina, see below), or their indexes.
        ax:           axes to draw on; a new ``Figure`` with one axes when None.
        seed:         seeds the choice of units when ``units`` is a count.
        in_positions: [N_0, 2] input positions; needed only for a connectivity list and ``layer == 1``.

    Returns:
        The figure holding ``ax``. Exactly one ``Circle`` patch is added per drawn unit.
    """
    if isinstance(linet_or_connectivity, Sequence):
        conns = list(linet_or_connectivity)
        num_layers = len(conns)
    else:  # a LiNet: read its (possibly loaded) buffers
        net = linet_or_connectivity
        conns = net.connectivity()
        num_layers = len(conns)
        in_positions = net.layer_positions(0).detach().cpu().numpy()
    if isinstance(layer, bool) or not isinstance(layer, (int, np.integer)) or not 1 <= layer <= num_layers:
        raise ValueError(f"layer: expected an int in [1, {num_layers}], got {layer!r}")
    if layer == 1:
        if in_positions is None:
            raise ValueError("in_positions: expected the [N_0, 2] input positions to draw layer 1, got None")
        prev = np.asarray(in_positions, dtype=np.float64)
    else:
        prev = np.asarray(conns[layer - 2].positions, dtype=np.float64)
    conn = conns[layer - 1]
    radius = receptive_field_radius(prev, conn)
    positions = np.asarray(conn.positions, dtype=np.float64)
    if isinstance(units, (int, np.integer)) and not isinstance(units, bool):
        if units < 1:
            raise ValueError(f"units: expected a count >= 1 or a sequence of unit indexes, got {units!r}")
        chosen = _spread_units(positions, radius, int(units), seed)
    else:
        chosen = np.asarray(units, dtype=np.int64).reshape(-1)
        if chosen.size and (chosen.min() < 0 or chosen.max() >= len(positions)):
            raise ValueError(
                f"units: expected indexes in [0, {len(positions)}) (units of layer {layer}), "
                f"got values in [{chosen.min()}, {chosen.max()}]"
            )

    if ax is None:
        fig = Figure(figsize=(6.0, 6.0), layout="constrained")
        ax = fig.add_subplot()
    colours = [f"C{i % 10}" for i in range(len(chosen))]
    ax.scatter(prev[:, 0], prev[:, 1], s=1.0, c="black", linewidths=0, zorder=1)
    segments = [
        np.stack([np.broadcast_to(positions[n], (conn.receptive_field, 2)), prev[conn.index[n]]], axis=1)
        for n in chosen
    ]
    if segments:
        lines = LineCollection(
            np.concatenate(segments), colors=np.repeat(colours, conn.receptive_field), linewidths=0.4, alpha=0.6, zorder=2
        )
        ax.add_collection(lines)
    for n, colour in zip(chosen, colours):
        ax.add_patch(Circle(tuple(positions[n]), radius[n], fill=False, edgecolor=colour, linewidth=1.0, zorder=3))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("retinal x (units of the input positions)")
    ax.set_ylabel("retinal y (units of the input positions)")
    ax.set_title(
        f"Layer {layer} receptive fields: {len(chosen)} of {conn.num_units} units, R = {conn.receptive_field}"
    )
    return ax.get_figure()
