"""The :class:`Retina`: one eye's photoreceptors with all their coordinates, saved and loaded as .npz.

The layouts themselves (noisy log-polar, human cone density) and the retina's geometry are in
:mod:`warp_vision.eye.layouts` (see docs/ARCHITECTURE.md, "Frames and units"). A :class:`Retina` orders its
photoreceptors along a Morton (Z-order) curve of ``domain_xy`` (:func:`warp_vision.frames.morton_order`)
so that neighbours on the retina are neighbours in memory (and in the ONV).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from warp_vision.eye.layouts import (
    RETINA_RADIUS_M,
    _check_angle,
    _check_seed,
    _domain_xy,
    cone_density_layout,
    default_rho_min,
    eye_positions_m,
    noisy_log_polar,
)
from warp_vision.eye.optics import NavarroEye, eye_from_optical_dir, optical_from_eye
from warp_vision.fileio import NPY_FORMAT_ERRORS, atomic_write
from warp_vision.frames import gaze_angles, morton_order

__all__ = ["Retina"]

_FORMAT_VERSION = 1
_SAVED_KEYS = ("format_version", "rho", "theta", "seed", "layout", "rho_max", "params_json")


@dataclass(eq=False)
class Retina:
    """One eye's photoreceptors: P points on the 12 mm retina sphere, in Morton order of ``domain_xy``.

    Row p of every array is photoreceptor p, the one whose irradiance is ONV elements 3p..3p+2.
    Build with :meth:`log_polar`, :meth:`cone_density` or :meth:`from_polar`; the fields are
    consistent with each other only as those constructors make them.

    Fields:
        rho:                  [P] float64, eccentricity [rad], angle at the eyeball centre from the fovea,
                              in [0, rho_max].
        theta:                [P] float64, polar angle [rad] in [0, 2 pi), from the eye frame's +x towards +y.
        domain_xy:            [P, 2] float64, retinal-domain position rho * (cos theta, sin theta) [rad]
                              (the liNet input positions).
        positions_eye_m:      [P, 3] float64, position in the eye frame [m] (:func:`eye_positions_m`).
        positions_optical_mm: [P, 3] float64, position in the optical frame [mm]
                              (``optics.optical_from_eye(positions_eye_m)``).
        seed:                 the seed the layout was drawn with.
        layout:               the layout's name: "log_polar", "cone_density", or the caller's.
        rho_max:              the largest eccentricity the layout may use [rad], in (0, pi].
        params:               the layout's settings (JSON-serialisable dict, e.g. rho_min, noise, fov_deg,
                              eye), kept for provenance and saved with the retina.
    """

    rho: np.ndarray
    theta: np.ndarray
    domain_xy: np.ndarray
    positions_eye_m: np.ndarray
    positions_optical_mm: np.ndarray
    seed: int
    layout: str
    rho_max: float
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        rho = np.asarray(self.rho)
        P = rho.shape[0] if rho.ndim == 1 else -1
        if P < 1:
            raise ValueError(f"rho: expected shape [P] with P >= 1, got shape {rho.shape}")
        for name, shape in (
            ("rho", (P,)),
            ("theta", (P,)),
            ("domain_xy", (P, 2)),
            ("positions_eye_m", (P, 3)),
            ("positions_optical_mm", (P, 3)),
        ):
            arr = getattr(self, name)
            if not isinstance(arr, np.ndarray) or arr.shape != shape or arr.dtype != np.float64:
                got = f"shape {arr.shape}, dtype {arr.dtype}" if isinstance(arr, np.ndarray) else type(arr).__name__
                raise ValueError(f"{name}: expected a float64 ndarray of shape {shape}, got {got}")
            if not np.isfinite(arr).all():
                raise ValueError(f"{name}: expected finite values, got NaN or inf")
        self.rho_max = _check_angle("rho_max", self.rho_max, 0.0, math.pi)
        if rho.min() < 0.0 or rho.max() > self.rho_max:
            raise ValueError(
                f"rho: expected values in [0, rho_max = {self.rho_max!r}], got [{rho.min()!r}, {rho.max()!r}]"
            )
        if self.theta.min() < 0.0 or self.theta.max() >= 2.0 * math.pi:
            raise ValueError(
                f"theta: expected values in [0, 2 pi), got [{self.theta.min()!r}, {self.theta.max()!r}]"
            )
        self.seed = _check_seed(self.seed)
        if not isinstance(self.layout, str) or not self.layout:
            raise ValueError(f"layout: expected a non-empty str, got {self.layout!r}")
        if not isinstance(self.params, dict):
            raise ValueError(f"params: expected a dict, got {type(self.params).__name__}")

    @property
    def P(self) -> int:
        """Number of photoreceptors."""
        return int(self.rho.shape[0])

    @property
    def inward_normals_eye(self) -> np.ndarray:
        """[P, 3] float64 unit vectors in the eye frame from each photoreceptor towards the eyeball centre."""
        return -self.positions_eye_m / RETINA_RADIUS_M

    def visual_angles(self, eye=None, wavelength_nm: float = 589.0) -> np.ndarray:
        """[P, 2] float64 (yaw, pitch) [rad] of the world direction each photoreceptor sees: its chief ray
        (through the pupil centre) leaving the cornea, in the eye frame, with the foveation targets'
        convention (:func:`warp_vision.frames.gaze_angles`): ``yaw = atan2(x, z)``,
        ``pitch = atan2(y, hypot(x, z))``. The image is inverted, so a photoreceptor at polar angle theta
        sees the field near theta + pi. NaN where the chief ray is blocked.

        Args:
            eye: the :class:`NavarroEye` (accommodation and pupil); default ``NavarroEye()``.
        """
        eye = NavarroEye() if eye is None else eye
        _, d, valid = eye.chief_ray(self.positions_optical_mm, wavelength_nm)
        out = gaze_angles(eye_from_optical_dir(d))
        out[~valid] = np.nan
        return out

    def local_spacing_rad(self) -> np.ndarray:
        """[P] float64: each photoreceptor's distance to its nearest neighbour in the retinal domain [rad]."""
        from scipy.spatial import cKDTree

        if self.P < 2:
            return np.full(self.P, np.inf)
        dist, _ = cKDTree(self.domain_xy).query(self.domain_xy, k=2)
        return dist[:, 1]

    # --- constructors ---
    @classmethod
    def from_polar(
        cls,
        rho,
        theta,
        seed: int,
        layout: str,
        rho_max: float,
        params: dict | None = None,
        morton: bool = True,
    ) -> Retina:
        """The general constructor: a retina from eccentricities and polar angles.

        Args:
            rho:     [P] eccentricities [rad] in [0, rho_max].
            theta:   [P] polar angles [rad] (any real; stored modulo 2 pi).
            seed:    the seed the layout was drawn with (recorded).
            layout:  the layout's name (recorded).
            rho_max: the layout's largest eccentricity [rad], in (0, pi].
            params:  JSON-serialisable layout settings to record (default: none).
            morton:  reorder the photoreceptors along the Morton curve of their ``domain_xy``
                     (:func:`warp_vision.frames.morton_order`); False keeps the given order.

        Returns:
            A :class:`Retina` with every coordinate derived from (rho, theta).

        Raises:
            ValueError: shapes that differ or are not [P] with P >= 1, non-finite values, rho outside
                [0, rho_max], a bad rho_max, seed, layout or params.
        """
        rho = np.array(rho, dtype=np.float64, copy=True)
        theta = np.array(theta, dtype=np.float64, copy=True)
        if rho.ndim != 1 or rho.shape[0] < 1 or theta.shape != rho.shape:
            raise ValueError(
                f"rho, theta: expected two arrays of the same shape [P] with P >= 1, got {rho.shape} and {theta.shape}"
            )
        if not (np.isfinite(rho).all() and np.isfinite(theta).all()):
            raise ValueError("rho, theta: expected finite values, got NaN or inf")
        rho_max = _check_angle("rho_max", rho_max, 0.0, math.pi)
        if rho.min() < 0.0 or rho.max() > rho_max:
            raise ValueError(f"rho: expected values in [0, rho_max = {rho_max!r}], got [{rho.min()!r}, {rho.max()!r}]")
        params = {} if params is None else dict(params)
        try:
            json.dumps(params)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"params: expected a JSON-serialisable dict, got {params!r} ({exc})") from None
        theta = np.mod(theta, 2.0 * math.pi)
        theta[theta >= 2.0 * math.pi] = 0.0
        xy = _domain_xy(rho, theta)
        if morton and rho.shape[0] > 1:
            order = morton_order(xy)
            rho, theta, xy = rho[order], theta[order], xy[order]
        eye = eye_positions_m(rho, theta)
        return cls(
            rho=rho,
            theta=theta,
            domain_xy=np.ascontiguousarray(xy),
            positions_eye_m=eye,
            positions_optical_mm=optical_from_eye(eye),
            seed=seed,
            layout=layout,
            rho_max=rho_max,
            params=params,
        )

    @staticmethod
    def _rho_max_for(eye, fov_deg: float) -> tuple[float, str]:
        """(rho_max [rad], repr of the eye) for the layout constructors."""
        eye = NavarroEye() if eye is None else eye
        return float(eye.retina_eccentricity_limit(fov_deg)), repr(eye)

    @classmethod
    def log_polar(cls, P: int = 14400, seed: int = 0, eye=None, fov_deg: float = 167.5, **layout_kwargs) -> Retina:
        """The paper's noisy log-polar retina (:func:`noisy_log_polar`), Morton-ordered.

        Args:
            P:             number of photoreceptors (positive int); the paper uses 14,400.
            seed:          seeds the layout (non-negative int).
            eye:           the eye whose lit retina bounds the layout: anything with
                           ``retina_eccentricity_limit(fov_deg) -> rad``; default ``NavarroEye()`` (relaxed,
                           4 mm pupil).
            fov_deg:       the full field of view [deg] (paper: 167.5); rho_max =
                           ``eye.retina_eccentricity_limit(fov_deg)``.
            layout_kwargs: ``rho_min`` [rad], ``noise`` (see :func:`noisy_log_polar`).
        """
        rho_max, eye_repr = cls._rho_max_for(eye, fov_deg)
        rho_min = layout_kwargs.pop("rho_min", None)
        if rho_min is None:
            rho_min = default_rho_min(rho_max)
        noise = layout_kwargs.pop("noise", 0.15)
        if layout_kwargs:
            raise ValueError(f"layout_kwargs: expected only rho_min and noise, got {sorted(layout_kwargs)}")
        rho, theta = noisy_log_polar(P, rho_max, seed, rho_min=rho_min, noise=noise)
        params = {"rho_min": float(rho_min), "noise": float(noise), "fov_deg": float(fov_deg), "eye": eye_repr}
        return cls.from_polar(rho, theta, seed, "log_polar", rho_max, params)

    @classmethod
    def cone_density(cls, P: int, seed: int = 0, eye=None, fov_deg: float = 167.5, **layout_kwargs) -> Retina:
        """A retina with the human cone density profile (:func:`cone_density_layout`), Morton-ordered.

        Args as :meth:`log_polar`; ``layout_kwargs``: ``noise``.
        """
        rho_max, eye_repr = cls._rho_max_for(eye, fov_deg)
        noise = layout_kwargs.pop("noise", 0.15)
        if layout_kwargs:
            raise ValueError(f"layout_kwargs: expected only noise, got {sorted(layout_kwargs)}")
        rho, theta = cone_density_layout(P, rho_max, seed, noise=noise)
        params = {"noise": float(noise), "fov_deg": float(fov_deg), "eye": eye_repr}
        return cls.from_polar(rho, theta, seed, "cone_density", rho_max, params)

    # --- files ---
    def save(self, path: str | os.PathLike) -> None:
        """Write the retina to ``path`` (an .npz archive, exactly that name), atomically
        (:func:`warp_vision.fileio.atomic_write`).

        Stores rho, theta, seed, layout, rho_max and params (as JSON); the other fields are derived on
        load.
        """

        def write(f) -> None:
            np.savez(
                f,
                format_version=np.int64(_FORMAT_VERSION),
                rho=self.rho,
                theta=self.theta,
                seed=np.int64(self.seed),
                layout=np.str_(self.layout),
                rho_max=np.float64(self.rho_max),
                params_json=np.str_(json.dumps(self.params, sort_keys=True)),
            )

        atomic_write(path, write, mkdir=False)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Retina:
        """Read a retina written by :meth:`save`; the photoreceptor order is kept as saved.

        Raises:
            FileNotFoundError: no such file.
            ValueError: naming the problem: not an .npz archive, a missing or malformed entry, an unknown
                format version, or content a retina cannot hold (shapes, NaN, rho outside [0, rho_max], ...).
        """
        path = os.fspath(path)
        try:
            data = np.load(path, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError(f"expected an .npz archive, got a single {type(data).__name__}")
            with data:
                files = set(data.files)
                content = {k: data[k] for k in _SAVED_KEYS if k in files}
        except FileNotFoundError:
            raise
        except (OSError, *NPY_FORMAT_ERRORS) as exc:
            raise ValueError(f"{path}: not a readable Retina .npz archive ({exc})") from None
        missing = [k for k in _SAVED_KEYS if k not in content]
        if missing:
            raise ValueError(f"{path}: not a saved Retina, missing entries {missing}")

        def scalar(key: str, kind: str):
            arr = content[key]
            if arr.shape != () or arr.dtype.kind not in kind:
                raise ValueError(
                    f"{path}: entry {key!r} expected a scalar of kind {kind!r}, got {arr.dtype} {arr.shape}"
                )
            return arr.item()

        version = scalar("format_version", "iu")
        if version != _FORMAT_VERSION:
            raise ValueError(f"{path}: format_version expected {_FORMAT_VERSION}, got {version}")
        try:
            params = json.loads(scalar("params_json", "U"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: entry 'params_json' is not valid JSON ({exc})") from None
        if not isinstance(params, dict):
            raise ValueError(f"{path}: entry 'params_json' expected a JSON object, got {type(params).__name__}")
        for key in ("rho", "theta"):
            arr = content[key]
            if arr.dtype != np.float64 or arr.ndim != 1:
                raise ValueError(f"{path}: entry {key!r} expected a float64 array [P], got {arr.dtype} {arr.shape}")
        try:
            return cls.from_polar(
                content["rho"],
                content["theta"],
                seed=scalar("seed", "iu"),
                layout=scalar("layout", "U"),
                rho_max=scalar("rho_max", "f"),
                params=params,
                morton=False,
            )
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

