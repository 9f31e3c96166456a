"""Strict YAML loading: YAML -> frozen dataclasses (the generic loader of every config).

The loader (STYLE.md §3) is generic: :func:`build_dataclass` walks the type hints of a frozen
dataclass, recursing into nested dataclass fields, converting YAML lists to tuples or numpy
arrays where the field is annotated so, and rejecting unknown keys and wrong types with a
:class:`~seqat.errors.ConfigError` that names the file, the dotted key and the value::

    configs/x.yaml: simulation.n_imagse: unknown key (expected one of: crs, ...)
    configs/x.yaml: simulation.n_images: expected an integer, got 'many'

The config classes live with their stage: :class:`pipeline.flight.schema.FlightConfig`
(``flight.yaml`` of a flight folder), :class:`pipeline.simulate.config.SimulateConfig`
(``configs/*_sim.yaml``); the estimator options of ``seqat run`` are built by
:mod:`pipeline.run.runner` with the same loader.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Literal, TypeVar

import numpy as np
import yaml

from seqat.errors import ConfigError, SeqatError
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


def _same_choice(value: object, choice: object) -> bool:
    """``value`` is the choice: equal and of the same type; a string choice in any case
    (``occlusion: ZBuffer`` is ``zbuffer``, as the command line's choice options)."""
    if isinstance(value, str) and isinstance(choice, str):
        return value.strip().lower() == choice.lower()
    return value == choice and type(value) is type(choice)


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
            if _same_choice(value, arg):
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
            if _same_choice(value, member.value):
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

