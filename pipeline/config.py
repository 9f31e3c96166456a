"""Strict YAML configuration: YAML -> frozen dataclasses, and the pipeline's config classes.

The loader (STYLE.md §3) is generic: :func:`build_dataclass` walks the type hints of a frozen
dataclass, recursing into nested dataclass fields, converting YAML lists to tuples or numpy
arrays where the field is annotated so, and rejecting unknown keys and wrong types with a
:class:`~seqat.errors.ConfigError` that names the file, the dotted key and the value::

    configs/x.yaml: simulation.n_imagse: unknown key (expected one of: crs, ...)
    configs/x.yaml: simulation.n_images: expected an integer, got 'many'

Config classes defined here: :class:`FlightConfig` (``flight.yaml`` of a flight folder) and
:class:`SimulateConfig` (``configs/*_sim.yaml``). The estimator options of ``seqat run`` are
built by :mod:`pipeline.runner` with the same loader.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TypeVar

import numpy as np
import yaml

from pipeline.navigation import BoresightConfig
from pipeline.tracking import TrackerOptions
from seqat.errors import ConfigError, SeqatError
from seqat.simulate import StripSimConfig
from seqat.types import FloatArray

T = TypeVar("T")

#: Longest rendering of an offending value in an error message (characters).
MAX_VALUE_REPR_CHARS = 80

#: YAML 1.2 style floats: PyYAML (YAML 1.1) reads ``1e-3`` (no dot) as a string.
_FLOAT_RE = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML loader that rejects duplicate keys and reads ``1e-3`` as a float."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode) -> dict[object, object]:
    loader.flatten_mapping(node)
    out: dict[object, object] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)  # type: ignore[no-untyped-call]
        try:
            hash(key)
        except TypeError as err:
            raise yaml.constructor.ConstructorError(
                None, None, f"unhashable key {key!r}", key_node.start_mark) from err
        if key in out:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        out[key] = loader.construct_object(value_node, deep=True)  # type: ignore[no-untyped-call]
    return out


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_RE, list("-+0123456789."))


# --------------------------------------------------------------------------------------------
# Generic loader
# --------------------------------------------------------------------------------------------


def load_yaml(path: Path | str) -> Mapping[str, object]:
    """Read a YAML file whose top level is a mapping.

    Parameters
    ----------
    path : Path or str

    Returns
    -------
    Mapping[str, object]
        The parsed document (plain dicts, lists, str, int, float, bool, None).

    Raises
    ------
    ConfigError
        The file cannot be read, is not valid YAML (with line and column), has a duplicate
        key, or its top level is not a mapping. An empty file gives an empty mapping.
    """
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{source}: cannot read: {err}") from err
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        raise ConfigError(f"{where}: invalid YAML: {err.problem or err.context}") from err
    except yaml.YAMLError as err:
        raise ConfigError(f"{source}: invalid YAML: {err}") from err
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of keys at the top level, "
                          f"got {_show(data)}")
    return data


def check_keys(mapping: object, allowed: typing.Iterable[str], source: str, key: str = "") -> (
        Mapping[str, object]):
    """Check that ``mapping`` is a mapping whose keys are all in ``allowed``.

    Parameters
    ----------
    mapping : object
        A YAML value; ``None`` (an empty section) counts as an empty mapping.
    allowed : iterable of str
    source : str
        File name for the error message.
    key : str
        Dotted key of ``mapping`` itself (``""`` for the top level).

    Returns
    -------
    Mapping[str, object]

    Raises
    ------
    ConfigError
        Not a mapping, or an unknown key (the message lists the allowed keys).
    """
    if mapping is None:
        return {}
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"{source}: {key or '(top level)'}: expected a mapping of keys, "
                          f"got {_show(mapping)}")
    allowed = sorted(allowed)
    for k in mapping:
        if not isinstance(k, str) or k not in allowed:
            raise ConfigError(f"{source}: {_join(key, str(k))}: unknown key "
                              f"(expected one of: {', '.join(allowed)})")
    return mapping


def build_dataclass(cls: type[T], mapping: object, source: str, *, key: str = "") -> T:
    """Build a (frozen) dataclass from a YAML mapping, strictly.

    Parameters
    ----------
    cls : type
        A dataclass. Supported field annotations: ``bool``, ``int``, ``float`` (ints accepted,
        must be finite), ``str``, ``Path``, ``Literal[...]``, ``Enum`` subclasses (by value),
        ``None``, unions of these (``X | None``, ``float | tuple[float, float, float]``),
        ``tuple[X, ...]`` and ``tuple[X, Y]``, ``list[X]``, ``dict[str, X]``, numpy arrays
        (``NDArray[np.float64]``) and nested dataclasses.
    mapping : object
        The YAML value (a mapping; ``None`` counts as empty).
    source : str
        File name used in error messages.
    key : str
        Dotted key of ``mapping`` in the file (``""`` for the top level).

    Returns
    -------
    cls instance
        Keys absent from ``mapping`` take the dataclass defaults.

    Raises
    ------
    ConfigError
        ``<source>: <dotted.key>: <problem>``: unknown key, missing required key, wrong type,
        or a value rejected by the dataclass's own validation (``__post_init__``).
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"build_dataclass needs a dataclass, got {cls!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    mapping = check_keys(mapping, fields, source, key)
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, object] = {}
    for name, f in fields.items():
        dotted = _join(key, name)
        if name in mapping:
            kwargs[name] = _convert(hints[name], mapping[name], source, dotted)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{source}: {dotted}: missing required key")
    try:
        return cls(**kwargs)
    except (SeqatError, ValueError, TypeError) as err:
        raise ConfigError(f"{source}: {_prefixed(key, str(err), fields)}") from err


