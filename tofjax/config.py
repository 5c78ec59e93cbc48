"""Typed TOML configuration: tables -> frozen, validated dataclasses.

Every config file in tofjax (scenes, and later fit and training configs) goes
through :func:`from_dict`, so unknown keys, missing keys and wrong types are
reported the same way everywhere: one line naming the file, the key and the
reason.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from .errors import UserError

T = TypeVar("T")

__all__ = ["ConfigError", "from_dict", "load_toml", "to_dict"]


class ConfigError(UserError):
    """A configuration is invalid. The message names the key and the reason."""


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file, turning I/O and syntax errors into :class:`ConfigError`."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, expected a TOML file") from None
    except PermissionError:
        raise ConfigError(f"{path}: permission denied") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.start}); TOML files are UTF-8") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot be read: {e.strerror or e}") from None


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        return f"a list of {len(args)} {_plural(args[0])}"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp) if a is not type(None))
    if dataclasses.is_dataclass(tp):
        return "a table"
    return {float: "a number", int: "an integer", bool: "true or false", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp))
    )


def _plural(tp: Any) -> str:
    """The plural of :func:`_type_name` for a list's elements ("numbers", "lists of 2 numbers")."""
    name = _type_name(tp)
    if name.startswith("a list of "):
        return "lists of " + name[len("a list of "):]
    if name == "true or false":
        return "booleans"
    if name.startswith(("a ", "an ")) and " or " not in name:
        return name.split(" ", 1)[1] + "s"
    return name


def _convert(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        if len(args) == 1:  # X | None: X's own error names the key (not "expected a table")
            return _convert(value, args[0], where)
        for a in args:
            try:
                return _convert(value, a, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {len(value)} values")
        return tuple(_convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        return from_dict(tp, value, where)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            value = float(value)
        except OverflowError:
            raise ConfigError(f"{where}: must be finite, got a number too large for a float") from None
        if not math.isfinite(value):
            raise ConfigError(f"{where}: must be finite, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp!r} at {where}")  # a bug in tofjax, not in the file


#: ``dataclasses.field(metadata={INFINITE_OK: True})``: a float field that also takes ``inf`` from a
#: file (a threshold whose "never" is +inf); every other float must be finite
INFINITE_OK = "infinite_ok"


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build the frozen dataclass ``cls`` from a TOML table.

    Unknown keys, missing required keys and wrong types raise
    :class:`ConfigError` naming the key. Nested dataclasses and tuples of them
    are built recursively. After construction the dataclass's own
    ``__post_init__`` checks its physics (ranges, geometry).
    """
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    prefix = f"{where}." if where else ""
    unknown = sorted(set(data) - set(fields))
    if unknown:
        known = ", ".join(sorted(fields))
        raise ConfigError(
            f"{prefix}{unknown[0]}: unknown key" + (f" (also {', '.join(unknown[1:])})" if unknown[1:] else "")
            + f"; known keys here: {known}"
        )
    kwargs = {}
    for name, f in fields.items():
        key = f"{prefix}{name}"
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{key}: missing key ({_type_name(hints[name])} is required)")
            continue
        if f.metadata.get(INFINITE_OK) and data[name] == math.inf and not isinstance(data[name], bool):
            kwargs[name] = math.inf  # a threshold whose "never" is +inf (TOML's inf)
            continue
        kwargs[name] = _convert(data[name], hints[name], key)
    try:
        return cls(**kwargs)
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(f"{prefix}{msg}" if where and not msg.startswith(prefix) else msg) from None


def to_dict(obj: Any) -> Any:
    """The inverse of :func:`from_dict`: a dataclass as plain TOML/JSON-able data."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    if isinstance(obj, tuple):
        return [to_dict(v) for v in obj]
    return obj


def toml_value(v: Any) -> str:
    """One value as TOML: booleans, numbers, strings and (nested) lists or tuples of them."""
    import json

    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {type(v).__name__}")
