"""Scene files: a generic loader from TOML tables to the options dataclasses.

Every numerical option lives as a typed field of a frozen dataclass next to the code that uses
it (``Material``, ``BodyOptions``, ``NewtonOptions``, ...). This module never repeats those
fields: it reads the dataclass type annotations and converts each TOML value accordingly
(``int``, ``float``, ``bool``, ``str``, ``Literal[...]``, ``tuple[float, ...]``, ``list[...]``,
``dict[str, ...]``, nested dataclasses, ``X | None``). Unknown keys are refused with a
suggestion (``difflib``), wrong types and NaN are refused, and value checks are left to each
dataclass's ``__post_init__``. Every error is an ``InputError`` whose message names the scene
file and the dotted key, e.g.
``scene.toml: unknown key 'body.materal' (did you mean 'material'?)``.

A scene turns on only the physics it uses: a table that is absent leaves its field at the
default, which for optional physics means off (``None``, an empty tuple of obstacles).
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
import tomllib
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from meshes.errors import InputError
from wrinkles.presets import apply_quality

# --------------------------------------------------------------------------------------------
# Where a value came from (for error messages)


@dataclass(frozen=True)
class Source:
    """Names the origin of a table, so errors can point at the file and key.

    Attributes:
        name: file name shown in messages (e.g. ``scene.toml``).
        overridden: dotted keys whose value came from a ``--set`` override.

    """

    name: str = "<dict>"
    overridden: frozenset[str] = frozenset()

    def where(self, key: str) -> str:
        """Return the message prefix ``"<file>: <key>"`` (or ``"--set <key>"``)."""
        if key in self.overridden:
            return f"{self.name}: --set {key}"
        if not self.name:
            return key
        return f"{self.name}: {key}" if key else self.name

    @property
    def lead(self) -> str:
        """``"<file>: "`` (empty for a source without a name)."""
        return f"{self.name}: " if self.name else ""

    def error(self, key: str, message: str) -> InputError:
        """Build the ``InputError`` for ``key`` with a one-line ``message``."""
        return InputError(f"{self.where(key)}: {message}")


def _join(prefix: str, key: str) -> str:
    """Dotted key ``prefix.key`` (just ``key`` at the top level)."""
    return f"{prefix}.{key}" if prefix else key


# --------------------------------------------------------------------------------------------
# Value conversion driven by type annotations


def _type_name(tp: Any) -> str:
    """Readable name of an annotation for error messages."""
    if typing.get_origin(tp) is None and hasattr(tp, "__name__"):
        return str(tp.__name__)
    return str(tp).replace("typing.", "").replace("collections.abc.", "")


def _convert_scalar(value: Any, tp: type, key: str, src: Source) -> Any:
    """Check/convert a TOML scalar to ``bool``, ``int``, ``float`` or ``str``.

    ``int`` is accepted where ``float`` is expected; ``bool`` is never taken as a number;
    ``nan`` is refused because no option means it (``inf`` is left to the dataclass, some
    options use it, e.g. an unbounded box corner).
    """
    if tp is bool and isinstance(value, bool):
        return value
    if tp is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if tp is float and isinstance(value, int | float) and not isinstance(value, bool):
        if math.isnan(value):
            raise src.error(key, "must be a number, got nan")
        return float(value)
    if tp is float and isinstance(value, str) and value in ("inf", "+inf", "-inf"):
        return float(value)  # strict JSON's spelling (summary.json), TOML writes inf
    if tp is str and isinstance(value, str):
        return value
    raise src.error(key, f"expected {tp.__name__}, got {type(value).__name__} {value!r}")


def _convert_literal(value: Any, choices: tuple[Any, ...], key: str, src: Source) -> Any:
    """Accept ``value`` only if it is one of the ``Literal`` choices."""
    for choice in choices:
        if value == choice and type(value) is type(choice):
            return choice
    options = ", ".join(repr(c) for c in choices)
    hint = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1)
    extra = f" (did you mean {hint[0]!r}?)" if hint else ""
    raise src.error(key, f"must be one of {options}, got {value!r}{extra}")


def _convert_union(value: Any, options: tuple[Any, ...], key: str, src: Source) -> Any:
    """Try each member of a union in order; ``None`` only where the union allows it."""
    if value is None:
        if type(None) in options:
            return None
        raise src.error(key, "must not be empty")
    errors = []
    for option in (o for o in options if o is not type(None)):
        try:
            return convert(value, option, key, src)
        except InputError as exc:
            errors.append(exc)
    if len(errors) == 1:
        raise errors[0]
    names = " or ".join(_type_name(o) for o in options if o is not type(None))
    raise src.error(key, f"expected {names}, got {type(value).__name__} {value!r}")


def _convert_sequence(value: Any, tp: Any, key: str, src: Source) -> Any:
    """Convert a TOML array to ``tuple[T, ...]``, ``tuple[T1, T2]``, ``list[T]``.

    ``Sequence[T]`` gives a tuple (immutable, like the frozen dataclasses holding it).
    """
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if not isinstance(value, list | tuple):
        raise src.error(key, f"expected an array ({_type_name(tp)}), got {value!r}")
    if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        if len(value) != len(args):
            raise src.error(key, f"expected {len(args)} values, got {len(value)}")
        return tuple(convert(v, t, f"{key}[{i}]", src) for i, (v, t) in
                     enumerate(zip(value, args, strict=True)))
    item = args[0] if args else Any
    items = [convert(v, item, f"{key}[{i}]", src) for i, v in enumerate(value)]
    return items if origin is list or tp is list else tuple(items)


def _convert_mapping(value: Any, tp: Any, key: str, src: Source) -> dict[str, Any]:
    """Convert a TOML table with free keys to ``dict[str, T]``."""
    if not isinstance(value, Mapping):
        raise src.error(key, f"expected a table, got {value!r}")
    args = typing.get_args(tp)
    item = args[1] if len(args) == 2 else Any
    return {k: convert(v, item, _join(key, k), src) for k, v in value.items()}


def convert(value: Any, tp: Any, key: str, src: Source) -> Any:
    """Convert one TOML value to the annotated type ``tp``.

    Args:
        value: the value read from TOML (or a ``--set`` override, or a resolved dict).
        tp: the resolved type annotation of the target field.
        key: dotted key of the value, for error messages.
        src: where the value came from.

    Returns:
        The converted value (dataclass instances for tables typed as dataclasses).

    Raises:
        InputError: wrong type, NaN, value not in a ``Literal``, unknown key.

    """
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return build(tp, value, key, src)
    if origin is Literal:
        return _convert_literal(value, typing.get_args(tp), key, src)
    if origin in (typing.Union, types.UnionType):
        return _convert_union(value, typing.get_args(tp), key, src)
    if origin in (tuple, list, Sequence) or tp in (tuple, list, Sequence):
        return _convert_sequence(value, tp, key, src)
    if origin in (dict, Mapping) or tp is dict:
        return _convert_mapping(value, tp, key, src)
    if tp in (bool, int, float, str):
        return _convert_scalar(value, tp, key, src)
    if tp is Path:
        return Path(_convert_scalar(value, str, key, src))
    raise src.error(key, f"the loader does not know the type {_type_name(tp)}")


# --------------------------------------------------------------------------------------------
# Tables -> dataclasses and keyword arguments


def _check_keys(table: Mapping[str, Any], known: list[str], prefix: str, src: Source) -> None:
    """Refuse keys not in ``known``, suggesting the closest known key."""
    for key in table:
        if key not in known:
            hint = difflib.get_close_matches(key, known, n=1)
            extra = f" (did you mean '{hint[0]}'?)" if hint else ""
            raise InputError(f"{src.lead}unknown key '{_join(prefix, key)}'{extra}")


def _required(hints: Mapping[str, Any], params: Mapping[str, inspect.Parameter]) -> list[str]:
    """Names of parameters without a default."""
    return [n for n in hints if params[n].default is inspect.Parameter.empty]


def convert_kwargs(hints: Mapping[str, Any], required: list[str], table: Any,
                   prefix: str, src: Source) -> dict[str, Any]:
    """Convert a TOML table to keyword arguments typed by ``hints``.

    Args:
        hints: parameter name -> resolved annotation.
        required: names that must be present.
        table: the TOML table.
        prefix: dotted key of the table.
        src: where the table came from.

    Returns:
        The converted keyword arguments (only the keys present in ``table``).

    """
    if not isinstance(table, Mapping):
        raise src.error(prefix, f"expected a table, got {table!r}")
    _check_keys(table, list(hints), prefix, src)
    for name in required:
        if name not in table:
            raise InputError(f"{src.lead}missing key '{_join(prefix, name)}'")
    return {k: convert(v, hints[k], _join(prefix, k), src) for k, v in table.items()}


def build[T](cls: type[T], table: Any, prefix: str = "", src: Source | None = None) -> T:
    """Build the frozen dataclass ``cls`` from a TOML table.

    Keys map to the ``init`` fields of ``cls`` through their type annotations; absent keys keep
    the field default, also inside a partial table of a field whose default is a dataclass
    instance (``augmented_linear = {ordering = "amd"}`` keeps the default's other values, not
    those of a bare ``LinearSolverOptions``). ``InputError`` raised by ``cls.__post_init__``
    is re-raised with the file and the dotted key of the table prepended.

    Args:
        cls: the dataclass type.
        table: mapping of field name -> TOML value.
        prefix: dotted key of the table (``""`` for the document root).
        src: where the table came from.

    Returns:
        The validated instance.

    """
    src = src or Source()
    fields = [f for f in dataclasses.fields(cls) if f.init]  # type: ignore[arg-type]
    hints = typing.get_type_hints(cls)
    field_hints = {f.name: hints[f.name] for f in fields}
    required = _required(field_hints, inspect.signature(cls).parameters)
    kwargs = convert_kwargs(field_hints, required, _over_field_defaults(fields, table),
                            prefix, src)
    try:
        return cls(**kwargs)
    except InputError as exc:
        raise _prefixed(str(exc), prefix, src) from None


def _over_field_defaults(fields: list[dataclasses.Field[Any]], table: Any) -> Any:
    """``table`` with each sub-table laid over its field's default dataclass instance, if any."""
    if not isinstance(table, Mapping):
        return table
    out = dict(table)
    for f in fields:
        value = out.get(f.name)
        if not isinstance(value, Mapping):
            continue
        default = (f.default_factory() if f.default_factory is not dataclasses.MISSING
                   else f.default)
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            base = to_dict(default)
            _merge(base, value)
            out[f.name] = base
    return out


