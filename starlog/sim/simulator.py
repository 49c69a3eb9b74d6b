"""The star-image simulator: a static star field seen by a camera on a perturbed platform.

Physics per frame ``n`` at time ``t = n / fps``:

1. every star sits at its fixed focal-plane position plus the platform offset
   ``(dx(t), dy(t))`` = jitter (sum of sinusoids) + drift (constant rate) + random walk,
   rotated first, when a roll is set, by ``roll(t)`` about the image centre;
2. its signal is a circular PSF integrated over each pixel (Gaussian: erf; Moffat or Airy:
   quadrature, :mod:`starlog.sim.profiles`), over a uniform sky;
3. hot pixels (fixed positions, constant extra charge) and cosmic-ray hits (random, sharp, 1–3
   pixel tracks) are added;
4. the camera (:class:`~starlog.sim.camera.CameraModel`) applies Poisson shot noise, read
   noise, gain, bias, quantisation and ADC saturation.

With ``sky_attitude`` the field is the real sky instead: the catalogue's stars projected through a
gnomonic camera at that attitude, and the platform motion turns the camera (its offset moves the
boresight, its roll turns it about the boresight), each frame's attitude kept as the truth.

Every random draw comes from generators seeded by ``(seed, purpose, frame)``, so a frame does
not depend on the frames before it (frames can be rendered in parallel) and the same
configuration always gives the same frames.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidParameterError
from starlog.sim.camera import CameraModel
from starlog.sim.profiles import AIRY_FWHM_PER_LAMBDA_D, AiryPSF, MoffatPSF, render_profile_stars
from starlog.sim.psf import render_stars

__all__ = ["PRESETS", "SimulationConfig", "SimulatedFrame", "StarField", "Simulator", "Jitter"]

_SEED_FIELD, _SEED_FRAME, _SEED_WALK, _SEED_JITTER, _SEED_HOT = 1, 2, 3, 4, 5


@dataclass(frozen=True)
class Jitter:
    """One sinusoidal platform vibration: ``amplitude_px * sin(2π f t + phase)`` on each axis.

    The x and y phases are drawn from the seed; ``amplitude_px`` is the peak amplitude per axis.
    """

    frequency_hz: float
    amplitude_px: float

    def __post_init__(self) -> None:
        if not (self.frequency_hz > 0 and np.isfinite(self.frequency_hz)):
            raise InvalidParameterError(f"jitter frequency must be > 0 Hz, got {self.frequency_hz!r}.")
        if not (self.amplitude_px >= 0 and np.isfinite(self.amplitude_px)):
            raise InvalidParameterError(f"jitter amplitude must be >= 0 px, got {self.amplitude_px!r}.")


@dataclass(frozen=True, kw_only=True)
class SimulationConfig:
    """Everything that defines a simulated log. Same config → identical frames and bytes.

    Attributes
    ----------
    width, height : int
        Frame size in pixels.
    n_stars : int
        Number of stars, placed uniformly at least ``margin`` px from the border.
    flux_min, flux_max : float
        Star signal range in photo-electrons per frame (log-uniform).
    fps : float
        Frame rate in Hz.
    n_frames : int
        Number of frames.
    start_time_ns : int
        ``log_time`` of frame 0; frame ``n`` is at ``start + round(n * 1e9 / fps)``.
    psf_sigma : float
        Gaussian PSF standard deviation in pixels.
    psf_model : {"gaussian", "moffat", "airy"}
        The PSF: pixel-integrated Gaussian of ``psf_sigma`` (default), Moffat of ``psf_fwhm`` and
        ``moffat_beta``, or Airy of ``airy_lambda_d`` (lambda/D in px; first dark ring at 1.22
        lambda/D) or, when that is 0, of FWHM ``psf_fwhm``.
    psf_fwhm : float
        Moffat / Airy FWHM, px; 0 (default): that of the Gaussian, ``2.3548 psf_sigma``.
    moffat_beta : float
        Moffat power index (> 1; 2.5 by default, typical of seeing).
    airy_lambda_d : float
        Airy lambda/D, px (0: from ``psf_fwhm``).
    sky : float
        Sky background, photo-electrons per pixel per frame.
    camera : CameraModel
        Read noise, gain, bias, ADC bits, full well.
    hot_pixels : int
        Number of hot pixels (fixed positions) and ``hot_pixel_charge`` their extra electrons.
    cosmic_rays_per_frame : float
        Mean number of cosmic-ray hits per frame (Poisson), each depositing
        1,000–20,000 e⁻ along a 1–3 pixel track.
    jitter : tuple of Jitter
        Platform vibration components.
    drift_px_per_s : (float, float)
        Constant platform drift (x, y).
    random_walk_px_per_sqrt_s : float
        Platform random walk: the offset's standard deviation grows as this × sqrt(t).
    margin : float
        Minimum distance of a star from the border, in pixels.
    roll_amplitude_rad, roll_frequency_hz : float
        Platform roll ``roll_amplitude_rad * sin(2π roll_frequency_hz t)`` about the image centre
        ``((width - 1) / 2, (height - 1) / 2)``, counter-clockwise in (x, y) = (column, row).
        0 (default): no roll.
    sky_attitude : (float, float, float) or None
        ``(ra, dec, roll)`` in degrees: render the real sky instead of a random field. The stars are
        the catalogue's (cedar-solve's Hipparcos star table, :mod:`starlog.attitude.catalogue`) of
        magnitude <= ``magnitude_limit`` seen by a gnomonic camera of horizontal field of view
        ``fov_deg`` at that attitude (:mod:`starlog.attitude.rotation`'s convention), at least
        ``margin`` px inside the frame; ``n_stars``, ``flux_min`` and ``flux_max`` are then unused.
        Platform motion becomes a rotation of the camera: the offset ``(dx, dy)`` turns the boresight
        towards the pixel offset from the centre, the roll turns it about the boresight, and every
        star is projected through the frame's attitude, recorded as the truth.
    fov_deg : float
        Horizontal field of view of the sky camera, degrees.
    magnitude_limit : float
        Faintest catalogue magnitude rendered.
    flux_mag6 : float
        Signal of a magnitude-6 star, photo-electrons per frame (``flux_mag6 * 10**(-0.4 (mag - 6))``).
    seed : int
        Seed of every random draw.
    """

    width: int = 256
    height: int = 256
    n_stars: int = 12
    flux_min: float = 5_000.0
    flux_max: float = 50_000.0
    fps: float = 300.0
    n_frames: int = 300
    start_time_ns: int = 0
    psf_sigma: float = 1.2
    psf_model: str = "gaussian"
    psf_fwhm: float = 0.0
    moffat_beta: float = 2.5
    airy_lambda_d: float = 0.0
    sky: float = 20.0
    camera: CameraModel = field(default_factory=CameraModel)
    hot_pixels: int = 0
    hot_pixel_charge: float = 3_000.0
    cosmic_rays_per_frame: float = 0.0
    jitter: tuple[Jitter, ...] = ()
    drift_px_per_s: tuple[float, float] = (0.0, 0.0)
    random_walk_px_per_sqrt_s: float = 0.0
    margin: float = 10.0
    roll_amplitude_rad: float = 0.0
    roll_frequency_hz: float = 1.0
    sky_attitude: tuple[float, float, float] | None = None
    fov_deg: float = 12.0
    magnitude_limit: float = 6.5
    flux_mag6: float = 20_000.0
    seed: int = 0

    def __post_init__(self) -> None:
        def need(ok: bool, message: str) -> None:
            if not ok:
                raise InvalidParameterError(message)

        need(8 <= self.width <= 16384 and 8 <= self.height <= 16384,
             f"frame size must be within 8..16384 px, got {self.width}x{self.height}.")
        need(0 <= self.n_stars <= 100_000, f"n_stars must be within 0..100000, got {self.n_stars}.")
        need(0 < self.flux_min <= self.flux_max, f"need 0 < flux_min <= flux_max, got {self.flux_min}, {self.flux_max}.")
        need(self.fps > 0 and np.isfinite(self.fps), f"fps must be > 0, got {self.fps}.")
        need(self.n_frames >= 1, f"n_frames must be >= 1, got {self.n_frames}.")
        need(self.start_time_ns >= 0, f"start_time_ns must be >= 0, got {self.start_time_ns}.")
        need(0.2 <= self.psf_sigma <= 50, f"psf_sigma must be within 0.2..50 px, got {self.psf_sigma}.")
        need(self.psf_model in ("gaussian", "moffat", "airy"),
             f"psf_model must be 'gaussian', 'moffat' or 'airy', got {self.psf_model!r}.")
        need(self.psf_fwhm >= 0 and self.airy_lambda_d >= 0 and self.moffat_beta > 1,
             f"need psf_fwhm >= 0, airy_lambda_d >= 0 and moffat_beta > 1, got {self.psf_fwhm}, "
             f"{self.airy_lambda_d}, {self.moffat_beta}.")
        need(self.sky >= 0, f"sky must be >= 0 e-/px, got {self.sky}.")
        need(self.hot_pixels >= 0, f"hot_pixels must be >= 0, got {self.hot_pixels}.")
        need(self.cosmic_rays_per_frame >= 0, f"cosmic_rays_per_frame must be >= 0, got {self.cosmic_rays_per_frame}.")
        need(self.random_walk_px_per_sqrt_s >= 0, "random_walk_px_per_sqrt_s must be >= 0.")
        need(np.isfinite(self.roll_amplitude_rad) and abs(self.roll_amplitude_rad) <= 0.1,
             f"roll_amplitude_rad must be within -0.1..0.1 rad, got {self.roll_amplitude_rad}.")
        need(self.roll_frequency_hz > 0 and np.isfinite(self.roll_frequency_hz),
             f"roll_frequency_hz must be > 0, got {self.roll_frequency_hz}.")
        need(0.5 <= self.fov_deg <= 90 and self.flux_mag6 > 0,
             f"need fov_deg within 0.5..90 and flux_mag6 > 0, got {self.fov_deg}, {self.flux_mag6}.")
        need(self.sky_attitude is None or len(self.sky_attitude) == 3,
             f"sky_attitude is (ra, dec, roll) in degrees, got {self.sky_attitude!r}.")
        need(2 * self.margin < min(self.width, self.height),
             f"margin {self.margin} px leaves no room for stars in a {self.width}x{self.height} frame.")

    @property
    def duration_s(self) -> float:
        """Time spanned by the frames, seconds."""
        return self.n_frames / self.fps

    def frame_time_ns(self, frame: int | npt.NDArray[np.int64]) -> Any:
        """``log_time`` of frame(s) ``frame`` (exposure time, integer ns)."""
        return self.start_time_ns + np.rint(np.asarray(frame, dtype=np.float64) * 1e9 / self.fps).astype(np.int64)

    def psf_profile(self) -> MoffatPSF | AiryPSF | None:
        """The Moffat or Airy PSF of the configuration (None: the Gaussian of ``psf_sigma``)."""
        fwhm = self.psf_fwhm or 2.0 * np.sqrt(2.0 * np.log(2.0)) * self.psf_sigma
        if self.psf_model == "moffat":
            return MoffatPSF(fwhm=fwhm, beta=self.moffat_beta)
        if self.psf_model == "airy":
            return AiryPSF(lambda_d=self.airy_lambda_d or fwhm / AIRY_FWHM_PER_LAMBDA_D)
        return None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready parameters (recorded as the simulate stage's provenance; a Gaussian PSF's
        configuration leaves out the other PSFs' parameters)."""
        d = asdict(self)
        if self.psf_model == "gaussian":
            for key in ("psf_model", "psf_fwhm", "moffat_beta", "airy_lambda_d"):
                d.pop(key)
        if self.sky_attitude is None:
            for key in ("sky_attitude", "fov_deg", "magnitude_limit", "flux_mag6"):
                d.pop(key)
        else:
            d["sky_attitude"] = [float(v) for v in self.sky_attitude]
        d["jitter"] = [asdict(j) for j in self.jitter]
        d["drift_px_per_s"] = list(self.drift_px_per_s)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SimulationConfig:
        """Inverse of :meth:`to_dict`."""
        d = dict(data)
        d["camera"] = CameraModel(**d.get("camera", {}))
        d["jitter"] = tuple(Jitter(**j) for j in d.get("jitter", ()))
        d["drift_px_per_s"] = tuple(d.get("drift_px_per_s", (0.0, 0.0)))
        if d.get("sky_attitude") is not None:
            d["sky_attitude"] = tuple(d["sky_attitude"])
        return cls(**d)


#: The paper's two "laboratory" datasets (its §3.1): static star field, small platform perturbations.
PRESETS: dict[str, dict[str, Any]] = {
    "paper300": {"fps": 300.0, "n_frames": 3248},
    "paper200": {"fps": 200.0, "n_frames": 3027},
}


@dataclass(frozen=True)
class StarField:
    """Fixed star positions (px) and fluxes (e⁻), one entry per star id; for a sky field, also each star's
    catalogue number, magnitude and sky unit vector."""

    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.float64]
    flux: npt.NDArray[np.float64]
    catalogue_id: npt.NDArray[np.int64] | None = None
    magnitude: npt.NDArray[np.float64] | None = None
    vectors: npt.NDArray[np.float64] | None = None


