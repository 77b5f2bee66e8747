"""Typed configuration: YAML recipes map 1:1 onto frozen dataclasses.

An unknown key is an error, overrides are dotted (``train.lr=1e-4``), and a config round-trips
through plain JSON-able dicts so checkpoints can carry it::

    cfg = load_config(TrainRecipe, "configs/codetalker_synth.yaml", ["train.lr=3e-4"])
    to_dict(cfg) == to_dict(from_dict(TrainRecipe, to_dict(cfg)))
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from talkmesh.errors import MissingDependencyError, TalkmeshError

T = TypeVar("T")


def to_dict(cfg: Any) -> Any:
    """A dataclass (nested) -> plain dicts, lists, numbers and strings."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {str(k): to_dict(v) for k, v in cfg.items()}
    return cfg


def _convert(tp: Any, value: Any, where: str) -> Any:
    """Coerce ``value`` to the annotated type ``tp`` (dataclasses, tuples, unions, literals)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, where)
            except TalkmeshError as e:
                errors.append(str(e))
        raise TalkmeshError(errors[0] if errors else f"{where}: bad value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise TalkmeshError(f"{where}: {value!r} is not one of {', '.join(map(repr, args))}")
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise TalkmeshError(f"{where}: expected a mapping, got {value!r}")
        return from_dict(tp, value, where)
    if origin in (tuple, list):
        if isinstance(value, str) or not isinstance(value, (list, tuple)):
            raise TalkmeshError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{k}]") for k, v in enumerate(value))
        if origin is tuple and args:
            if len(args) != len(value):
                raise TalkmeshError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(
                _convert(a, v, f"{where}[{k}]") for k, (a, v) in enumerate(zip(args, value))
            )
        inner = args[0] if args else Any
        items = [_convert(inner, v, f"{where}[{k}]") for k, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise TalkmeshError(f"{where}: expected a mapping, got {value!r}")
        kt, vt = args or (Any, Any)
        return {_convert(kt, k, where): _convert(vt, v, f"{where}.{k}") for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise TalkmeshError(f"{where}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise TalkmeshError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str):  # YAML 1.1 reads 1e-4 (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TalkmeshError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise TalkmeshError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build the dataclass ``cls`` from a mapping; unknown keys and wrong types are errors."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        prefix = f"{where}." if where else ""
        raise TalkmeshError(
            f"unknown config key {prefix}{unknown[0]}: valid keys here are {', '.join(sorted(fields))}"
        )
    kwargs = {
        name: _convert(hints[name], value, f"{where}.{name}" if where else name)
        for name, value in data.items()
    }
    try:
        return cls(**kwargs)
    except TypeError as e:  # a required field is missing
        raise TalkmeshError(f"config {where or cls.__name__}: {e}") from None
    except ValueError as e:  # __post_init__ validation
        raise TalkmeshError(f"config {where or cls.__name__}: {e}") from None


def _parse_scalar(text: str) -> Any:
    """An override's value as YAML would read it (``1e-4``, ``true``, ``[1, 2]``, ``name``)."""
    try:
        import yaml

        return yaml.safe_load(text)
    except ImportError:
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            return text


def merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``override`` on top, recursively for nested mappings (neither is changed)."""
    out = dict(base)
    for k, v in override.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``a.b.c=value`` overrides to a nested dict (a new dict; the input is unchanged)."""
    out = json.loads(json.dumps(data))
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise TalkmeshError(f"override '{item}' must look like key.sub=value")
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise TalkmeshError(f"override '{item}': {part} is not a section")
            node = child
        node[parts[-1]] = _parse_scalar(text)
    return out


def read_yaml(path: str | Path) -> dict[str, Any]:
    """A YAML file -> dict, with one-line errors naming the file."""
    try:
        import yaml
    except ImportError:
        raise MissingDependencyError("pyyaml", "train", "reading YAML configs") from None
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark else ""
        raise TalkmeshError(f"{path}{where}: not valid YAML") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise TalkmeshError(f"{path}: a config must be a mapping of sections")
    return data


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] = ()) -> T:
    """YAML file (optional) + dotted overrides -> the validated dataclass ``cls``."""
    data = read_yaml(path) if path is not None else {}
    try:
        return from_dict(cls, apply_overrides(data, list(overrides)))
    except TalkmeshError as e:
        raise TalkmeshError(f"{path}: {e}" if path else str(e)) from None
