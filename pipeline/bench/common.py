"""What the benchmarks share: the machine record, the load average, the strip config, progress."""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import scipy
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pipeline.bench.report import (
    Machine,
)
from pipeline.simulate.config import SimulateConfig, load_simulate_config
from seqat.errors import ConfigError
from seqat.simulate import StripSimConfig


def load_sim_config(path: Path) -> StripSimConfig:
    """``simulation:`` section of a ``kind: observations`` config (strict: unknown keys are
    :class:`~seqat.errors.ConfigError` naming the file and the key)."""
    config = load_simulate_config(path)
    if not isinstance(config, SimulateConfig):
        raise ConfigError(f"{path}: kind: the benchmark needs kind: observations, got "
                          f"{config.kind!r}")
    return config.simulation


def load_average() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan


def machine(load_start: float) -> Machine:
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return Machine(
        platform=platform.platform(),
        python=platform.python_version(),
        numpy=np.__version__,
        scipy=scipy.__version__,
        cpu_count=os.cpu_count() or 0,
        cpu_model=model,
        load_average_1m=load_start,
        load_average_1m_end=load_average(),
    )


@contextmanager
def progress_bars(enabled: bool) -> Iterator[Progress]:
    with Progress(
        TextColumn("{task.description:<28}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        disable=not enabled,
        transient=False,
    ) as p:
        yield p
