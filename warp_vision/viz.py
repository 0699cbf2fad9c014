"""Figures (matplotlib, no pyplot: every function draws on a ``matplotlib.figure.Figure``, so no GUI
backend is ever needed; save with ``fig.savefig(path)``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle

__all__ = ["plot_receptive_fields", "plot_retina_layout", "tone_map", "plot_onv", "plot_eye_rays", "plot_image"]


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
    radius (``LayerConnectivity.radius``) is centred at the unit's
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
    conn, prev = _layer_and_inputs(linet_or_connectivity, layer, in_positions)
    radius = conn.radius(prev)
    positions = np.asarray(conn.positions, dtype=np.float64)
    chosen = _chosen_units(units, positions, radius, seed, layer)

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
            np.concatenate(segments), colors=np.repeat(colours, conn.receptive_field), linewidths=0.4, alpha=0.6,
            zorder=2
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


def _layer_and_inputs(linet_or_connectivity, layer, in_positions):
    """(layer ``layer``'s LayerConnectivity, its input positions [N_{h-1}, 2] float64) for
    :func:`plot_receptive_fields`."""
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
    return conns[layer - 1], prev


def _chosen_units(units, positions: np.ndarray, radius: np.ndarray, seed: int, layer: int) -> np.ndarray:
    """The indexes of the units :func:`plot_receptive_fields` draws: ``units`` spread ones for a count,
    else the given indexes (checked)."""
    if isinstance(units, (int, np.integer)) and not isinstance(units, bool):
        if units < 1:
            raise ValueError(f"units: expected a count >= 1 or a sequence of unit indexes, got {units!r}")
        return _spread_units(positions, radius, int(units), seed)
    chosen = np.asarray(units, dtype=np.int64).reshape(-1)
    if chosen.size and (chosen.min() < 0 or chosen.max() >= len(positions)):
        raise ValueError(
            f"units: expected indexes in [0, {len(positions)}) (units of layer {layer}), "
            f"got values in [{chosen.min()}, {chosen.max()}]"
        )
    return chosen


def plot_retina_layout(
    retina,
    ax: Axes | Sequence[Axes] | None = None,
    fovea_radius_deg: float | None = None,
    fovea_count: int = 400,
    max_points: int = 200_000,
    marker_size: float | None = None,
    seed: int = 0,
) -> Figure:
    """Draw a retina's photoreceptors in the retinal domain (paper, Fig. 2b) and zoom on its fovea.

    Left panel: every photoreceptor as a small dot at ``domain_xy`` in degrees of eccentricity (x =
    rho cos theta, y = rho sin theta), equal aspect, the rho_max circle dashed and the zoomed region
    outlined. Right panel: the fovea, rho < ``fovea_radius_deg``, with larger dots.

    Args:
        retina:           a :class:`warp_vision.eye.retina.Retina`.
        ax:               None: a new ``Figure`` with the two panels side by side. A pair of axes: the two
                          panels on them. One ``Axes``: the whole layout only, on it.
        fovea_radius_deg: radius of the zoom [deg]; default: 1.1 x the eccentricity of the
                          ``fovea_count``-th photoreceptor from the fovea.
        fovea_count:      sets the default zoom (>= 1).
        max_points:       at most this many photoreceptors in the left panel (a seeded random subset of
                          larger retinas, said in the title), so millions of points stay drawable.
        marker_size:      dot area [pt^2] in the left panel; default scales with 1 / P.
        seed:             seeds the subset.

    Returns:
        The figure holding the axes.
    """
    if isinstance(fovea_count, bool) or not isinstance(fovea_count, (int, np.integer)) or fovea_count < 1:
        raise ValueError(f"fovea_count: expected an int >= 1, got {fovea_count!r}")
    if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 1:
        raise ValueError(f"max_points: expected an int >= 1, got {max_points!r}")
    xy = np.degrees(np.asarray(retina.domain_xy, dtype=np.float64))
    rho_deg = np.degrees(np.asarray(retina.rho, dtype=np.float64))
    rho_max_deg = float(np.degrees(retina.rho_max))
    P = len(rho_deg)
    if fovea_radius_deg is None:
        k = min(int(fovea_count), P)
        fovea_radius_deg = 1.1 * float(np.partition(rho_deg, k - 1)[k - 1])
        if fovea_radius_deg <= 0.0:
            fovea_radius_deg = rho_max_deg
    elif not np.isfinite(fovea_radius_deg) or fovea_radius_deg <= 0:
        raise ValueError(f"fovea_radius_deg: expected a positive number of degrees, got {fovea_radius_deg!r}")

    axes = _layout_axes(ax)
    shown = np.arange(P)
    if P > max_points:
        shown = np.sort(np.random.default_rng(seed).choice(P, size=int(max_points), replace=False))
    size = float(np.clip(3000.0 / len(shown), 0.02, 4.0)) if marker_size is None else float(marker_size)
    full = axes[0]
    full.scatter(xy[shown, 0], xy[shown, 1], s=size, c="black", linewidths=0, rasterized=True)
    full.add_patch(Circle((0.0, 0.0), rho_max_deg, fill=False, edgecolor="0.5", linestyle="--", linewidth=0.8))
    full.add_patch(Circle((0.0, 0.0), fovea_radius_deg, fill=False, edgecolor="C3", linewidth=0.8))
    lim = 1.03 * rho_max_deg
    full.set_xlim(-lim, lim)
    full.set_ylim(-lim, lim)
    full.set_aspect("equal")
    full.set_xlabel("x = rho cos(theta) [deg of eccentricity]")
    full.set_ylabel("y = rho sin(theta) [deg of eccentricity]")
    subset = f" ({len(shown):,} drawn)" if len(shown) < P else ""
    full.set_title(f"{retina.layout} retina: P = {P:,}{subset}, rho_max = {rho_max_deg:.1f} deg")

    if len(axes) == 2:
        _draw_fovea_zoom(axes[1], xy, rho_deg, fovea_radius_deg)
    return axes[0].get_figure()


def _layout_axes(ax) -> list[Axes]:
    """The axes of :func:`plot_retina_layout`: two new side-by-side panels for None, else ``ax`` (one or
    a pair)."""
    if ax is None:
        fig = Figure(figsize=(11.0, 5.5), layout="constrained")
        return list(fig.subplots(1, 2))
    if isinstance(ax, Axes):
        return [ax]
    axes = list(ax)
    if len(axes) != 2 or not all(isinstance(a, Axes) for a in axes):
        raise ValueError(f"ax: expected None, one Axes or a pair of Axes, got {ax!r}")
    return axes


def _draw_fovea_zoom(zoom: Axes, xy: np.ndarray, rho_deg: np.ndarray, fovea_radius_deg: float) -> None:
    """The right panel of :func:`plot_retina_layout`: the photoreceptors within ``fovea_radius_deg``."""
    near = rho_deg <= 1.05 * fovea_radius_deg
    n_near = int(near.sum())
    zoom_size = float(np.clip(4000.0 / max(n_near, 1), 2.0, 30.0))
    zoom.scatter(xy[near, 0], xy[near, 1], s=zoom_size, c="black", linewidths=0)
    zoom.add_patch(Circle((0.0, 0.0), fovea_radius_deg, fill=False, edgecolor="C3", linewidth=0.8))
    zoom.set_xlim(-fovea_radius_deg, fovea_radius_deg)
    zoom.set_ylim(-fovea_radius_deg, fovea_radius_deg)
    zoom.set_aspect("equal")
    zoom.set_xlabel("x [deg of eccentricity]")
    zoom.set_ylabel("y [deg of eccentricity]")
    inside = int((rho_deg < fovea_radius_deg).sum())
    zoom.set_title(f"fovea: rho < {fovea_radius_deg:.3g} deg ({inside:,} photoreceptors)")


# --------------------------------------------------------------------------------------------------
# ONVs, ray diagrams, images


def tone_map(rgb: np.ndarray, white: float | None = None) -> np.ndarray:
    """Linear radiance/irradiance [..., 3] -> displayable sRGB-ish values in [0, 1].

    Scales so the 99th percentile maps to 1 (or by ``white``), clips, applies a 1/2.2 gamma.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    if white is None:
        white = float(np.percentile(rgb, 99)) if rgb.size else 1.0
    white = white if white > 0 else 1.0
    return np.clip(rgb / white, 0.0, 1.0) ** (1 / 2.2)


def plot_onv(retina, onv, ax: Axes | None = None, white: float | None = None, marker_size: float | None = None,
             mark: Sequence | None = None, title: str | None = None) -> Figure:
    """The ONV as a retina image (paper, Figs. 7 and 11): each photoreceptor a dot of its RGB response.

    retina: a :class:`warp_vision.eye.retina.Retina`; onv: [3P] (one ONV; a torch tensor or array).
    Drawn in the retinal domain (degrees of eccentricity; the optical image is inverted, as on a real
    retina). mark: optional (x_deg, y_deg) points to mark (e.g. the predicted and the true fovea).
    """
    v = onv.detach().cpu().numpy() if hasattr(onv, "detach") else np.asarray(onv)
    if v.size != 3 * retina.P:
        raise ValueError(f"onv: expected {3 * retina.P} values for this retina (P={retina.P}), got {v.size}")
    v = v.reshape(-1, 3)
    if ax is None:
        fig = Figure(figsize=(5.5, 5.5))
        ax = fig.add_subplot(1, 1, 1)
    else:
        fig = ax.figure
    xy = np.degrees(retina.domain_xy)
    size = marker_size if marker_size is not None else max(0.3, min(8.0, 3.0e4 / retina.P))
    ax.set_facecolor("black")
    ax.scatter(xy[:, 0], xy[:, 1], c=tone_map(v, white), s=size, linewidths=0)
    for i, m in enumerate(mark or []):
        ax.plot([m[0]], [m[1]], marker="+x"[i % 2], color="cyan" if i == 0 else "magenta", markersize=12, mew=2)
    ax.set_aspect("equal")
    ax.set_xlabel("retinal x (deg)")
    ax.set_ylabel("retinal y (deg)")
    ax.set_title(title or f"ONV, P = {retina.P:,}")
    return fig


def plot_eye_rays(eye, eccentricities_deg: Sequence[float] = (0.0, 30.0), samples: int = 5, ax: Axes | None = None,
                  world_length_mm: float = 8.0) -> Figure:
    """A photoreceptor's rays through the eye (paper, Fig. 2c): a meridional section of the optics.

    For each eccentricity (deg, in the section's plane), rays from that retina point through
    ``samples`` points across the pupil, refracted by the lens and cornea, in red, green and blue
    (their channel's wavelength), drawn from the float64 optics (:meth:`NavarroEye.trace_path`).
    """
    from warp_vision.eye.optics import CHANNEL_WAVELENGTHS_NM, EYE_CENTRE_MM, RETINA_RADIUS_MM, sag

    if ax is None:
        fig = Figure(figsize=(9, 5))
        ax = fig.add_subplot(1, 1, 1)
    else:
        fig = ax.figure
    # surfaces (z horizontal, y vertical, the world to the left)
    for surf in eye.surfaces():
        y = np.linspace(-surf.semi_diameter, surf.semi_diameter, 200)
        ax.plot(surf.z0 + sag(y, surf.R, surf.Q), y, color="0.3", lw=1)
    a = np.linspace(np.radians(-110), np.radians(110), 300)
    ax.plot(EYE_CENTRE_MM + RETINA_RADIUS_MM * np.cos(a), RETINA_RADIUS_MM * np.sin(a), color="0.5", lw=2)
    r = eye.pupil_radius_mm
    for sgn in (-1, 1):  # the iris
        ax.plot([eye.pupil_z_mm, eye.pupil_z_mm], [sgn * r, sgn * 6.0], color="saddlebrown", lw=3)
    colors = {633.0: "red", 543.0: "green", 458.0: "blue"}
    py = np.linspace(-0.9, 0.9, samples) * r
    for rho in eccentricities_deg:
        q = np.array([0.0, -RETINA_RADIUS_MM * np.sin(np.radians(rho)),
                      EYE_CENTRE_MM + RETINA_RADIUS_MM * np.cos(np.radians(rho))])
        for wl in CHANNEL_WAVELENGTHS_NM:
            path = eye.trace_path(np.repeat(q[None], samples, 0), np.stack([np.zeros(samples), py], 1), wl,
                                  world_length_mm)
            for ray in path:
                if np.all(np.isfinite(ray)):
                    ax.plot(ray[:, 2], ray[:, 1], color=colors[wl], lw=0.6, alpha=0.8)
        ax.plot([q[2]], [q[1]], "ko", ms=4)
    ax.set_aspect("equal")
    ax.set_xlabel("z (mm, optical axis; the world is to the left)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{eye!r}: rays of photoreceptors at {', '.join(f'{e:g}' for e in eccentricities_deg)} deg")
    return fig


def plot_image(image, ax: Axes | None = None, white: float | None = None, title: str | None = None) -> Figure:
    """A rendered camera image [H, W, 3] (linear radiance), tone-mapped."""
    img = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if ax is None:
        fig = Figure(figsize=(img.shape[1] / 80 + 0.5, img.shape[0] / 80 + 0.5))
        ax = fig.add_subplot(1, 1, 1)
    else:
        fig = ax.figure
    ax.imshow(tone_map(img, white))
    ax.set_axis_off()
    if title:
        ax.set_title(title)
    return fig
