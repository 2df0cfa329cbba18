"""The training sets of official PixLoc in their public layouts: MegaDepth and Extended CMU
Seasons, with the preprocessed info files that cvg/pixloc releases for them.

MegaDepth::

    <root>/Undistorted_SfM/<scene>/images/<name>        images
    <root>/megadepth_pixloc_training/<scene>.pkl        image_names, poses [(R, t)], intrinsics [K],
                                                        points3D (P, 3), p3D_observed [ids], overlap_matrix

Extended CMU Seasons::

    <root>/slice<N>/database/<name>, slice<N>/query/<name>   images (``..._c0_...`` or ``_c1_``)
    <root>/cmu_pixloc_training/slice<N>.pkl             ref_/query_image_names, ref_/query_poses,
                                                        points3D, p3D_observed (of references),
                                                        query_closest_indices, query_overlap_matrix

Pairs are those of the official samplers (overlap in (min_overlap, 1]); CMU queries observe
the points of their closest reference, and CMU training starts from the reference pose.
The info files are pickles: they are read with an unpickler that accepts numpy arrays and
plain containers only, never code.
"""

from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from pipeline.scene import CameraRecord, ImageRecord, Scene, SceneError
from pipeline.mapping.readers.safe_pickle import load_data_pickle

# The two cameras of Extended CMU Seasons (official pixloc/pixlib/datasets/cmu.py).
CMU_CAMERAS = {
    "c0": CameraRecord("OPENCV", 1024, 768, (868.993378, 866.063001, 525.942323, 420.042529,
                                             -0.399431, 0.188924, 0.000153, 0.000571)),
    "c1": CameraRecord("OPENCV", 1024, 768, (873.382641, 876.489513, 529.324138, 397.272397,
                                             -0.397066, 0.181925, 0.000176, -0.000579)),
}
def read_info(path) -> Dict:
    return load_data_pickle(path, "PixLoc training info file")


def _matrix(R, t) -> np.ndarray:
    return np.concatenate([np.asarray(R, float).reshape(3, 3), np.asarray(t, float).reshape(3, 1)], 1)


def _observations(observed: List[np.ndarray]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    obs_point = np.concatenate([np.asarray(o, np.int64).reshape(-1) for o in observed])
    obs_image = np.concatenate([np.full(len(np.asarray(o).reshape(-1)), i) for i, o in enumerate(observed)])
    return obs_point, obs_image, np.full((len(obs_point), 2), np.nan)


def _overlap_pairs(mat: np.ndarray, min_overlap: float, max_overlap: float = 1.0) -> List[Tuple[int, int]]:
    i, j = np.nonzero((mat > min_overlap) & (mat <= max_overlap))
    return list(zip(i.tolist(), j.tolist()))


def read_megadepth(root, scene: str, min_overlap: float = 0.3) -> Tuple[Scene, List[Tuple[int, int]]]:
    """One MegaDepth scene and its (reference, query) pairs."""
    root = Path(root)
    info = read_info(root / "megadepth_pixloc_training" / f"{scene}.pkl")
    images = []
    for name, (R, t), K in zip(info["image_names"], info["poses"], info["intrinsics"]):
        K = np.asarray(K, float)
        # official: a PINHOLE camera whose size is twice the principal point
        camera = CameraRecord("PINHOLE", int(round(2 * K[0, 2])), int(round(2 * K[1, 2])),
                              (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        images.append(ImageRecord(str(name), root / "Undistorted_SfM" / scene / "images" / str(name), camera,
                                  _matrix(R, t), {"scene": scene}))
    obs = _observations(info["p3D_observed"])
    pairs = _overlap_pairs(np.asarray(info["overlap_matrix"]), min_overlap)
    return Scene(images, np.asarray(info["points3D"], float), *obs), pairs


def read_cmu_slice(root, slice_: int, min_overlap: float = 0.3) -> Tuple[Scene, List[Tuple[int, int]]]:
    """One Extended CMU Seasons slice: references then queries, and (reference, query) pairs."""
    root = Path(root)
    info = read_info(root / "cmu_pixloc_training" / f"slice{slice_}.pkl")
    images = []
    for prefix, folder in (("ref", "database"), ("query", "query")):
        for name, (R, t) in zip(info[f"{prefix}_image_names"], info[f"{prefix}_poses"]):
            cam_id = next((p for p in str(name).split("_") if p in CMU_CAMERAS), None)
            if cam_id is None:
                raise SceneError(f"CMU image {name} names no camera (c0 or c1).")
            images.append(ImageRecord(str(name), root / f"slice{slice_}" / folder / str(name), CMU_CAMERAS[cam_id],
                                      _matrix(R, t), {"slice": str(slice_), "split": prefix}))
    num_ref = len(info["ref_image_names"])
    observed = list(info["p3D_observed"]) + [info["p3D_observed"][k] for k in info["query_closest_indices"]]
    obs = _observations(observed)
    mat = np.asarray(info["query_overlap_matrix"])  # (queries, references)
    pairs = [(j, num_ref + i) for i, j in _overlap_pairs(mat, min_overlap)]
    return Scene(images, np.asarray(info["points3D"], float), *obs), pairs