def _prefixed(message: str, prefix: str, src: Source) -> InputError:
    """Attach file and table to a ``__post_init__`` message.

    Messages that start with the table's own name (``material.E must be > 0``) are joined
    into one dotted key (``scene.toml: body.material.E must be > 0``); others are prefixed
    (``scene.toml: body.material: ...``).
    """
    parent, _, last = prefix.rpartition(".")
    if last and message.startswith(f"{last}."):
        return InputError(f"{src.lead}{_join(parent, message)}")
    return src.error(prefix, message)


def call_kwargs(func: Callable[..., Any], table: Any, prefix: str,
                src: Source, skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """Convert a TOML table to the keyword arguments of ``func`` using its annotations.

    Used for mesh builders: ``[mesh.params]`` keys are checked against the builder signature
    exactly like dataclass fields (unknown keys refused with a suggestion, types converted).

    Args:
        func: the callable whose keyword parameters the table fills.
        table: the TOML table.
        prefix: dotted key of the table.
        src: where the table came from.
        skip: parameter names the table may not set (filled by the caller, e.g. ``comm``).

    """
    hints = typing.get_type_hints(func)
    params = {n: p for n, p in inspect.signature(func).parameters.items()
              if n not in skip and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}
    hints = {n: hints.get(n, Any) for n in params}
    return convert_kwargs(hints, _required(hints, params), table, prefix, src)


# --------------------------------------------------------------------------------------------
# Expert options: dotted keys into an internal options dataclass


def unflatten(options: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """Nest a mapping with dotted keys (``{"shift.growth": 5}`` -> ``{"shift": {"growth": 5}}``).

    Raises:
        InputError: a key is given twice (once dotted, once nested) or crosses a value.

    """
    nested: dict[str, Any] = {}
    for dotted, value in options.items():
        *parents, leaf = str(dotted).split(".")
        table = nested
        for depth, part in enumerate(parents):
            table = table.setdefault(part, {})
            if not isinstance(table, dict):
                key = _join(prefix, ".".join(parents[:depth + 1]))
                raise InputError(f"{key}: is a value, not a table")
        if isinstance(value, Mapping):
            value = unflatten(value, _join(prefix, dotted))
        if leaf in table and not (isinstance(table[leaf], dict) and isinstance(value, dict)):
            raise InputError(f"{_join(prefix, dotted)}: given twice")
        if isinstance(value, dict) and isinstance(table.get(leaf), dict):
            table[leaf].update(value)
        else:
            table[leaf] = value
    return nested


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Return a nested mapping as sorted dotted keys (the canonical form of an expert mapping)."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        dotted = _join(prefix, str(key))
        if isinstance(value, Mapping) and value:
            flat.update(flatten(value, dotted))
        else:
            flat[dotted] = value
    return dict(sorted(flat.items()))


def expert[T](cls: type[T], options: Mapping[str, Any], prefix: str,
              named: Mapping[str, Any] | None = None,
              defaults: Mapping[str, Any] | None = None) -> T:
    """Build the internal options dataclass ``cls`` from named keys and an expert mapping.

    A scene exposes a few named choices of a solver and passes the rest as a mapping of dotted
    field paths of ``cls`` (``[shell.solver.options] "shift.growth" = 5``), the way dolfinx
    passes ``petsc_options``. Both go through the loader's conversion and validation; a key of
    the mapping that one of the named keys already sets is refused (one place per value).

    Args:
        cls: the internal options dataclass.
        options: the expert mapping (dotted or nested keys).
        prefix: dotted key of the mapping, for messages (``shell.solver.options``).
        named: field values set by the scene's named keys (dotted paths of ``cls``).
        defaults: starting values where the scene's defaults differ from ``cls``'s (the
            mapping may change them).

    Raises:
        InputError: unknown key (with a suggestion), wrong type or value, or a key that a
            named key already sets; the message names ``prefix.<key>``.

    """
    named = dict(named or {})
    tree = unflatten(options, prefix)
    for key in named:
        parts, table = key.split("."), tree
        for part in parts[:-1]:
            table = table.get(part, {}) if isinstance(table, dict) else {}
        if isinstance(table, dict) and parts[-1] in table:
            raise InputError(f"{_join(prefix, key)}: set by a named key of the scene, not here")
    merged = unflatten(dict(defaults or {}), prefix)
    _merge(merged, tree)
    _merge(merged, unflatten(named, prefix))
    return build(cls, merged, prefix, Source(""))


def _merge(into: dict[str, Any], other: Mapping[str, Any]) -> None:
    """Deep-merge ``other`` into ``into`` (tables merged, values replaced)."""
    for key, value in other.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            _merge(into[key], value)
        else:
            into[key] = value


# --------------------------------------------------------------------------------------------
# Serialisation


def to_dict(obj: Any) -> Any:
    """Return the resolved configuration as plain JSON-able data (dict, list, str, None...).

    ``build(type(obj), to_dict(obj))`` reproduces ``obj`` (the round trip is tested).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    if isinstance(obj, Mapping):
        return {str(k): to_dict(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_dict(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


# --------------------------------------------------------------------------------------------
# Overrides (--set key=value)


def parse_literal(text: str) -> Any:
    """Parse ``text`` as a TOML literal (``1e4``, ``true``, ``[0, 0, -9.81]``, ``"box"``).

    A bare word that is not valid TOML (``box``) is taken as a string, so
    ``--set mesh.builder=box`` works without shell quoting.
    """
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_override(doc: dict[str, Any], assignment: str, src_name: str) -> str:
    """Apply one ``key=value`` override to the TOML document in place; return the key.

    Intermediate tables are created, and values may be inline TOML, so
    ``--set 'body.contacts=[{obstacle="plane"}]'`` turns ground contact on. The key itself is
    validated later by the loader like any key of the file.
    """
    key, sep, text = assignment.partition("=")
    key = key.strip()
    if not sep or not key or any(not part for part in key.split(".")):
        raise InputError(f"{src_name}: --set expects key=value with a dotted key, "
                         f"got {assignment!r}")
    parts, table, depth = key.split("."), doc, 0
    while depth < len(parts) - 1:
        rest = ".".join(parts[depth:])
        if rest in table:  # a mapping that spells the rest as one dotted key
            break
        table = table.setdefault(parts[depth], {})
        depth += 1
        if not isinstance(table, dict):
            raise InputError(f"{src_name}: --set {key}: "
                             f"'{'.'.join(parts[:depth])}' is not a table")
    table[".".join(parts[depth:])] = parse_literal(text.strip())
    return key


# --------------------------------------------------------------------------------------------
# Reading scene files


def read_toml(path: Path) -> dict[str, Any]:
    """Read a TOML file, turning I/O and syntax errors into ``InputError``."""
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: scene file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, expected a scene file") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path.name}: invalid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text file: {exc}") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the scene file ({exc.strerror})") from None


def load[T](cls: type[T], path: str | Path, overrides: list[str] | None = None,
            overlays: Sequence[Callable[[dict[str, Any], str], Any]] = ()) -> T:
    """Load the dataclass ``cls`` from a TOML file, with ``--set key=value`` overrides.

    A top-level ``quality`` key selects a preset overlay (:mod:`wrinkles.presets`), merged
    after the overrides into the keys still absent: ``--set`` > file keys > preset > defaults.

    Args:
        cls: root dataclass of the document (``wrinkles.scene.Scene`` for scene files).
        path: the TOML file.
        overrides: ``key=value`` strings applied after reading, in order.
        overlays: further ``overlay(doc, file name)`` fills of absent keys, applied after the
            preset (e.g. the defaults that follow a scene's ``up`` axis).

    Returns:
        The validated instance.

    """
    path = Path(path)
    doc = read_toml(path)
    keys = [apply_override(doc, text, path.name) for text in overrides or []]
    apply_quality(doc, path.name)
    for overlay in overlays:
        overlay(doc, path.name)
    return build(cls, doc, "", Source(path.name, frozenset(keys)))


__all__ = [
    "Source",
    "apply_override",
    "build",
    "call_kwargs",
    "convert",
    "expert",
    "flatten",
    "load",
    "parse_literal",
    "read_toml",
    "to_dict",
    "unflatten",
]
