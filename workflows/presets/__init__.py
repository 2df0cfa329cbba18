"""Dataset presets: the paper's settings per dataset, as YAML data (see the .yaml files here)."""

from importlib import resources
from typing import Any, Dict, List, Optional

import yaml


def available() -> List[str]:
    return sorted(p.name[:-5] for p in resources.files(__package__).iterdir() if p.name.endswith(".yaml"))


def load(name: str) -> Dict:
    path = resources.files(__package__) / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"Unknown preset {name!r}; available: {', '.join(available())}.")
    preset = yaml.safe_load(path.read_text()) or {}
    check_keys(_dotted(preset), PRESET_KEYS | {f"from_poses.{k}" for k in PRESET_KEYS}, f"preset {name}.yaml")
    return preset


def check_keys(keys, allowed, where: str) -> None:
    """Refuse keys that are not in ``allowed`` (a misspelt key would pass unnoticed and its
    setting be the default), with the nearest valid name."""
    import difflib

    unknown = sorted(set(keys) - set(allowed))
    if unknown:
        hints = []
        for key in unknown:
            near = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=0.6)
            hints.append(f"{key!r}" + (f" (did you mean {near[0]!r}?)" if near else ""))
        raise ValueError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(hints)}; "
                         f"valid keys: {', '.join(sorted(allowed))}.")


def _dotted(d: Dict, prefix: str = "") -> List[str]:
    out = []
    for k, v in d.items():
        if isinstance(v, dict) and k not in ("layout",):
            out += _dotted(v, f"{prefix}{k}.")
        else:
            out.append(prefix + k)
    return out


# command-line option -> where a preset holds its value
MAPPING = {
    "resize": ("features", "resize"), "image_scales": ("features", "image_scales"), "pad": ("features", "pad"),
    "num_dbs": ("localizer", "num_dbs"), "average_observations": ("localizer", "average_observations"),
    "iters": ("localizer", "num_iters"), "retrieval_k": ("retrieval", "k"),
    "same_tag": ("retrieval", "same_tag"), "prior": ("prior",), "levels": ("levels",),
    "point_selection": ("point_selection",), "min_points": ("localizer", "min_points"), "scales": ("scales",),
    "points_per_cell": ("localizer", "points_per_cell"),
    "pose_names": ("pose_names",),
}


# what a preset may hold: the settings of MAPPING (also under ``from_poses``), and its documentation
PRESET_KEYS = {".".join(path) for path in MAPPING.values()} | {"description", "layout", "thresholds", "model_hint"}


def _lookup(preset: Dict, keys) -> Any:
    value = preset
    for k in keys:
        value = value.get(k) if isinstance(value, dict) else None
    return value


def apply(args, preset: Optional[Dict], defaults: Dict) -> None:
    """Resolve the options in ``defaults`` that the command line left unset (``None``): the
    preset's value if it has one, else the built-in default. An option given on the command
    line always wins, whatever its value.

    A preset's ``from_poses`` block (the paper's refinement-mode settings) overrides the rest
    when the prior comes from another pipeline (``--prior hloc`` or ``poses``); its point
    selection (hloc's PnP inliers) applies only with ``--prior hloc``, which has them.
    """
    preset = preset or {}
    prior = args.prior if getattr(args, "prior", None) is not None else preset.get("prior")
    if prior in ("hloc", "poses") and "from_poses" in preset:
        from_poses = dict(preset["from_poses"])
        if prior != "hloc":
            from_poses.pop("point_selection", None)
        preset = _merge(preset, from_poses)
    for arg, default in defaults.items():
        if not hasattr(args, arg) or getattr(args, arg) is not None:
            continue
        value = _lookup(preset, MAPPING[arg]) if arg in MAPPING else None
        setattr(args, arg, value if value is not None else default)


def _merge(base: Dict, override: Dict) -> Dict:
    out = dict(base)
    for k, v in override.items():
        out[k] = _merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out