@dataclass(frozen=True)
class SimulatedFrame:
    """One rendered frame with its truth.

    ``x``, ``y`` are the instantaneous true positions (fixed position rotated by ``platform_roll``
    about the image centre, plus the platform offset).
    """

    index: int
    log_time: int
    image: npt.NDArray[np.uint16]
    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.float64]
    flux: npt.NDArray[np.float64]
    platform_dx: float
    platform_dy: float
    platform_roll: float = 0.0
    attitude: npt.NDArray[np.float64] | None = None  # sky fields: the true attitude matrix (sky -> camera)


class Simulator:
    """Render the frames of a :class:`SimulationConfig`.

    Examples
    --------
    >>> sim = Simulator(SimulationConfig(n_frames=2, seed=1))
    >>> [f.image.shape for f in sim.frames()]
    [(256, 256), (256, 256)]
    """

    def __init__(self, config: SimulationConfig) -> None:
        self.config = config
        rng = np.random.default_rng([config.seed, _SEED_FIELD])
        c = config
        if c.sky_attitude is not None:
            self.field = sky_field(c)
        else:
            x = rng.uniform(c.margin, c.width - 1 - c.margin, c.n_stars)
            y = rng.uniform(c.margin, c.height - 1 - c.margin, c.n_stars)
            flux = np.exp(rng.uniform(np.log(c.flux_min), np.log(c.flux_max), c.n_stars))
            self.field = StarField(x=x, y=y, flux=flux)
        jrng = np.random.default_rng([config.seed, _SEED_JITTER])
        self._jitter_phase = jrng.uniform(0, 2 * np.pi, (len(c.jitter), 2))
        hrng = np.random.default_rng([config.seed, _SEED_HOT])
        self._hot_rows = hrng.integers(0, c.height, c.hot_pixels)
        self._hot_cols = hrng.integers(0, c.width, c.hot_pixels)
        self._walk = self._random_walk()

    def _random_walk(self) -> npt.NDArray[np.float64]:
        c = self.config
        if c.random_walk_px_per_sqrt_s == 0:
            return np.zeros((c.n_frames, 2))
        rng = np.random.default_rng([c.seed, _SEED_WALK])
        steps = rng.normal(0.0, c.random_walk_px_per_sqrt_s * np.sqrt(1.0 / c.fps), (c.n_frames, 2))
        steps[0] = 0.0
        return np.cumsum(steps, axis=0)

    def platform_offset(self, frame: int) -> tuple[float, float]:
        """Platform offset ``(dx, dy)`` in px at frame ``frame``."""
        c = self.config
        t = frame / c.fps
        dx = c.drift_px_per_s[0] * t + self._walk[frame, 0]
        dy = c.drift_px_per_s[1] * t + self._walk[frame, 1]
        for j, (px, py) in zip(c.jitter, self._jitter_phase):
            w = 2 * np.pi * j.frequency_hz * t
            dx += j.amplitude_px * np.sin(w + px)
            dy += j.amplitude_px * np.sin(w + py)
        return float(dx), float(dy)

    def platform_roll(self, frame: int) -> float:
        """Platform roll about the image centre at frame ``frame``, rad (0 without a roll)."""
        c = self.config
        return float(c.roll_amplitude_rad * np.sin(2 * np.pi * c.roll_frequency_hz * frame / c.fps))

    def true_attitude(self, frame: int) -> npt.NDArray[np.float64] | None:
        """Sky fields: the frame's attitude matrix (sky → camera), the platform's rotation applied to the
        configured attitude (:class:`SimulationConfig`); None for a random field."""
        if self.config.sky_attitude is None:
            return None
        dx, dy = self.platform_offset(frame)
        return platform_attitude(self.config, dx, dy, self.platform_roll(frame))

    def true_positions(self, frame: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Instantaneous true star positions ``(x, y)`` at frame ``frame``, px."""
        c = self.config
        if c.sky_attitude is not None:
            x, y, _ = sky_camera(c, self.true_attitude(frame)).project(self.field.vectors)
            return x, y
        dx, dy = self.platform_offset(frame)
        if c.roll_amplitude_rad == 0:
            return self.field.x + dx, self.field.y + dy
        roll = self.platform_roll(frame)
        cx, cy = (c.width - 1) / 2.0, (c.height - 1) / 2.0
        u, v = self.field.x - cx, self.field.y - cy
        return (cx + np.cos(roll) * u - np.sin(roll) * v + dx,
                cy + np.sin(roll) * u + np.cos(roll) * v + dy)

    def expected_electrons(self, frame: int) -> tuple[npt.NDArray[np.float64], float, float]:
        """Noise-free expected signal (e⁻/px: sky + stars + hot pixels) and the platform offset."""
        c = self.config
        dx, dy = self.platform_offset(frame)
        x, y = self.true_positions(frame)
        image = np.full((c.height, c.width), float(c.sky))
        profile = c.psf_profile()
        if profile is None:
            render_stars(image.shape, x, y, self.field.flux, c.psf_sigma, out=image)
        else:
            render_profile_stars(image.shape, x, y, self.field.flux, profile, out=image)
        if c.hot_pixels:
            image[self._hot_rows, self._hot_cols] += c.hot_pixel_charge
        return image, dx, dy

    def _add_cosmic_rays(self, image: npt.NDArray[np.float64], rng: np.random.Generator) -> None:
        c = self.config
        for _ in range(rng.poisson(c.cosmic_rays_per_frame)):
            row, col = int(rng.integers(0, c.height)), int(rng.integers(0, c.width))
            length = int(rng.integers(1, 4))
            dr, dc = [(0, 1), (1, 0), (1, 1)][int(rng.integers(0, 3))]
            charge = rng.uniform(1_000.0, 20_000.0)
            for k in range(length):
                r, cc = row + k * dr, col + k * dc
                if r < c.height and cc < c.width:
                    image[r, cc] += charge * (1.0 if k == 0 else rng.uniform(0.3, 1.0))

    def render(self, frame: int) -> SimulatedFrame:
        """Render frame ``frame`` (independent of the other frames)."""
        c = self.config
        if not 0 <= frame < c.n_frames:
            raise InvalidParameterError(f"frame {frame} is outside 0..{c.n_frames - 1}.")
        expected, dx, dy = self.expected_electrons(frame)
        rng = np.random.default_rng([c.seed, _SEED_FRAME, frame])
        if c.cosmic_rays_per_frame:
            self._add_cosmic_rays(expected, rng)
        image = c.camera.expose(expected, rng)
        x, y = self.true_positions(frame)
        return SimulatedFrame(
            index=frame,
            log_time=int(c.frame_time_ns(frame)),
            image=image,
            x=x,
            y=y,
            flux=self.field.flux.copy(),
            platform_dx=dx,
            platform_dy=dy,
            platform_roll=self.platform_roll(frame),
            attitude=self.true_attitude(frame),
        )

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[SimulatedFrame]:
        """Render frames ``start..stop-1`` one at a time."""
        stop = self.config.n_frames if stop is None else stop
        for n in range(start, stop):
            yield self.render(n)


# ---------------------------------------------------------------- sky fields
def sky_camera(config: SimulationConfig, attitude: npt.NDArray[np.float64]) -> Any:
    """The gnomonic camera (:class:`starlog.attitude.camera.Camera`) of a sky field at ``attitude``."""
    from starlog.attitude.camera import camera_for_image, focal_from_fov

    camera = camera_for_image((config.height, config.width), focal_from_fov(config.fov_deg, config.width))
    return replace(camera, rotation=attitude)


def platform_attitude(config: SimulationConfig, dx: float, dy: float, roll: float) -> npt.NDArray[np.float64]:
    """The attitude of a sky field under platform motion: the configured attitude rolled by ``roll`` (rad,
    counter-clockwise in (x, y) about the boresight), then turned so that the boresight's image moves by
    ``(dx, dy)`` px."""
    from starlog.attitude.camera import focal_from_fov
    from starlog.attitude.rotation import attitude_from_radec_roll, small_rotation

    assert config.sky_attitude is not None
    base = attitude_from_radec_roll(*config.sky_attitude)
    cos, sin = np.cos(roll), np.sin(roll)
    rolled = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]]) @ base
    shift = float(np.hypot(dx, dy))
    if shift == 0.0:
        return rolled
    angle = np.arctan2(shift, focal_from_fov(config.fov_deg, config.width))
    return small_rotation(np.array([-dy, dx, 0.0]) / shift * angle) @ rolled


def sky_field(config: SimulationConfig) -> StarField:
    """The catalogue stars of a sky field (:class:`SimulationConfig`'s ``sky_attitude``) at its attitude."""
    from starlog.attitude.catalogue import load_catalogue
    from starlog.attitude.rotation import attitude_from_radec_roll

    assert config.sky_attitude is not None
    catalogue = load_catalogue()
    attitude = attitude_from_radec_roll(*config.sky_attitude)
    camera = sky_camera(config, attitude)
    rows = catalogue.cone(attitude[2], config.fov_deg)
    rows = rows[catalogue.magnitude[rows] <= config.magnitude_limit]
    x, y, front = camera.project(catalogue.vectors[rows])
    m = config.margin
    inside = front & (x >= m) & (x <= config.width - 1 - m) & (y >= m) & (y <= config.height - 1 - m)
    rows, x, y = rows[inside], x[inside], y[inside]
    magnitude = catalogue.magnitude[rows]
    return StarField(x=x, y=y, flux=config.flux_mag6 * 10.0 ** (-0.4 * (magnitude - 6.0)),
                     catalogue_id=catalogue.ids[rows], magnitude=magnitude, vectors=catalogue.vectors[rows])
