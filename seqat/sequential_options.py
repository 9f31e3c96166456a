"""Options of the sequential estimator (:class:`seqat.sequential.SequentialAT`), checked
when made; docs/algorithm.md explains each choice."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from seqat.calibration import SelfCalibration
from seqat.departures import DEFAULT_MAX_WINDOW_IMAGES
from seqat.errors import ConfigError
from seqat.robust import NAV_ROBUST_SCALE, ROBUST_SCALE, check_scale
from seqat.simultaneous import SimOptions

#: Window engines (SequentialOptions.engine).
ENGINES = ("information", "inverse")


@dataclass(frozen=True, kw_only=True)
class SequentialOptions:
    """Options of the sequential estimator."""

    correlation_threshold: float | None = 0.1  # None: Seq-F (no window cut)
    # Seq-R: at most this many images in the window after an update, whatever their
    # correlations (on a block flown on a weak GPS/INS the whole block stays correlated
    # and the paper's rule never cuts; also the latency budget's last dial); None: the
    # paper's rule alone (docs/algorithm.md, *Seq-R: the window*).
    max_window_images: int | None = DEFAULT_MAX_WINDOW_IMAGES
    initial_images: int = 10  # images adjusted simultaneously before the sequential stage
    min_rays: int = 2  # a tie point is born once seen in this many window images
    min_ray_angle_deg: float = 8.0  # ... and its rays spread at least this much (docs/algorithm.md)
    max_update_iterations: int = 10  # 1 = the paper's single linearisation
    iteration_tolerance_px: float = 0.01  # stop when the rows predict the new estimate this well
    smoothing: bool = True  # Seq-R: keep RTS gains so solution() can smooth departed parameters
    relinearise_px: float | None = 1.0  # re-linearise the window when its rows are this far off
    relinearise_iterations: int = 20  # at most this many Gauss-Newton steps per re-linearisation
    # Drift check (seed 003 §3.2): every this many images the window is re-adjusted from its
    # observations whatever its linearisation error, and the change is reported (drift_m,
    # drift_deg of ImageUpdate). None: only when the error exceeds relinearise_px.
    drift_check_every: int | None = None
    # Seq-R: a departed GP seen again, or a departed image holding a pending ray of a point
    # being born, re-enters the window if it left at most this many images ago (0: never).
    reopen_max_age: int = 1000
    # Seq-R: departed parameters older than this many images are final: smoothed once more,
    # then moved to a compact store or handed to the caller's sink, their records dropped.
    # Memory stays flat with flight length. None: keep everything (exact RTS smoothing).
    smoothing_lag: int | None = None
    # Baarda's data snooping of each update's rows (w-test, critical value; 3.29 is
    # alpha0 = 0.001 two-sided); None: off (the paper). docs/algorithm.md, "Blunders".
    snooping_critical: float | None = None
    # "information": the window's information matrix, Cholesky-factorised with its GPs
    # eliminated after every update (numerically stable, rank checked); "inverse": the
    # paper's update of the inverse normal matrix (Eq. 10-14). docs/algorithm.md, *Engines*.
    engine: str = "information"
    # Robust loss of the image points: least squares within this many sigma, a Cauchy tail
    # beyond (seqat/robust.py; the initial Sim uses the same); None: least squares (the
    # paper's estimator). On by default: one wrong tie point must not move the solution.
    # docs/algorithm.md, *Robust loss*.
    robust_scale: float | None = ROBUST_SCALE
    nav_robust_scale: float | None = NAV_ROBUST_SCALE  # ... of the GPS/INS groups (σ per DoF)
    # finish() re-opens the departed images and GPs (within reopen_max_age) and re-linearises
    # them with the window: the final values are the nonlinear smoother's (real-time values:
    # solution(smoothed=False)). Needs smoothing. docs/algorithm.md, *What the window costs*.
    final_reopen: bool = True
    # After an update that moved earlier window images beyond 3 sigma, a window whose camera
    # parameters are undetermined is adjusted again from least-squares weights with them
    # held, and kept when it fits better (seqat/second_start.py; docs/algorithm.md, *A
    # second start during the flight*). Information engine, relinearise_px, self-calibration.
    second_start: bool = True
    # Self-calibration (seqat/calibration.py): the camera's free interior parameters are
    # estimated with the EOPs, in the initial Sim and then in the window, which they never
    # leave; None: the camera is fixed. docs/algorithm.md, *Self-calibration*.
    calibration: SelfCalibration | None = None
    sim: SimOptions = SimOptions()

    def __post_init__(self) -> None:
        check_scale("robust_scale", self.robust_scale)
        check_scale("nav_robust_scale", self.nav_robust_scale)
        if self.engine not in ENGINES:
            raise ConfigError(f"engine: expected one of {', '.join(ENGINES)}, "
                              f"got {self.engine!r}")
        if self.correlation_threshold is not None and not 0 <= self.correlation_threshold <= 1:
            raise ConfigError(f"correlation_threshold: expected a value in [0, 1] or null, "
                              f"got {self.correlation_threshold!r}")
        if self.max_window_images is not None and self.max_window_images < 2:
            raise ConfigError(f"max_window_images: expected >= 2 or null, "
                              f"got {self.max_window_images}")
        if self.initial_images < 1:
            raise ConfigError(f"initial_images: expected >= 1, got {self.initial_images}")
        if self.min_rays < 2:
            raise ConfigError(f"min_rays: expected >= 2, got {self.min_rays}")
        if self.max_update_iterations < 1:
            raise ConfigError(f"max_update_iterations: expected >= 1, "
                              f"got {self.max_update_iterations}")
        if self.relinearise_px is not None and not self.relinearise_px > 0:
            raise ConfigError(f"relinearise_px: expected a positive number or null, "
                              f"got {self.relinearise_px!r}")
        if self.snooping_critical is not None and not self.snooping_critical > 0:
            raise ConfigError(f"snooping_critical: expected a positive number or null, "
                              f"got {self.snooping_critical!r}")
        if self.smoothing_lag is not None and self.smoothing_lag < 10:
            raise ConfigError(f"smoothing_lag: expected >= 10 images or null, "
                              f"got {self.smoothing_lag}")
        if self.reopen_max_age < 0:
            raise ConfigError(f"reopen_max_age: expected >= 0, got {self.reopen_max_age}")
        if self.drift_check_every is not None and (self.drift_check_every < 1
                                                   or self.relinearise_px is None):
            raise ConfigError("drift_check_every: expected >= 1 (and relinearise_px set), "
                              f"got {self.drift_check_every}")
        if self.relinearise_iterations < 1:
            raise ConfigError(f"relinearise_iterations: expected >= 1, "
                              f"got {self.relinearise_iterations}")

    def sim_options(self) -> SimOptions:
        """The options of a Sim adjusting this run's flight: :attr:`sim` with the choices both
        estimators share (``min_rays``, data snooping, both robust losses, self-calibration).
        The initial block and the final check (``pipeline.run.final_check``) start here."""
        return dataclasses.replace(self.sim, min_rays=self.min_rays,
                                   snooping_critical=self.snooping_critical,
                                   robust_scale=self.robust_scale,
                                   nav_robust_scale=self.nav_robust_scale,
                                   calibration=self.calibration)
