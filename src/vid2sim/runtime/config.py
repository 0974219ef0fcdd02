"""Configuration trees: nested dataclasses to JSON and back, and command-line flags generated from them.

A configuration is a dataclass whose fields are numbers, strings, booleans, ``None``-able versions of those,
tuples of them, ``Literal`` choices, or nested configuration dataclasses. Every field is documented in its
class docstring's ``Attributes:`` section (Google style); that text is the flag's help.

- :func:`to_dict` / :func:`from_dict`: the JSON form written beside every output (``config.json``) and read
  back, checked field by field (an unknown key, a wrong type or a bad value raises
  :class:`~vid2sim.runtime.errors.ConfigError` naming the dotted path, e.g. ``joint.iterations``).
- :func:`merge`: a config with some fields replaced, given as a nested dict (presets are such dicts).
- :func:`add_flags` / :func:`flag_overrides`: one ``--section.field`` flag per leaf field of a tree, and the
  nested dict of the flags a user typed.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import types
import typing
from typing import Any, Literal, Union

from vid2sim.runtime.errors import ConfigError

# ---- documentation ----------------------------------------------------------------------------------------


def field_docs(cls: type) -> dict[str, str]:
    """The help text of each field of the dataclass ``cls``, from its docstring's ``Attributes:`` section.

    An entry ``name: text`` (continued on more-indented lines) documents ``name``; ``a, b: text`` documents both.
    """
    doc = cls.__doc__ or ""
    match = re.search(r"^(\s*)Attributes:\s*$", doc, flags=re.M)
    if match is None:
        return {}
    docs: dict[str, str] = {}
    indent: int | None = None
    names: list[str] = []
    for line in doc[match.end():].splitlines():
        if not line.strip():
            continue
        width = len(line) - len(line.lstrip())
        if indent is None:
            indent = width
        if width < indent:
            break
        entry = re.match(r"([A-Za-z_][\w, ]*):\s*(.*)", line.strip()) if width == indent else None
        if entry is not None:
            names = [n.strip() for n in entry.group(1).split(",")]
            for n in names:
                docs[n] = entry.group(2)
        else:
            for n in names:
                docs[n] += " " + line.strip()
    return docs


# ---- types ---------------------------------------------------------------------------------------------------


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    """(T, True) for ``T | None``; (tp, False) otherwise."""
    if typing.get_origin(tp) in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


def _describe(tp: Any) -> str:
    inner, optional = _unwrap_optional(tp)
    if typing.get_origin(inner) is Literal:
        text = " or ".join(repr(a) for a in typing.get_args(inner))
    elif typing.get_origin(inner) is tuple:
        text = "a list of numbers"
    else:
        text = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(inner, str(inner))
    return text + (" or null" if optional else "")


def _coerce(value: Any, tp: Any, path: str) -> Any:
    """``value`` (from JSON or a flag) as the type ``tp`` of the field at ``path``; ConfigError otherwise."""
    inner, optional = _unwrap_optional(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{path} must be {_describe(tp)}, got null")
    origin = typing.get_origin(inner)
    bad = ConfigError(f"{path} must be {_describe(tp)}, got {value!r}")
    if dataclasses.is_dataclass(inner):
        if not isinstance(value, dict):
            raise ConfigError(f"{path} must be an object of {inner.__name__}'s fields, got {value!r}")
        return from_dict(inner, value, path)
    if origin is Literal:
        if value not in typing.get_args(inner):
            raise bad
        return value
    if origin is tuple:
        args = typing.get_args(inner)
        if not isinstance(value, (list, tuple)):
            raise bad
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{path}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{path} must hold {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{path}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if inner is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if inner is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if inner is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        return float(value)
    if inner is str:
        if not isinstance(value, str):
            raise bad
        return value
    return value  # a type this module does not check (kept as given)


# ---- dict form -----------------------------------------------------------------------------------------------


def to_dict(config: Any) -> dict[str, Any]:
    """The JSON-ready nested dict of a configuration dataclass (tuples become lists)."""

    def plain(x: Any) -> Any:
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            return {f.name: plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        return x

    return plain(config)


def from_dict(cls: type, data: dict[str, Any], path: str = "") -> Any:
    """An instance of the configuration dataclass ``cls`` from its nested dict; missing fields take their
    defaults (so a ``config.json`` of an older version still loads).

    Raises:
        ConfigError: an unknown key, a value of the wrong type, or a value the dataclass's own checks refuse;
        the message names the dotted path.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{path or cls.__name__} must be an object, got {type(data).__name__}")
    hints = _hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(f"unknown setting {where}{unknown[0]} ({cls.__name__} has {', '.join(sorted(names))})")
    values = {k: _coerce(v, hints[k], f"{path}.{k}" if path else k) for k, v in data.items()}
    return cls(**values)


