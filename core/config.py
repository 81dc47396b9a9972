"""One loader for every typed configuration: frozen dataclasses built from mappings (TOML, YAML, dicts).

:func:`config_from_dict` rejects unknown keys listing the valid ones, recurses into nested sections
(fields whose type is itself a config dataclass), and coerces values to the field's type where the
meaning is unambiguous (an int for a float, a list for a tuple, the text of a number, a boolean or a
list from the command line's ``--set key=value``, a boolean also as 0/1, yes/no or on/off). A value
of the wrong kind is a :class:`~roomcap.core.errors.FormatError` naming the key. A field declared with
:func:`bounded` also has its range checked (:func:`check_range`). ARCHITECTURE.md: each default lives in its
dataclass only; no ``.get(key, default)`` in the algorithms.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from roomcap.core.errors import FormatError

T = TypeVar("T")


def _parse_text(text: str) -> Any:
    """The value a command-line string stands for: a number, a boolean, a list, or the text itself."""
    import tomllib

    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


# booleans written as words or 0/1 (``--set mirror=1``, ``mirror = "yes"``); any other value is an error
_BOOL_WORDS: dict[Any, bool] = {"true": True, "yes": True, "on": True, "1": True, 1: True,
                                "false": False, "no": False, "off": False, "0": False, 0: False}  # fmt: skip


def _coerce(
    value: Any, hint: Any, where: str, path: str | os.PathLike[str] | None, error: type[FormatError]
) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        for a in options:  # the first kind that takes the value as it is
            if _is_instance(value, a):
                return _coerce(value, a, where, path, error)
        return _coerce(value, options[0], where, path, error) if len(options) == 1 else value
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        if isinstance(value, Mapping):
            return config_from_dict(hint, value, where, path, error=error)
        return value
    if isinstance(value, str) and hint in (int, float, bool, tuple, list) or origin in (tuple, list):
        value = _parse_text(value) if isinstance(value, str) else value
    if hint is bool and isinstance(value, (str, int)) and not isinstance(value, bool):
        value = _BOOL_WORDS.get(value.lower() if isinstance(value, str) else value, value)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if (hint is tuple or origin is tuple) and isinstance(value, list):
        return tuple(value)
    if hint in (int, float, bool) and not _is_instance(value, hint):
        raise error(path, where, f"expected {hint.__name__}, got {value!r}.", "Fix the value.")
    return value


def coerce(
    value: Any,
    hint: Any,
    where: str,
    path: str | os.PathLike[str] | None = None,
    error: type[FormatError] = FormatError,
) -> Any:
    """One value coerced to the type ``hint`` as :func:`config_from_dict` does (``error`` names ``where``).

    >>> coerce("2.5", float, "fps"), coerce([1, 2], tuple[int, ...], "scales"), coerce("yes", bool, "mirror")
    (2.5, (1, 2), True)
    >>> coerce("fast", int, "workers")
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: <input>: field 'workers': expected int, got 'fast'. Fix the value.
    """
    return _coerce(value, hint, where, path, error)


def bounded(default: Any, lo: float, hi: float) -> Any:
    """A dataclass field whose value :func:`config_from_dict` checks to lie in [lo, hi] (None passes).

    >>> @dataclasses.dataclass(frozen=True)
    ... class Chunks:
    ...     chunk_s: float = bounded(0.0, 0.0, 3600.0)
    >>> config_from_dict(Chunks, {"chunk_s": 60})
    Chunks(chunk_s=60.0)
    >>> config_from_dict(Chunks, {"chunk_s": -1}, "track")
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: <input>: field 'track.chunk_s': -1.0 is outside the valid range [0.0,
    3600.0].
    """
    return dataclasses.field(default=default, metadata={"range": (lo, hi)})


def check_range(
    value: Any,
    where: str,
    path: str | os.PathLike[str] | None,
    lo: float,
    hi: float,
    *,
    integer: bool = False,
    allow_none: bool = False,
    error: type[FormatError] = FormatError,
) -> Any:
    """``value`` as a float (an int with ``integer``) in [lo, hi], else ``error`` naming ``where``.

    >>> check_range(3, "workers", None, 1, 64, integer=True)
    3
    >>> check_range(0.5, "workers", "run.toml", 1, 64, integer=True)
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: run.toml: field 'workers': expected an integer in [1, 64], got 0.5.
    """
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(path, where, f"expected a number in [{lo}, {hi}], got {value!r}.")
    if integer and int(value) != value:
        raise error(path, where, f"expected an integer in [{lo}, {hi}], got {value!r}.")
    if not (lo <= value <= hi):
        raise error(path, where, f"{value!r} is outside the valid range [{lo}, {hi}].")
    return int(value) if integer else float(value)


def _is_instance(value: Any, hint: Any) -> bool:
    if hint is Any:
        return True
    origin = typing.get_origin(hint) or hint
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(origin, type) and isinstance(value, origin)


def check_keys(
    data: Mapping[str, Any],
    valid: typing.Iterable[str],
    where: str | None,
    path: str | os.PathLike[str] | None,
    error: type[FormatError] = FormatError,
    fix: str = "Remove or rename them.",
    name_key: bool = False,
) -> None:
    """``error`` listing the valid keys when ``data`` has others (the one wording of every config);
    ``name_key``: the error's field is the first unknown key (under ``where``), as file formats name it.

    >>> check_keys({"fps": 25}, ["fps", "chunk_s"], "track", None)
    >>> check_keys({"fsp": 25}, ["fps", "chunk_s"], "track", "run.toml")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: run.toml: field 'track': unknown keys ['fsp']; valid keys: ...
    """
    names = sorted(valid)
    unknown = sorted(set(data) - set(names))
    if unknown:
        if name_key:
            where = f"{where}.{unknown[0]}" if where else unknown[0]
        raise error(path, where, f"unknown keys {unknown}; valid keys: {names}.", fix)


def config_from_dict(
    cls: type[T],
    data: Mapping[str, Any],
    where: str | None = None,
    path: str | os.PathLike[str] | None = None,
    *,
    error: type[FormatError] = FormatError,
) -> T:
    """Build the frozen config dataclass ``cls`` from ``data`` (see the module docstring); problems raise
    ``error`` (a :class:`~roomcap.core.errors.FormatError`, or a subclass such as cams.yaml's
    ``ConfigError``).

    >>> @dataclasses.dataclass(frozen=True)
    ... class Stage:
    ...     fps: float = 25.0
    ...     scales: tuple[float, ...] = (1.0,)
    >>> config_from_dict(Stage, {"fps": 30, "scales": [1, 0.5]})
    Stage(fps=30.0, scales=(1, 0.5))
    """
    if not isinstance(data, Mapping):
        raise error(path, where or cls.__name__, f"expected a table of settings, got {data!r}.")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    check_keys(data, fields, where or cls.__name__, path, error)
    hints = typing.get_type_hints(cls)
    kw = {}
    for k, v in data.items():
        name = f"{where}.{k}" if where else k
        hint = hints.get(k, Any)
        value = _coerce(v, hint, name, path, error)
        rng = fields[k].metadata.get("range")
        if rng is not None:
            integer = hint is int or (
                typing.get_origin(hint) in (typing.Union, types.UnionType) and int in typing.get_args(hint)
            )
            value = check_range(
                value, name, path, rng[0], rng[1], integer=integer, allow_none=True, error=error
            )
        kw[k] = value
    return cls(**kw)


def as_config(cls: type[T], value: T | Mapping[str, Any] | None) -> T:
    """A stage function's ``config`` argument as ``cls``: the typed config itself, ``None`` for the
    defaults, or a mapping (a script's ``{"chunk_s": 30}``) parsed by ``cls.from_dict`` where it has one.

    >>> @dataclasses.dataclass(frozen=True)
    ... class Stage:
    ...     fps: float = 25.0
    >>> as_config(Stage, None), as_config(Stage, {"fps": 30}), as_config(Stage, Stage(50.0))
    (Stage(fps=25.0), Stage(fps=30.0), Stage(fps=50.0))
    """
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        parse = getattr(cls, "from_dict", None)
        return parse(dict(value)) if parse is not None else config_from_dict(cls, value)
    raise TypeError(f"expected {cls.__name__}, a mapping or None, got {type(value).__name__}")
