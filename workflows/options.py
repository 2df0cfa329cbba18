"""The command line of a job's settings (``pipeline.settings``: the dataclasses hold the settings and
their defaults; a dataset preset and then the command line override them by dotted path).

- ``Flag(path, help)``: the command-line option of one field; ``add_flags`` takes its type,
  choices and shown default from the dataclass, so a new option is its field plus one line.
- ``given(args, flags)``: the fields the command line set.
"""

import argparse
from pathlib import Path
from typing import Any, Dict

from pipeline.settings import Flag, build, check_keys, default_of, dotted, field_types, item_type, plain_type

__all__ = ["Flag", "add_flags", "at_least", "build", "check_keys", "dotted", "field_types", "given"]


def at_least(minimum: int):
    """An argparse type: a whole number of at least ``minimum`` (a count: examples, threads, pairs),
    refused by argparse with the option's name otherwise."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, not {value}")
        return value
    parse.__name__ = "at_least"
    return parse


def add_flags(parser, cls, flags: Dict[str, Flag], prefix: str = "") -> None:
    """One option per flag, defaulting to ``None`` (unset: the preset or the dataclass decides);
    ``prefix``: before each field's path in the parsed arguments (a plug-in's own options)."""
    types = field_types(cls)
    for name, flag in flags.items():
        kind = plain_type(types[flag.path])
        default = default_of(cls, flag.path)
        switch = flag.value is not None or kind is bool  # a flag without argument
        note = "" if "default" in flag.help or switch or default is None else f" (default {shown(default)})"
        kwargs: Dict[str, Any] = {"dest": prefix + flag.path, "default": None, "help": flag.help + note}
        if switch:
            kwargs.update(action="store_const", const=True if flag.value is None else flag.value)
        else:
            item = item_type(kind)
            kwargs["type"] = Path if flag.file else item
            if flag.choices:
                kwargs["choices"] = list(flag.choices)
            else:
                kwargs["metavar"] = flag.metavar or name.lstrip("-").upper().replace("-", "_")
            if item is not kind:  # a tuple: several values
                kwargs["nargs"] = "+"
        parser.add_argument(name, **kwargs)


def given(args: argparse.Namespace, flags: Dict[str, Flag], prefix: str = "") -> Dict[str, Any]:
    """The fields that the command line set, by dotted path (files made absolute)."""
    out = {}
    for flag in flags.values():
        value = getattr(args, prefix + flag.path, None)
        if value is not None:
            out[flag.path] = str(Path(value).expanduser().resolve()) if flag.file else value
    return out


def shown(value) -> str:
    """A default as the help shows it."""
    if isinstance(value, tuple):
        return " ".join(str(v) for v in value)
    return str(value)