def _join(key: str, name: str) -> str:
    return f"{key}.{name}" if key else name


def _prefixed(key: str, message: str, fields: typing.Iterable[str] = ()) -> str:
    """Prefix a validation message with its section unless it already names it.

    A message starting ``"<field>: "`` (a field of the section) becomes ``"<key>.<field>: "``.
    """
    if not key or message.startswith(f"{key}.") or message.startswith(f"{key}:"):
        return message
    head, sep, rest = message.partition(": ")
    if sep and head in set(fields):
        return f"{key}.{head}: {rest}"
    return f"{key}: {message}"


def _show(value: object) -> str:
    text = repr(value)
    if len(text) > MAX_VALUE_REPR_CHARS:
        text = text[: MAX_VALUE_REPR_CHARS - 3] + "..."
    return text


def _describe(tp: object) -> str:
    """Human description of an annotation for error messages."""
    origin = typing.get_origin(tp)
    if tp is bool:
        return "true or false"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a finite number"
    if tp is str or tp is Path:
        return "a string"
    if tp is type(None):
        return "null"
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return "one of " + ", ".join(repr(m.value) for m in tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        return f"a list of {len(args)} {_plural(args[0]) if len(set(args)) == 1 else 'values'}"
    if origin is list:
        return f"a list of {_plural(typing.get_args(tp)[0])}"
    if origin is np.ndarray:
        return "a (nested) list of finite numbers"
    if dataclasses.is_dataclass(tp) or origin in (dict, Mapping):
        return "a mapping"
    return str(tp)


_PLURALS: dict[object, str] = {int: "integers", float: "numbers", str: "strings",
                                bool: "booleans"}


def _plural(tp: object) -> str:
    return _PLURALS.get(tp, "values")


def _fail(tp: object, value: object, source: str, dotted: str) -> ConfigError:
    return ConfigError(f"{source}: {dotted}: expected {_describe(tp)}, got {_show(value)}")


def _convert(tp: object, value: object, source: str, dotted: str) -> object:
    """Convert one YAML value to the annotated type or raise ConfigError."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is object or tp is typing.Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        others = [a for a in args if a is not type(None)]
        if len(others) == 1:  # ``X | None``: X's own, more precise, error
            return _convert(others[0], value, source, dotted)
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, source, dotted)
            except ConfigError:
                continue
        raise _fail(tp, value, source, dotted)
    if origin is Literal:
        for arg in args:
            if value == arg and type(value) is type(arg):
                return arg
        raise _fail(tp, value, source, dotted)
    if tp is type(None):
        if value is None:
            return None
        raise _fail(tp, value, source, dotted)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _fail(tp, value, source, dotted)
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise _fail(tp, value, source, dotted)
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise _fail(tp, value, source, dotted)
    if tp is str:
        if isinstance(value, str):
            return value
        raise _fail(tp, value, source, dotted)
    if tp is Path:
        if isinstance(value, str) and value:
            return Path(value)
        raise _fail(tp, value, source, dotted)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if value == member.value:
                return member
        raise _fail(tp, value, source, dotted)
    if origin is tuple or origin is list:
        if not isinstance(value, list | tuple):
            raise _fail(tp, value, source, dotted)
        if origin is list:
            item_types: tuple[object, ...] = (args[0],) * len(value)
        elif len(args) == 2 and args[1] is Ellipsis:
            item_types = (args[0],) * len(value)
        else:
            if len(value) != len(args):
                raise _fail(tp, value, source, dotted)
            item_types = args
        items = [_convert(t, v, source, f"{dotted}[{i}]")
                 for i, (t, v) in enumerate(zip(item_types, value, strict=True))]
        return tuple(items) if origin is tuple else items
    if origin is np.ndarray:
        return _to_float_array(tp, value, source, dotted)
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise _fail(tp, value, source, dotted)
        key_tp, val_tp = args
        return {_convert(key_tp, k, source, dotted):
                _convert(val_tp, v, source, _join(dotted, str(k))) for k, v in value.items()}
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return build_dataclass(tp, value, source, key=dotted)
    raise TypeError(f"{dotted}: unsupported config annotation {tp!r}")


def _to_float_array(tp: object, value: object, source: str, dotted: str) -> FloatArray:
    def numbers_only(v: object) -> bool:
        if isinstance(v, list | tuple):
            return all(numbers_only(x) for x in v)
        return isinstance(v, int | float) and not isinstance(v, bool)

    if not isinstance(value, list | tuple) or not numbers_only(value):
        raise _fail(tp, value, source, dotted)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except ValueError as err:  # ragged nesting
        raise _fail(tp, value, source, dotted) from err
    if not np.all(np.isfinite(arr)):
        raise _fail(tp, value, source, dotted)
    return arr


# --------------------------------------------------------------------------------------------
# Pipeline configuration classes
# --------------------------------------------------------------------------------------------

#: Number of components of a position or attitude sigma given as a list.
AXES = 3

SigmaTriple = float | tuple[float, float, float]


def _triple(value: SigmaTriple, name: str) -> tuple[float, float, float]:
    """Expand a scalar-or-3-list sigma and check every component is positive and finite."""
    trip = (value,) * AXES if isinstance(value, int | float) else tuple(value)
    if len(trip) != AXES or not all(math.isfinite(v) and v > 0 for v in trip):
        raise ConfigError(f"{name}: expected a positive number or a list of {AXES} positive "
                          f"numbers, got {value!r}")
    return (float(trip[0]), float(trip[1]), float(trip[2]))


@dataclass(frozen=True, kw_only=True)
class CameraConfig:
    """``camera:`` section of ``flight.yaml`` (OpenCV pixel convention, docs/conventions.md).

    ``model: PINHOLE`` is an ideal camera with square pixels (``fx_px == fy_px``) and no
    distortion; ``model: OPENCV`` adds the OpenCV distortion ``k1 k2 p1 p2 k3``, removed by
    :mod:`pipeline.camera` before image points reach seqat.
    """

    model: Literal["PINHOLE", "OPENCV"]
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name}: expected a positive integer, got {getattr(self, name)}")
        for name in ("fx_px", "fy_px"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected a positive number, got {getattr(self, name)}")
        if self.model == "PINHOLE":
            if self.fx_px != self.fy_px:
                raise ConfigError(
                    f"fy_px: a PINHOLE camera has square pixels, fx_px = fy_px, got "
                    f"{self.fx_px!r} and {self.fy_px!r} (use model: OPENCV)")
            if self.has_distortion:
                raise ConfigError("a PINHOLE camera has no distortion, got non-zero "
                                  "k1 k2 p1 p2 k3 (use model: OPENCV)")

    @property
    def distortion(self) -> FloatArray:
        """(5,) OpenCV distortion coefficients ``[k1, k2, p1, p2, k3]``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0.0))


