"""Settings as frozen, nested dataclasses: one place that builds them from plain data.

The job (``pipeline.localization.shard.LocalizationJob``), a store's feature settings and every
plug-in's own settings are frozen dataclasses holding their defaults. Their values come in by
dotted path (``localizer.num_iters``): from a dataset preset, the command line, or a recorded
``job.json``.

- ``build(cls, *layers)``: the dataclass from its defaults and the layers, later ones winning; a key
  that is no field is refused with the nearest valid name, a value of another type is refused
  naming its key.
- ``parse(cls, tree)``: the dataclass from a nested dict (as ``asdict`` writes it): absent fields
  take their defaults, so settings recorded before a field existed are the same settings.
- ``Flag``: how a field is set on the command line (``workflows.options`` makes the options).
"""

import dataclasses
import difflib
import typing
from dataclasses import dataclass
from typing import Any, Dict, Iterable, Optional, Sequence


@dataclass(frozen=True)
class Flag:
    """The command-line option of the field at ``path``. ``choices``: its valid values; ``value``: a
    flag without argument that sets the field to this value (``--no-verify``: ``False``); ``file``:
    a path, made absolute once; ``metavar``: its placeholder in the help."""

    path: str
    help: str
    choices: Optional[Sequence[str]] = None
    value: Any = None
    file: bool = False
    metavar: Optional[str] = None


def field_types(cls, prefix: str = "") -> Dict[str, Any]:
    """Every field of ``cls`` and of its nested dataclasses, by dotted path, with its type (a
    nested dataclass is a field too: it can be given whole)."""
    out = {}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        out[prefix + f.name] = hints[f.name]
        if is_dataclass_type(hints[f.name]):
            out.update(field_types(hints[f.name], f"{prefix}{f.name}."))
    return out


def default_of(cls, path: str) -> Any:
    """The default of the field at ``path`` (nested dataclasses at their own defaults)."""
    head, _, rest = path.partition(".")
    f = next(f for f in dataclasses.fields(cls) if f.name == head)
    if rest:
        return default_of(typing.get_type_hints(cls)[head], rest)
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else None


def parse(cls, tree: Dict, where: str = "settings"):
    """``cls`` from a nested dict (``asdict``'s form): absent fields at their defaults, an unknown
    key or a value of another type refused (ValueError naming ``where`` and the key)."""
    return build(cls, dotted(tree), where=where)


def dotted(tree: Dict, prefix: str = "", keep: Iterable[str] = ()) -> Dict[str, Any]:
    """A nested dict as ``{dotted path: value}``; the keys in ``keep`` stay whole."""
    out = {}
    for k, v in tree.items():
        if isinstance(v, dict) and k not in keep:
            out.update(dotted(v, f"{prefix}{k}.", keep))
        else:
            out[prefix + k] = v
    return out


def check_keys(keys, allowed, where: str) -> None:
    """Refuse keys that are not in ``allowed`` (a misspelt key would pass unnoticed and its
    setting be the default), with the nearest valid name."""
    unknown = sorted(set(keys) - set(allowed))
    if unknown:
        hints = []
        for key in unknown:
            near = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=0.6)
            hints.append(f"{key!r}" + (f" (did you mean {near[0]!r}?)" if near else ""))
        raise ValueError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(hints)}; "
                         f"valid keys: {', '.join(sorted(allowed))}.")


def build(cls, *layers: Dict[str, Any], where: str = "settings", names: Optional[Dict[str, str]] = None):
    """``cls`` from its defaults, then each layer (``{dotted path: value}``) in turn; a value of
    another type than its field's is refused, naming ``where`` and the key (as ``names`` shows it,
    where the user's file gives it by another name)."""
    values: Dict[str, Any] = {}
    for layer in layers:
        check_keys(layer, field_types(cls), where)
        values.update(layer)
    try:
        return _build(cls, values, "")
    except _WrongType as e:
        key = (names or {}).get(e.key, e.key)
        raise ValueError(f"{where}: {key} is {e.value!r}, not {_described(e.kind)}.") from None


class _WrongType(Exception):
    def __init__(self, key: str, value, kind):
        super().__init__(key)
        self.key, self.value, self.kind = key, value, kind


def _build(cls, values: Dict[str, Any], prefix: str):
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        key, kind = prefix + f.name, hints[f.name]
        if key in values:
            kwargs[f.name] = _coerce(values[key], kind, key)
        elif is_dataclass_type(kind) and (f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
                                   or any(k.startswith(key + ".") for k in values)):
            base = values.get(key)
            kwargs[f.name] = _build(kind, values, key + ".") if base is None else _coerce(base, kind, key)
    return cls(**kwargs)


def is_dataclass_type(kind) -> bool:
    return isinstance(kind, type) and dataclasses.is_dataclass(kind)


def plain_type(kind):
    """``Optional[X]`` as ``X``."""
    args = [a for a in typing.get_args(kind) if a is not type(None)]
    return args[0] if typing.get_origin(kind) is typing.Union and len(args) == 1 else kind


def item_type(kind):
    """The type of one value: ``Tuple[int, ...]`` -> int; others as they are."""
    if typing.get_origin(kind) in (tuple, list):
        return typing.get_args(kind)[0]
    return kind


def _coerce(value, kind, key: str = "value"):
    """``value`` as its field's type ``kind``: YAML and argparse give lists where the dataclass keeps
    tuples (hashable, as recorded); a whole number is a float too. A value of another
    type (a string for a number, a list for a string, NaN) is refused: before, it reached the
    dataclass's range checks as a TypeError, or ran."""
    converted = _converted(value, kind)
    if converted is _WRONG:
        raise _WrongType(key, value, kind)
    return converted


_WRONG = object()


def _converted(value, kind):
    plain = plain_type(kind)
    if plain is not kind and value is None:  # Optional
        return None
    if plain is typing.Any or plain is dict or typing.get_origin(plain) is dict or plain is typing.Dict:
        return value if plain is typing.Any or isinstance(value, dict) else _WRONG
    if is_dataclass_type(plain):
        return value if isinstance(value, plain) else _WRONG
    if plain is bool:
        return value if isinstance(value, bool) else _WRONG
    if plain is int:
        if isinstance(value, float) and value.is_integer():
            return int(value)
        return value if isinstance(value, int) and not isinstance(value, bool) else _WRONG
    if plain is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value == value  # not NaN
        return value if ok else _WRONG
    if plain is str:
        return value if isinstance(value, str) else _WRONG
    if plain is tuple or typing.get_origin(plain) is tuple:
        if not isinstance(value, (list, tuple)):
            return _WRONG
        args = typing.get_args(plain)
        if not args:  # a bare Tuple: any items
            return tuple(value)
        items = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        if len(items) != len(value):
            return _WRONG
        out = tuple(_converted(v, k) for v, k in zip(value, items))
        return _WRONG if any(v is _WRONG for v in out) else out
    return value


def _described(kind, plural: bool = False) -> str:
    plain = plain_type(kind)
    nouns = {bool: ("true or false", "true or false values"), int: ("a whole number", "whole numbers"),
             float: ("a number", "numbers"), str: ("a string", "strings")}
    text = nouns[plain][plural] if plain in nouns else None
    if text is None and (plain is tuple or typing.get_origin(plain) is tuple):
        args = typing.get_args(plain)
        text = ("a list" if not args else f"a list of {_described(args[0], True)}" if args[-1] is Ellipsis
                else f"a list of {len(args)}: " + ", ".join(_described(a) for a in args))
    text = text or getattr(plain, "__name__", str(plain)) + ("s" if plural else "")
    return text + (" or null" if plain is not kind else "")
