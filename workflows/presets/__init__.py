"""Dataset presets: the paper's settings per dataset, as YAML data (see the .yaml files here).

A preset's keys are the fields of the jobs it sets, by the same names: ``localizer.num_iters``,
``retrieval.k``, ``prior`` ... of ``pipeline.localization.shard.LocalizationJob`` and ``features.resize`` ...
of the map's ``pipeline.mapping.features.FeatureConfig``; a ``from_poses`` block overrides them in
refinement mode; ``thresholds`` and ``pose_names`` set the outputs; ``description``, ``layout``
and ``model_hint`` document it. Any other key is refused with the nearest valid name.
"""

from importlib import resources
from pathlib import Path
from typing import Any, Dict, List, Optional

from pipeline.localization.shard import LocalizationJob
from pipeline.textfiles import read_yaml

from ..options import check_keys, dotted, field_types

# what a preset cannot set: the run's inputs, and the store's own feature settings (a localize job
# takes them from the store)
INPUTS = {"store", "model", "device", "prior_poses", "hloc_logs", "retrieval.method", "retrieval.pairs",
          "retrieval.descriptors", "features"}
DOCUMENTATION = {"description", "layout", "model_hint"}
OUTPUTS = {"thresholds", "pose_names"}
SETTINGS = {k for k in field_types(LocalizationJob) if k not in INPUTS and k != "features.model"}
# every key a preset may hold (also under ``from_poses``: the settings)
PRESET_KEYS = SETTINGS | DOCUMENTATION | OUTPUTS | {f"from_poses.{k}" for k in SETTINGS}


def available() -> List[str]:
    return sorted(p.name[:-5] for p in resources.files(__package__).iterdir() if p.name.endswith(".yaml"))


def load(name: str) -> Dict:
    path = resources.files(__package__) / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"Unknown preset {name!r}; available: {', '.join(available())}.")
    preset = read_yaml(Path(str(path)), f"preset {name}.yaml")
    check_keys(dotted(preset, keep=("layout",)), PRESET_KEYS, f"preset {name}.yaml")
    return preset


def job_settings(preset: Optional[Dict], prior: Optional[str]) -> Dict[str, Any]:
    """The localize job's fields that ``preset`` sets, by dotted path: its ``from_poses`` block
    (the paper's refinement-mode settings) overrides the rest when the prior comes from another
    pipeline (``prior`` ``hloc`` or ``poses``: the command line's, else the preset's); its point
    selection (hloc's PnP inliers) applies only with ``hloc``, which has them."""
    preset = dict(preset or {})
    prior = prior if prior is not None else preset.get("prior")
    from_poses = dict(preset.pop("from_poses", None) or {})
    settings = {k: v for k, v in dotted(preset, keep=("layout",)).items()
                if k in SETTINGS and not k.startswith("features.")}
    if prior in ("hloc", "poses") and from_poses:
        if prior != "hloc":
            from_poses.pop("point_selection", None)
        settings.update(dotted(from_poses))
    return settings


def feature_settings(preset: Optional[Dict]) -> Dict[str, Any]:
    """The map's feature settings (``FeatureConfig`` fields) that ``preset`` sets."""
    return dotted((preset or {}).get("features", {}))
