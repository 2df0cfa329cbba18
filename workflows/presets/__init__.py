"""Dataset presets: the paper's settings per dataset, as YAML data (see the .yaml files here)."""

from importlib import resources
from typing import Dict, List

import yaml


def available() -> List[str]:
    return sorted(p.name[:-5] for p in resources.files(__package__).iterdir() if p.name.endswith(".yaml"))


def load(name: str) -> Dict:
    path = resources.files(__package__) / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"Unknown preset {name!r}; available: {', '.join(available())}.")
    return yaml.safe_load(path.read_text())


def apply(args, preset: Dict, defaults: Dict) -> None:
    """Set ``args`` fields from the preset where the user left the command-line default.

    A preset's ``from_poses`` block (the paper's refinement-mode settings) overrides the rest
    when the prior comes from another pipeline (``--prior hloc`` or ``poses``).
    """
    if getattr(args, "prior", None) in ("hloc", "poses") and "from_poses" in preset:
        preset = _merge(preset, preset["from_poses"])
    mapping = {
        "resize": ("features", "resize"), "image_scales": ("features", "image_scales"), "pad": ("features", "pad"),
        "num_dbs": ("localizer", "num_dbs"), "average_observations": ("localizer", "average_observations"),
        "iters": ("localizer", "num_iters"), "retrieval_k": ("retrieval", "k"),
        "same_tag": ("retrieval", "same_tag"), "prior": ("prior",), "levels": ("levels",),
        "point_selection": ("point_selection",), "min_points": ("localizer", "min_points"), "scales": ("scales",),
    }
    for arg, keys in mapping.items():
        if not hasattr(args, arg) or getattr(args, arg) != defaults.get(arg):
            continue
        value = preset
        for k in keys:
            value = value.get(k) if isinstance(value, dict) else None
        if value is not None:
            setattr(args, arg, value)


def _merge(base: Dict, override: Dict) -> Dict:
    out = dict(base)
    for k, v in override.items():
        out[k] = _merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out