def merge(config: Any, overrides: dict[str, Any], path: str = "") -> Any:
    """A copy of ``config`` with the fields named in the nested dict ``overrides`` replaced (checked as in
    :func:`from_dict`); nested configurations are merged field by field, not replaced."""
    if not overrides:
        return dataclasses.replace(config)
    hints = _hints(type(config))
    names = {f.name for f in dataclasses.fields(config) if f.init}
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        where = f"{path}.{key}" if path else key
        if key not in names:
            raise ConfigError(f"unknown setting {where} ({type(config).__name__} has {', '.join(sorted(names))})")
        current = getattr(config, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[key] = merge(current, value, where)
        else:
            changes[key] = _coerce(value, hints[key], where)
    return dataclasses.replace(config, **changes)


# ---- command-line flags --------------------------------------------------------------------------------------


def _leaves(cls: type, prefix: str = "") -> list[tuple[str, Any, str]]:
    """(dotted path, type, help) of every leaf field of the configuration tree ``cls``."""
    out = []
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = _hints(cls)[f.name]
        path = f"{prefix}{f.name}"
        inner, optional = _unwrap_optional(tp)
        if dataclasses.is_dataclass(inner) and not optional:
            out += _leaves(inner, path + ".")
        elif not dataclasses.is_dataclass(inner):
            out.append((path, tp, docs.get(f.name, "")))
    return out


def _parser_type(tp: Any, flag: str):
    """An argparse ``type`` callable for a scalar field (``none`` → None where the field allows it)."""
    inner, optional = _unwrap_optional(tp)
    base = inner
    if typing.get_origin(inner) is Literal:
        base = type(typing.get_args(inner)[0])
    if typing.get_origin(inner) is tuple:
        base = typing.get_args(inner)[0]

    def parse(text: str) -> Any:
        if optional and text.lower() in ("none", "null"):
            return None
        try:
            if typing.get_origin(inner) is tuple:  # a list's values: separated by spaces or commas ("4,5")
                return tuple(base(part) for part in text.split(",") if part.strip())
            return base(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected {_describe(tp)}, got {text!r}") from None

    return parse


def add_flags(parser: argparse.ArgumentParser, cls: type, aliases: dict[str, str] | None = None,
              group_title: str | None = None, defaults: typing.Callable[[str], str] | None = None,
              skip: typing.Collection[str] = ()) -> None:
    """One flag per leaf field of the configuration tree ``cls``: ``--section.field`` (booleans also
    ``--no-section.field``; a list takes its values separated by spaces or commas). ``aliases`` maps a short flag
    ("--iterations") to the dotted path it sets ("joint.iterations"); ``defaults(path)`` says what the default is,
    for the help; the dotted paths in ``skip`` get no flag (the caller's own, or a setting its command does not
    use). Defaults are left out of the namespace (argparse.SUPPRESS), so :func:`flag_overrides` returns only what
    was typed."""
    aliases = aliases or {}
    by_path: dict[str, list[str]] = {}
    for flag, path in aliases.items():
        if flag != f"--{path}":
            by_path.setdefault(path, []).append(flag)
    group = parser.add_argument_group(group_title) if group_title else parser
    for path, tp, text in _leaves(cls):
        if path in skip:
            continue
        inner, optional = _unwrap_optional(tp)
        flags = [f"--{path}"] + by_path.get(path, [])
        dest = "config:" + path
        text = (text + (f" ({defaults(path)})" if defaults else "")).strip().replace("%", "%%")
        common = dict(dest=dest, default=argparse.SUPPRESS, help=text or None)
        if inner is bool and not optional:
            group.add_argument(*flags, action=argparse.BooleanOptionalAction, **common)
        elif typing.get_origin(inner) is tuple:
            group.add_argument(*flags, nargs="+", type=_parser_type(tp, flags[0]), metavar="V", **common)
        elif typing.get_origin(inner) is Literal:
            group.add_argument(*flags, type=_parser_type(tp, flags[0]), choices=typing.get_args(inner), **common)
        else:
            group.add_argument(*flags, type=_parser_type(tp, flags[0]), metavar=_describe(inner).split()[-1].upper(),
                               **common)


def flag_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The nested dict of the configuration flags typed on the command line (see :func:`add_flags`)."""
    out: dict[str, Any] = {}
    for dest, value in vars(args).items():
        if not dest.startswith("config:"):
            continue
        *parents, leaf = dest[len("config:"):].split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        if isinstance(value, list):  # a list flag: each typed value is a tuple of its comma-separated parts
            value = [v for part in value for v in (part if isinstance(part, tuple) else (part,))]
        node[leaf] = list(value) if isinstance(value, tuple) else value
    return out


def flag_names(cls: type, aliases: dict[str, str] | None = None) -> dict[str, str]:
    """Dotted path → the flag a user types for it (the alias when there is one), for error messages."""
    names = {path: f"--{path}" for path, _, _ in _leaves(cls)}
    for flag, path in (aliases or {}).items():
        names[path] = flag
    return names


def class_paths(cls: type, prefix: str = "") -> dict[str, str]:
    """``"ClassName.field"`` → dotted path for every leaf of the tree (the names configs' own checks use in their
    messages), so a message can name the flag instead."""
    out: dict[str, str] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        inner, optional = _unwrap_optional(_hints(cls)[f.name])
        path = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(inner) and not optional:
            out.update(class_paths(inner, path + "."))
        else:
            out[f"{cls.__name__}.{f.name}"] = path
    return out


def name_flags(message: str, cls: type, aliases: dict[str, str] | None = None) -> str:
    """``message`` with each ``ClassName.field`` and dotted path of the tree ``cls`` replaced by its flag."""
    flags = flag_names(cls, aliases)
    for qualified, path in sorted(class_paths(cls).items(), key=lambda kv: -len(kv[0])):
        if path in flags:  # (an optional nested configuration has no flags of its own)
            message = re.sub(rf"\b{re.escape(qualified)}\b", flags[path], message)
    return message
