"""Dataset presets: the paper's settings per dataset, as YAML data (see the .yaml files here).

A preset's keys are the fields of the jobs it sets, by the same names: ``localizer.num_iters``,
``retrieval.k``, ``prior`` (a prior's name) ... of ``pipeline.localization.shard.LocalizationJob``, a
prior's own settings under its name (``hloc.point_selection``), and ``features.resize`` ...
of the map's ``pipeline.mapping.features.FeatureConfig``; a ``from_poses`` block overrides them in
refinement mode; ``thresholds`` and ``pose_names`` set the outputs; ``description``, ``layout``
and ``model_hint`` document it. Any other key is refused with the nearest valid name.
"""

from importlib import resources
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from pipeline.localization.priors import PRIORS
from pipeline.localization.shard import LocalizationJob
from pipeline.textfiles import read_yaml

from ..options import check_keys, dotted, field_types

# what a preset cannot set: the run's inputs, and the store's own feature settings (a localize job
# takes them from the store)
INPUTS = {"store", "model", "device", "retrieval", "features"}
DOCUMENTATION = {"description", "layout", "model_hint"}
OUTPUTS = {"thresholds", "pose_names"}
# a prior's own settings, under its name (``hloc.point_selection``); its input files are the run's
ENTRY_SETTINGS = {f"{name}.{k}" for name, entry in PRIORS.items() for k in field_types(entry)
                  if k.split(".")[0] not in entry.inputs}
SETTINGS = {k for k in field_types(LocalizationJob) if k not in INPUTS and k != "features.model"} | ENTRY_SETTINGS
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


def job_settings(preset: Optional[Dict], prior: Optional[str]) -> Tuple[Dict[str, Any], Dict[str, Dict]]:
    """The localize job's fields that ``preset`` sets, by dotted path, and its blocks of entry
    settings (``{"prior": {"name": its prior, NAME: {field: value}}}``). Its ``from_poses`` block
    (the paper's refinement-mode settings) overrides the rest when the prior (``prior``, else the
    preset's) refines another pipeline's poses (``given_poses``); a prior's own settings apply to
    that prior only."""
    preset = dict(preset or {})
    prior = prior if prior is not None else preset.get("prior")
    from_poses = dict(preset.pop("from_poses", None) or {})
    settings = {k: v for k, v in dotted(preset, keep=("layout",)).items()
                if k in SETTINGS and not k.startswith("features.")}
    if prior is not None and PRIORS.entry(prior).given_poses:
        settings.update({k: v for k, v in dotted(from_poses).items() if not k.startswith("features.")})
    blocks: Dict[str, Dict] = {"prior": {}}
    if "prior" in settings:
        blocks["prior"]["name"] = settings.pop("prior")
    for key in [k for k in settings if k in ENTRY_SETTINGS]:
        name, field = key.split(".", 1)
        blocks["prior"].setdefault(name, {})[field] = settings.pop(key)
    return settings, blocks


def feature_settings(preset: Optional[Dict]) -> Dict[str, Any]:
    """The map's feature settings (``FeatureConfig`` fields) that ``preset`` sets."""
    return dotted((preset or {}).get("features", {}))
