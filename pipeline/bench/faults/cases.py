"""Cases, scenarios and results of ``seqat bench faults`` (shared by the suite, the flight
case and the report)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.bench.faults.injection import (
    Detection,
    GapStats,
)
from pipeline.bench.report import Machine, Triple
from seqat.simulate import StripSimConfig
from seqat.types import FloatArray

#: The cases, in report order.
CASES = ("strip", "block", "rendered")
#: The simulated block: three serpentine strips of 80 images (40 s each, 20 s turns).
BLOCK = StripSimConfig(strips=3, n_images=80, n_points=400)
#: Variant names (SIM: the simultaneous adjustment of the same dropout, for reference).
OFF, ON, ORACLE, SIM = "snooping off", "snooping on", "oracle", "Sim"


@dataclass(frozen=True, kw_only=True)
class FaultBenchOptions:
    """What is injected and how runs are configured (defaults: issue 7)."""

    blunder_fractions: tuple[float, ...] = (0.05, 0.20)
    blunder_min_px: float = 10.0
    blunder_max_px: float = 100.0
    jump_m: float = 5.0
    dropout_s: float = 30.0
    snooping_critical: float = 3.29  # alpha0 = 0.001, two-sided
    min_rays: int = 3  # with snooping on: a blunder in a new point is detectable
    threshold: float = 0.1  # Seq-R correlation threshold
    neighbours: int = 15  # images on each side of the dropout compared with it
    gp_outlier_m: float = 1.0  # a GP off by more than this (3D) counts as an outlier
    strip_images: int | None = None  # None: the strip config's own n_images
    rendered_initial_images: int = 4  # 12 images: the default 10 would leave 2 sequential


@dataclass(frozen=True, kw_only=True)
class FaultSetup:
    """The faults injected in one case and seed (image ids, counts)."""

    case: str
    seed: int
    n_images: int
    n_observations: int
    blunders: tuple[int, ...]  # per fraction of FaultBenchOptions.blunder_fractions
    jump_image: str
    jump_offset_m: Triple
    dropout_images: tuple[str, ...]
    dropout_span_s: float  # first to last dropout image


@dataclass(frozen=True, kw_only=True)
class FaultRun:
    """One run of one case, seed, fault and variant, scored against truth.

    RMSEs are per axis over the images / points estimated; ``gp_outliers`` counts GPs off by
    more than the options' ``gp_outlier_m``; ``rejected`` counts observations removed by
    data snooping; timings are the sequential stage's ``update_ms``. ``error`` is set (and
    the numbers are NaN) when the run failed.
    """

    case: str
    seed: int
    fault: str
    variant: str
    n_images: int
    n_points: int
    pos_rmse_m: Triple
    att_rmse_deg: Triple
    gp_rmse_m: Triple
    gp_outliers: int
    sigma0: float
    update_ms_median: float
    update_ms_p95: float
    update_ms_max: float
    rejected: int
    nav_downweighted: tuple[str, ...]
    detection: Detection | None
    detection_testable: Detection | None  # blunders of points with >= min_rays observations
    jump_flagged: bool | None
    jump_error_m: float  # 3D position error of the jump image
    dropout_position: GapStats | None  # 3D position error, metres
    dropout_attitude: GapStats | None  # largest attitude error, degrees
    skipped: int  # dropout images that could not be resected
    run_s: float
    error: str = ""


@dataclass(frozen=True, kw_only=True)
class FaultBenchReport:
    """Everything ``faults.json`` holds."""

    date: str
    runtime_s: float
    machine: Machine
    options: FaultBenchOptions
    strip_config: str
    rendered_flight: str
    cases: tuple[str, ...]
    seeds: tuple[int, ...]
    setups: tuple[FaultSetup, ...]
    runs: tuple[FaultRun, ...]


# ---------------------------------------------------------------------------- scenarios
@dataclass(frozen=True, kw_only=True, eq=False)
class Scenario:
    """One run's input: observations (pixels, kept rows), nav jump, dropout, snooping."""

    fault: str
    variant: str
    uv_px: FloatArray  # (k, 2) observed pixels after injection
    keep: np.ndarray  # (k,) bool: rows given to the estimator
    injected: frozenset[tuple[int, int]]  # (image index, point index) of blunders
    jump: tuple[int, FloatArray] | None = None
    gap: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    snooping: bool = False


@dataclass(frozen=True, kw_only=True, eq=False)
class Outcome:
    """What a run gives back, in the case's image and point numbering."""

    eop: FloatArray  # (n, 6) world, NaN for images not estimated
    point_index: np.ndarray  # (m,) int, points estimated
    xyz_m: FloatArray  # (m, 3)
    sigma0: float
    sequential_ms: FloatArray
    rejections: frozenset[tuple[int, int]]
    nav_downweighted: tuple[tuple[int, str], ...]
    skipped: int


class Case:
    """A flight with truth whose runs take a scenario (interface of the two kinds)."""

    name: str
    image_ids: tuple[str, ...]
    point_ids: tuple[str, ...]
    times_s: FloatArray
    truth_eop: FloatArray
    truth_xyz: dict[int, FloatArray]  # point index -> truth (rendered: see _FolderCase)
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_uv: FloatArray
    width_px: int
    height_px: int
    first_sequential: int

    def run(self, sc: Scenario, options: FaultBenchOptions,
            tick: Callable[[], None]) -> Outcome:
        raise NotImplementedError