#: Default a priori σ of GPS positions (x, y, z), metres: a consumer GNSS receiver.
DEFAULT_SIGMA_POSITION_M = (3.0, 3.0, 5.0)
#: Default a priori σ of INS attitudes (omega, phi, kappa), degrees: a low-grade autopilot
#: IMU whose "heading" may be the GPS course (on Seneca the adjusted kappa differs from it by
#: +12 deg on one heading and -20 deg on the reverse one: the wind's crab angle; roll and
#: pitch differ by 4-5 deg rms).
DEFAULT_SIGMA_ATTITUDE_DEG = (5.0, 5.0, 15.0)


@dataclass(frozen=True, kw_only=True)
class NavConfig:
    """``nav:`` section of ``flight.yaml``: where the GPS/INS comes from and its precision.

    ``source: file`` reads ``file`` (``frame: projected`` or ``geodetic``); ``source: images``
    reads each image's EXIF/XMP (docs/formats.md). ``height`` is the height kind of a
    geodetic ``nav.csv`` (``ellipsoidal`` WGS 84 or ``egm96`` orthometric). ``boresight`` and
    ``lever_arm_m`` (GPS antenna -> camera, body axes x forward, y right, z down, metres) apply
    to geodetic attitudes and positions only. ``dropout`` is what becomes of an image
    without a GNSS fix (empty or ``nan`` position fields, no ``nav.csv`` row, no GPS in its
    EXIF): ``bridge`` (default) sends it to the estimator without a position constraint,
    resected on the known ground points; ``skip`` leaves it out (docs/formats.md).
    """

    source: Literal["file", "images"] = "file"
    file: str = "nav.csv"
    frame: Literal["projected", "geodetic"] = "projected"
    height: Literal["ellipsoidal", "egm96"] = "ellipsoidal"
    sigma_position_m: SigmaTriple = DEFAULT_SIGMA_POSITION_M
    sigma_attitude_deg: SigmaTriple = DEFAULT_SIGMA_ATTITUDE_DEG
    boresight: BoresightConfig = BoresightConfig()
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dropout: Literal["bridge", "skip"] = "bridge"

    def __post_init__(self) -> None:
        _triple(self.sigma_position_m, "sigma_position_m")
        _triple(self.sigma_attitude_deg, "sigma_attitude_deg")

    @property
    def sigma_eop(self) -> FloatArray:
        """(6,) standard deviations of ``[X, Y, Z]`` (metres) and ``[omega, phi, kappa]`` (rad)."""
        pos = _triple(self.sigma_position_m, "sigma_position_m")
        att = _triple(self.sigma_attitude_deg, "sigma_attitude_deg")
        return np.concatenate([np.asarray(pos), np.radians(att)])


