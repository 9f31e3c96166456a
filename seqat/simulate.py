"""Simulated image strips and blocks with exact truth (seed 000 §3.1, Tables 2-3).

Straight strips (one by default; several parallel ones flown back and forth make a block)
flown at constant height and speed over gently undulating terrain, with smooth position and
attitude wander; tie points scattered over the ground coverage,
projected into every image that sees them, plus white image noise; GPS/INS EOPs = truth +
white noise. Numpy only; writing files is the pipeline's job.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from seqat.geometry import depth, project
from seqat.types import EOP_SIZE, FloatArray, Frame, PinholeCamera

#: Number of sinusoids summed for a smooth random wander signal.
WANDER_COMPONENTS = 3
#: Periods (seconds) of the wander sinusoids are drawn from this range.
WANDER_PERIOD_S = (20.0, 200.0)
#: Wavelengths (metres) of the terrain undulations are drawn from this range.
TERRAIN_WAVELENGTH_M = (250.0, 900.0)
#: Tie points are scattered over this fraction of the across-track footprint.
ACROSS_TRACK_FILL = 0.9


@dataclass(frozen=True, kw_only=True)
class StripSimConfig:
    """Parameters of a simulated strip or block; the defaults reproduce seed 000 Table 2.

    ``n_images`` is per strip; ``n_points`` over the whole block. With ``strips`` > 1 the
    strips are flown alternately forward and back (serpentine), ``strip_spacing_m`` apart
    (default: from ``side_overlap``), with ``turn_s`` seconds between strips; the block is
    centred on the origin.
    """

    n_images: int = 384
    strips: int = 1
    side_overlap: float = 0.6  # used when strip_spacing_m is not given
    strip_spacing_m: float | None = None
    turn_s: float = 20.0
    frame_rate_hz: float = 2.0
    speed_m_s: float = 10.0
    height_m: float = 200.0  # above the mean terrain height
    heading_deg: float = 90.0  # flight direction, clockwise from grid north
    focal_mm: float = 17.0
    pixel_um: float = 3.45
    width_px: int = 2456
    height_px: int = 2058
    mount_kappa_deg: float = 90.0  # 90: the image x axis (long side) points forward
    n_points: int = 304
    terrain_relief_m: float = 10.0
    terrain_mean_z_m: float = 100.0
    attitude_wander_deg: float = 0.5
    position_wander_m: float = 2.0
    sigma_position_m: float = 0.3
    sigma_attitude_deg: float = 0.1
    sigma_px: float = 1.0
    # Lens distortion of the simulated camera (OpenCV k1, k2, p1, p2, k3; seqat/types.py).
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    origin_e_m: float = 500000.0
    origin_n_m: float = 4090000.0
    edge_margin_px: float = 10.0

    def __post_init__(self) -> None:
        from seqat.errors import ConfigError

        positive = (
            "frame_rate_hz",
            "speed_m_s",
            "height_m",
            "focal_mm",
            "pixel_um",
            "sigma_position_m",
            "sigma_attitude_deg",
            "sigma_px",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(
                    f"simulation.{name}: expected a positive number, got {getattr(self, name)!r}"
                )
        if self.n_images < 2:
            raise ConfigError(f"simulation.n_images: expected at least 2, got {self.n_images}")
        if self.n_points < 1:
            raise ConfigError(f"simulation.n_points: expected at least 1, got {self.n_points}")
        if self.strips < 1:
            raise ConfigError(f"simulation.strips: expected at least 1, got {self.strips}")
        if not 0 <= self.side_overlap < 1:
            raise ConfigError(
                f"simulation.side_overlap: expected a value in [0, 1), got {self.side_overlap!r}"
            )
        if self.strip_spacing_m is not None and not self.strip_spacing_m > 0:
            raise ConfigError(f"simulation.strip_spacing_m: expected a positive number or "
                              f"null, got {self.strip_spacing_m!r}")
        if len(self.distortion) != 5 or not all(np.isfinite(v) for v in self.distortion):
            raise ConfigError(f"simulation.distortion: expected 5 numbers (k1, k2, p1, p2, "
                              f"k3), got {self.distortion!r}")
        if not self.turn_s >= 0:
            raise ConfigError(f"simulation.turn_s: expected >= 0, got {self.turn_s!r}")

    @property
    def across_half_m(self) -> float:
        """Half the across-track ground extent of a nadir image at the mean terrain."""
        gsd = self.height_m / self.camera.f_px
        hx, hy = self.width_px / 2 * gsd, self.height_px / 2 * gsd
        m = np.radians(self.mount_kappa_deg)
        return float(abs(np.sin(m)) * hy + abs(np.cos(m)) * hx)

    @property
    def spacing_m(self) -> float:
        """Distance between strip axes."""
        if self.strip_spacing_m is not None:
            return self.strip_spacing_m
        return 2.0 * self.across_half_m * (1.0 - self.side_overlap)

    @property
    def camera(self) -> PinholeCamera:
        k1, k2, p1, p2, k3 = (float(v) for v in self.distortion)
        return PinholeCamera(
            f_px=self.focal_mm * 1e3 / self.pixel_um,
            cx_px=(self.width_px - 1) / 2.0,
            cy_px=(self.height_px - 1) / 2.0,
            width_px=self.width_px,
            height_px=self.height_px,
            k1=k1, k2=k2, p1=p1, p2=p2, k3=k3,
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class SimulatedFlight:
    """A simulated observations flight with exact truth (world coordinates)."""

    camera: PinholeCamera
    image_ids: tuple[str, ...]
    times_s: FloatArray  # (n,)
    truth_eop: FloatArray  # (n, 6) world m / rad
    nav_eop: FloatArray  # (n, 6)
    nav_sigma: FloatArray  # (6,) m, m, m, rad, rad, rad
    point_ids: tuple[str, ...]
    truth_xyz: FloatArray  # (m, 3)
    obs_image: np.ndarray  # (k,) int, grouped by image in acquisition order
    obs_point: np.ndarray  # (k,) int
    obs_uv: FloatArray  # (k, 2) px
    sigma_px: float

    def frames(self) -> Iterator[Frame]:
        """The flight as estimator input, one :class:`Frame` per image in order."""
        bounds = np.searchsorted(self.obs_image, np.arange(len(self.image_ids) + 1))
        for i, iid in enumerate(self.image_ids):
            sl = slice(bounds[i], bounds[i + 1])
            yield Frame(
                image_id=iid,
                nav_eop=self.nav_eop[i],
                nav_sigma=self.nav_sigma,
                point_ids=tuple(self.point_ids[j] for j in self.obs_point[sl]),
                uv_px=self.obs_uv[sl],
                sigma_px=self.sigma_px,
            )


def _wander(rng: np.random.Generator, t: FloatArray, amplitude: float) -> FloatArray:
    """Smooth zero-mean random signal of r.m.s. about ``amplitude`` sampled at ``t``."""
    out = np.zeros_like(t)
    for _ in range(WANDER_COMPONENTS):
        period = rng.uniform(*WANDER_PERIOD_S)
        out += np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
    return out * amplitude * np.sqrt(2.0 / WANDER_COMPONENTS)


def _terrain(rng: np.random.Generator, relief_m: float, mean_m: float):  # type: ignore[no-untyped-def]
    """A smooth random terrain height function ``z(e, n)`` (local metres)."""
    waves = [
        (rng.uniform(*TERRAIN_WAVELENGTH_M), rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi))
        for _ in range(2)
    ]

    def z(e: FloatArray, n: FloatArray) -> FloatArray:
        h = np.zeros(np.broadcast(e, n).shape)
        for wl, az, ph in waves:
            h += np.sin(2 * np.pi * (e * np.cos(az) + n * np.sin(az)) / wl + ph)
        return mean_m + relief_m * h / np.sqrt(len(waves))

    return z


def simulate_strip(config: StripSimConfig, seed: int) -> SimulatedFlight:
    """Simulate a strip (or a block of strips) of images with tie points and GPS/INS
    (seed 000 §3.1).

    Parameters
    ----------
    config : StripSimConfig
    seed : int
        Seed of ``numpy.random.default_rng``; the same seed gives the same flight.

    Returns
    -------
    SimulatedFlight
        Points seen in fewer than two images are dropped.
    """
    rng = np.random.default_rng(seed)
    cam = config.camera
    per = config.n_images
    n = per * config.strips
    strip = np.repeat(np.arange(config.strips), per)
    step = np.tile(np.arange(per), config.strips)
    t = (np.arange(n) + strip * config.turn_s * config.frame_rate_hz) / config.frame_rate_hz
    heading = np.radians(config.heading_deg)
    fwd = np.array([np.sin(heading), np.cos(heading)])
    right = np.array([np.cos(heading), -np.sin(heading)])
    s_axis = config.speed_m_s * np.arange(per) / config.frame_rate_hz
    s_axis -= s_axis[-1] / 2.0  # strips centred on the origin
    back = strip % 2 == 1  # serpentine: odd strips flown backwards
    s = np.where(back, s_axis[::-1][step], s_axis[step])
    offset = (strip - (config.strips - 1) / 2.0) * config.spacing_m
    z_of = _terrain(rng, config.terrain_relief_m, config.terrain_mean_z_m)
    cross = _wander(rng, t, config.position_wander_m)
    en = s[:, None] * fwd + (offset + cross)[:, None] * right
    up = config.terrain_mean_z_m + config.height_m + _wander(rng, t, config.position_wander_m)
    att_amp = np.radians(config.attitude_wander_deg)
    omega = _wander(rng, t, att_amp)
    phi = _wander(rng, t, att_amp)
    kappa = (-heading + np.radians(config.mount_kappa_deg) + np.where(back, np.pi, 0.0)
             + _wander(rng, t, att_amp))
    truth_local = np.column_stack([en, up, omega, phi, kappa])

    # Ground coverage of a nadir image, split into along- and across-track half extents.
    gsd = config.height_m / cam.f_px
    hx, hy = config.width_px / 2 * gsd, config.height_px / 2 * gsd
    across_half = config.across_half_m
    # Across the block: the strips' axes plus the fill of one footprint on either side.
    widen = 1.0 + (config.strips - 1) / 2.0 * config.spacing_m / (across_half * ACROSS_TRACK_FILL)
    ps = rng.uniform(s_axis[0], s_axis[-1], config.n_points)
    pc = rng.uniform(-1, 1, config.n_points) * across_half * ACROSS_TRACK_FILL * widen
    order = np.argsort(ps)
    ps, pc = ps[order], pc[order]
    pen = ps[:, None] * fwd + pc[:, None] * right
    pts_local = np.column_stack([pen, z_of(pen[:, 0], pen[:, 1])])

    # Project each image only against the points within its along-track reach: O(n * k).
    reach = np.hypot(hx, hy) * 1.5 + 3 * config.position_wander_m
    lo = np.searchsorted(ps, s - reach)
    hi = np.searchsorted(ps, s + reach)
    obs_i, obs_j, obs_uv = [], [], []
    mg = config.edge_margin_px
    for i in range(n):
        j = np.arange(lo[i], hi[i])
        if j.size == 0:
            continue
        e = np.repeat(truth_local[i : i + 1], j.size, axis=0)
        uv = project(e, pts_local[j], cam)
        ok = (
            (depth(e, pts_local[j]) > 0)
            & (uv[:, 0] >= mg)
            & (uv[:, 0] <= cam.width_px - 1 - mg)
            & (uv[:, 1] >= mg)
            & (uv[:, 1] <= cam.height_px - 1 - mg)
        )
        obs_i.append(np.full(int(ok.sum()), i))
        obs_j.append(j[ok])
        obs_uv.append(uv[ok])
    oi = np.concatenate(obs_i)
    oj = np.concatenate(obs_j)
    ouv = np.concatenate(obs_uv) + rng.normal(0.0, config.sigma_px, (oi.size, 2))
    # Keep points seen at least twice; renumber them in order of first sight.
    counts = np.bincount(oj, minlength=config.n_points)
    keep_obs = counts[oj] >= 2
    oi, oj, ouv = oi[keep_obs], oj[keep_obs], ouv[keep_obs]
    _, first = np.unique(oj, return_index=True)
    kept = oj[np.sort(first)]
    remap = np.full(config.n_points, -1)
    remap[kept] = np.arange(kept.size)
    oj = remap[oj]

    origin = np.array([config.origin_e_m, config.origin_n_m, 0.0])
    truth_eop = truth_local.copy()
    truth_eop[:, :3] += origin
    nav_sigma = np.array(
        [config.sigma_position_m] * 3 + [np.radians(config.sigma_attitude_deg)] * 3
    )
    nav_eop = truth_eop + rng.normal(0.0, 1.0, (n, EOP_SIZE)) * nav_sigma
    width = max(4, len(str(n)))
    pwidth = max(4, len(str(kept.size)))
    return SimulatedFlight(
        camera=cam,
        image_ids=tuple(f"img_{i + 1:0{width}d}" for i in range(n)),
        times_s=t,
        truth_eop=truth_eop,
        nav_eop=nav_eop,
        nav_sigma=nav_sigma,
        point_ids=tuple(f"p{j + 1:0{pwidth}d}" for j in range(kept.size)),
        truth_xyz=pts_local[kept] + origin,
        obs_image=oi,
        obs_point=oj,
        obs_uv=ouv,
        sigma_px=config.sigma_px,
    )
