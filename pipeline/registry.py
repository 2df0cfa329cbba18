"""Plug-in registries: one per axis (map sources, retrieval methods, priors, global descriptors).

An entry is a frozen settings dataclass registered under its name: its fields are its settings,
its class attributes say what it needs and what it gives (``flags``: its command-line options,
relative to its fields; ``help``: one line for the command line's choices), its methods run it
and validate it. The command line, the presets, the planner and the benchmarks read the entries;
nothing else names one. A new plug-in is one class with ``@REGISTRY.register("name")``.

A job records an entry's settings with its name under the registry's ``tag``
(``{"name": "sift", "min_inliers": 10, ...}``); ``Registry.parse`` reads them back, absent fields
at their defaults.
"""

from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Dict

from pipeline.settings import parse


class Registry(dict):
    """``name -> entry class``. ``axis``: what an entry is, in messages ("prior"); ``tag``: the key
    that names the entry in a recorded dict."""

    def __init__(self, axis: str, tag: str = "name"):
        super().__init__()
        self.axis, self.tag = axis, tag

    def register(self, name: str):
        """Class decorator: the settings dataclass ``cls`` becomes the entry ``name``."""
        def add(cls):
            if name in self:
                raise ValueError(f"{self.axis} {name!r} is registered twice")
            if not is_dataclass(cls):
                raise TypeError(f"{self.axis} {name!r}: an entry is a settings dataclass")
            cls.name = name
            self[name] = cls
            return cls
        return add

    def entry(self, name: str) -> type:
        """The entry ``name``; an unknown name is refused with the known ones."""
        if name not in self:
            raise ValueError(f"Unknown {self.axis} {name!r}: use one of {', '.join(self)}.")
        return self[name]

    def record(self, settings) -> Dict:
        """An entry's settings as a job records them: its name under ``tag``, then its fields."""
        return {self.tag: settings.name, **asdict(settings)}

    def parse(self, tree: Dict, where: str = "settings"):
        """An entry's settings from ``record``'s form (absent fields at their defaults)."""
        if not isinstance(tree, dict):
            raise ValueError(f"{where}: {self.axis} settings are a mapping, not {tree!r}.")
        tree = dict(tree)
        cls = self.entry(tree.pop(self.tag, None))
        return parse(cls, tree, f"{where} ({self.axis} {cls.name})")


def check_inputs(settings, needs: str) -> None:
    """Refuse an entry's settings whose input files (the fields named by its ``inputs``) are not
    given or do not exist; ``needs``: how messages name the entry (``--prior poses``)."""
    for name in settings.inputs:
        path = getattr(settings, name)
        if not path:
            flag = next((f for f, flag in settings.flags.items() if flag.path == name), name)
            raise ValueError(f"{needs} needs {flag} FILE.")
        if not Path(path).is_file():
            raise ValueError(f"Input file {path} does not exist.")