@dataclass(frozen=True, kw_only=True)
class FlightConfig:
    """``flight.yaml`` of a flight folder (docs/formats.md).

    File names are relative to the flight folder (absolute paths are allowed).
    """

    crs: str = "auto"
    camera: CameraConfig | None = None
    nav: NavConfig = NavConfig()
    sigma_image_px: float = 1.0
    observations: str | None = None
    images: str | None = None
    checkpoints: str | None = None
    lidar: str | tuple[str, ...] | None = None
    tracking: TrackerOptions = TrackerOptions()

    def __post_init__(self) -> None:
        if not self.sigma_image_px > 0:
            raise ConfigError(f"sigma_image_px: expected a positive number, "
                              f"got {self.sigma_image_px!r}")
        if not self.crs.strip():
            raise ConfigError("crs: expected a CRS such as 'EPSG:32652', got an empty string")


#: ``kind`` of a simulation config: precomputed image observations (the paper's input mode).
SIM_KIND_OBSERVATIONS = "observations"


@dataclass(frozen=True, kw_only=True)
class SimulateConfig:
    """``configs/*_sim.yaml``: what ``seqat simulate`` makes.

    ``simulation`` holds the fields of :class:`seqat.simulate.StripSimConfig` (all optional;
    the defaults reproduce the paper's strip).
    """

    kind: Literal["observations"]
    crs: str
    simulation: StripSimConfig = StripSimConfig()


#: ``kind`` of a simulation config: images rendered over real terrain (pipeline/render_flight.py).
SIM_KIND_RENDERED = "rendered"


@dataclass(frozen=True, kw_only=True)
class RenderSourceConfig:
    """``source:`` of a rendered simulation: texture and terrain (paths relative to the config).

    ``texture`` is a north-up image with a world file beside it (``.wld``, ``.jgw``);
    ``texture_crs`` its CRS (anything pyproj accepts, or a WKT file). ``lidar`` are LAS/LAZ
    files gridded (highest point per ``cell_m`` cell, gaps interpolated) into the surface;
    ``las_crs`` overrides their CRS.
    """

    texture: str
    texture_crs: str
    lidar: tuple[str, ...]
    las_crs: str | None = None
    cell_m: float = 1.0

    def __post_init__(self) -> None:
        if not self.cell_m > 0:
            raise ConfigError(f"cell_m: expected a positive number, got {self.cell_m!r}")
        if not self.lidar:
            raise ConfigError("lidar: expected at least one LAS/LAZ file")


@dataclass(frozen=True, kw_only=True)
class FlightPlanConfig:
    """``plan:`` of a rendered simulation: parallel strips flown back and forth.

    ``direction_deg`` is the grid azimuth of the first strip (clockwise from grid north);
    strips alternate direction, ``strip_spacing_m`` apart, centred on ``center_m`` (default:
    the centre of the first LiDAR file). ``height_m`` is above the mean terrain height.
    Attitude wanders smoothly (``attitude_wander_deg`` standard deviation, periods of about
    ``wander_period_s``).
    """

    strips: int = 2
    strip_spacing_m: float = 75.0
    strip_length_m: float = 200.0
    direction_deg: float = 90.0
    center_m: tuple[float, float] | None = None
    height_m: float = 100.0
    speed_m_s: float = 8.0
    frame_rate_hz: float = 0.3
    turn_time_s: float = 20.0
    attitude_wander_deg: float = 1.0
    wander_period_s: float = 20.0

    def __post_init__(self) -> None:
        if self.strips < 1:
            raise ConfigError(f"strips: expected a positive integer, got {self.strips!r}")
        for name in ("strip_length_m", "height_m", "speed_m_s", "frame_rate_hz",
                     "wander_period_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected a positive number, "
                                  f"got {getattr(self, name)!r}")
        for name in ("strip_spacing_m", "turn_time_s", "attitude_wander_deg"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}: expected a number >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True, kw_only=True)
class NavNoiseConfig:
    """``nav:`` of a rendered simulation: GPS/INS errors (white + random-walk bias) and mount.

    A bias random walk of ``d`` per sqrt(s) grows to ``d * sqrt(t)`` after ``t`` seconds.
    ``lever_arm_m``: GPS antenna -> camera, body axes (x forward, y right, z down).
    """

    sigma_position_m: float = 0.05
    position_drift_m_per_sqrt_s: float = 0.01
    sigma_attitude_deg: float = 0.05
    attitude_drift_deg_per_sqrt_s: float = 0.005
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name != "lever_arm_m" and not getattr(self, f.name) >= 0:
                raise ConfigError(f"{f.name}: expected a number >= 0, "
                                  f"got {getattr(self, f.name)!r}")


@dataclass(frozen=True, kw_only=True)
class RenderOutputConfig:
    """``output:`` of a rendered simulation: image finish, LiDAR sampling and check points."""

    jpeg_quality: int = 92
    vignetting: float = 0.15
    noise_sigma_dn: float = 2.0
    lidar_density_per_m2: float = 1.0
    lidar_sigma_m: float = 0.03
    checkpoints: int = 36
    sigma_image_px: float = 0.5

    def __post_init__(self) -> None:
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"jpeg_quality: expected 1..100, got {self.jpeg_quality!r}")
        if not 0 <= self.vignetting < 1:
            raise ConfigError(f"vignetting: expected a number in [0, 1), got {self.vignetting!r}")
        for name in ("noise_sigma_dn", "lidar_density_per_m2", "lidar_sigma_m", "checkpoints"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}: expected a number >= 0, got {getattr(self, name)!r}")
        if not self.sigma_image_px > 0:
            raise ConfigError(f"sigma_image_px: expected a positive number, "
                              f"got {self.sigma_image_px!r}")


@dataclass(frozen=True, kw_only=True)
class RenderSimulateConfig:
    """``configs/*.yaml`` with ``kind: rendered``: a camera flown over real texture and terrain."""

    kind: Literal["rendered"]
    crs: str
    source: RenderSourceConfig
    camera: CameraConfig
    plan: FlightPlanConfig = FlightPlanConfig()
    nav: NavNoiseConfig = NavNoiseConfig()
    output: RenderOutputConfig = RenderOutputConfig()


def load_flight_config(path: Path | str) -> FlightConfig:
    """Read and validate a ``flight.yaml`` (structure and types; CRS: :mod:`pipeline.flight`)."""
    return build_dataclass(FlightConfig, load_yaml(path), str(path))


def load_simulate_config(path: Path | str) -> SimulateConfig | RenderSimulateConfig:
    """Read and validate a simulation config; ``kind`` chooses the class.

    ``kind: observations`` -> :class:`SimulateConfig`, ``kind: rendered`` ->
    :class:`RenderSimulateConfig`.
    """
    mapping = load_yaml(path)
    kind = mapping.get("kind") if isinstance(mapping, Mapping) else None
    if kind == SIM_KIND_RENDERED:
        return build_dataclass(RenderSimulateConfig, mapping, str(path))
    return build_dataclass(SimulateConfig, mapping, str(path))
