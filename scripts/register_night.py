"""A reference pose for the Sacre Coeur night photo (``data/sacre_coeur/query/night.jpg``), in
the frame of the oracle's SfM model of the 10 day photos (``oracle/sacre_coeur_sfm``).

Independent of PixLoc (so that it can judge PixLoc): SIFT and 2D-3D matching, then
P3P-RANSAC and refinement with pycolmap, as docs/night.md describes:

1. SfM of the 10 day photos with pycolmap (``run_sfm``: SIFT, exhaustive matching): its
   database holds the descriptors of every track's observations.
2. SIFT of the night photo at three resolutions (full, 1/2, 1/3); each keypoint is matched to
   the nearest track descriptor (RootSIFT, ratio 0.85 against the best other 3D point).
3. ``pycolmap.estimate_and_refine_absolute_pose`` with the focal length of the photo's EXIF
   (35 mm equivalent 34 mm: f = 34 / 35 x 2816 = 2735.5 px, as ``pixloc queries`` reads it), fixed.
   The resolution with the most inliers gives the pose; the other two give its spread.
4. A similarity from this SfM's 10 camera centres to the oracle model's moves the pose there.

Usage: python scripts/register_night.py [--shared ../shared] [--work /tmp/night-registration]
Writes tests/data/sacre_coeur_night.json.
"""

import argparse
import json
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from pipeline.exif import exif_camera
from pipeline.images import read_image
from pipeline.mapping.readers.colmap import run_sfm

HERE = Path(__file__).resolve().parent.parent


def track_descriptors(rec: pycolmap.Reconstruction, database: Path):
    """(N, 128) unit RootSIFT descriptors of every observation of every 3D point, and the point ids."""
    db = sqlite3.connect(database)
    ids = {n: i for i, n in db.execute("select image_id, name from images")}
    desc = {i: np.frombuffer(b, np.uint8).reshape(r, c)
            for i, r, c, b in db.execute("select image_id, rows, cols, data from descriptors")}
    D, P = [], []
    for pid, p in rec.points3D.items():
        for el in p.track.elements:
            D.append(desc[ids[rec.images[el.image_id].name]][el.point2D_idx])
            P.append(pid)
    D = np.asarray(D, np.float32)
    return D / np.linalg.norm(D, axis=1, keepdims=True), np.asarray(P)


def match_2d3d(keypoints, descriptors, D, P, ratio=0.85):
    d = descriptors.astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sim = d @ D.T
    top = np.argsort(-sim, axis=1)[:, :30]
    keep, target = [], []
    for k in range(len(d)):
        first = top[k, 0]
        others = [j for j in top[k, 1:] if P[j] != P[first]]
        s2 = sim[k, others[0]] if others else 0.0
        d1, d2 = np.sqrt(max(0.0, 2 - 2 * sim[k, first])), np.sqrt(max(0.0, 2 - 2 * s2))
        if d1 < ratio * d2:
            keep.append(k)
            target.append(P[first])
    return keypoints[keep, :2].astype(np.float64), np.asarray(target)


def guided_matches(keypoints, descriptors, D, P, rec, T, params, radius, min_similarity=0.8):
    """Each keypoint matched to the most similar track descriptor among the 3D points that
    project within ``radius`` pixels of it at pose ``T``."""
    d = descriptors.astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ids = np.array(sorted(rec.points3D))
    xyz = np.array([rec.points3D[int(i)].xyz for i in ids]) @ T[:, :3].T + T[:, 3]
    front = xyz[:, 2] > 0
    uv = xyz[:, :2] / np.where(front, xyz[:, 2], 1)[:, None] * params[0] + np.asarray(params[1:3])
    where = {int(i): k for k, i in enumerate(ids)}
    obs_uv = uv[[where[int(p)] for p in P]]
    obs_ok = front[[where[int(p)] for p in P]]
    index = np.nonzero(obs_ok)[0]
    p2d, pid = [], []
    for start in range(0, len(keypoints), 2000):
        kp = keypoints[start:start + 2000]
        near = np.linalg.norm(kp[:, None] - obs_uv[index][None], axis=-1) < radius
        sim = np.where(near, d[start:start + 2000] @ D[index].T, -1)
        j = sim.argmax(1)
        for k in np.nonzero(sim[np.arange(len(kp)), j] >= min_similarity)[0]:
            p2d.append(kp[k])
            pid.append(P[index[j[k]]])
    return np.asarray(p2d, np.float64), np.asarray(pid)


def umeyama(src: np.ndarray, dst: np.ndarray):
    """Scale s, rotation R, translation t with dst ~ s R src + t (least squares)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    E = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ E @ Vt
    s = np.trace(np.diag(S) @ E) / a.var(0).sum()
    return s, R, mu_d - s * R @ mu_s


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--shared", type=Path, default=HERE.parent / "shared")
    p.add_argument("--work", type=Path, default=Path("/tmp/night-registration"))
    p.add_argument("--output", type=Path, default=HERE / "tests" / "data" / "sacre_coeur_night.json")
    args = p.parse_args()
    root = args.shared / "data" / "sacre_coeur"
    night = root / "query" / "night.jpg"
    camera = exif_camera(night).camera
    run_sfm(root / "mapping", args.work)
    rec = pycolmap.Reconstruction(str(next((args.work / "sparse").iterdir())))
    D, P = track_descriptors(rec, args.work / "database.db")
    gray = read_image(night).mean(-1).astype(np.float32) / 255
    pcam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=camera.width, height=camera.height,
                           params=list(camera.params[:3]))
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = 16000
    options.max_image_size = 4000
    options.num_threads = 1
    sift = pycolmap.Sift(options, pycolmap.Device.cpu)
    estimates, pooled = [], []
    for scale in (1.0, 0.5, 1 / 3):
        im = gray if scale == 1 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        kps, desc = sift.extract(np.ascontiguousarray(im))
        p2d, pid = match_2d3d(kps, desc, D, P)
        p2d /= scale
        p3d = np.array([rec.points3D[int(i)].xyz for i in pid])
        ransac = pycolmap.AbsolutePoseEstimationOptions()
        ransac.ransac.max_error = 12.0
        res = pycolmap.estimate_and_refine_absolute_pose(p2d, p3d, pcam, ransac)
        if res is None:
            print(f"scale {scale:.2f}: {len(p2d)} matches, no pose")
            continue
        # guided matching: keypoints near the projection of a 3D point at that pose, then again
        for radius in (16.0, 6.0):
            p2d, pid = guided_matches(kps[:, :2] / scale, desc, D, P, rec, res["cam_from_world"].matrix(),
                                      pcam.params, radius)
            p3d = np.array([rec.points3D[int(i)].xyz for i in pid])
            ransac.ransac.max_error = 4.0
            res = pycolmap.estimate_and_refine_absolute_pose(p2d, p3d, pcam, ransac)
        T = res["cam_from_world"].matrix()
        inl = np.asarray(res["inlier_mask"])
        X = p3d[inl] @ T[:, :3].T + T[:, 3]
        err = np.linalg.norm(X[:, :2] / X[:, 2:] * pcam.params[0] + pcam.params[1:3] - p2d[inl], axis=1)
        pooled.append((p2d[inl], p3d[inl]))
        estimates.append({"scale": scale, "matches": len(p2d), "inliers": int(res["num_inliers"]),
                          "inlier_points": len(set(pid[inl].tolist())), "median_error_px": float(np.median(err)),
                          "cam_from_world": T})
        print(f"scale {scale:.2f}: {len(p2d)} matches, {res['num_inliers']} inliers, "
              f"median reprojection error {np.median(err):.2f} px")
    # all resolutions' inliers together, with the focal length and a radial distortion refined
    p2d, p3d = (np.concatenate(x) for x in zip(*pooled))
    radial = pycolmap.Camera(model="SIMPLE_RADIAL", width=camera.width, height=camera.height,
                             params=list(camera.params[:3]) + [0.0])
    ransac.ransac.max_error = 4.0
    refine = pycolmap.AbsolutePoseRefinementOptions()
    refine.refine_focal_length = True
    refine.refine_extra_params = True
    res = pycolmap.estimate_and_refine_absolute_pose(p2d, p3d, radial, ransac, refine)
    inl = np.asarray(res["inlier_mask"])
    print(f"pooled: {len(p2d)} matches, {res['num_inliers']} inliers; refined camera {radial.params}")
    estimates.append({"scale": "pooled", "matches": len(p2d), "inliers": int(res["num_inliers"]),
                      "camera": {"model": "SIMPLE_RADIAL", "params": [float(x) for x in radial.params]},
                      "cam_from_world": res["cam_from_world"].matrix()})
    best = estimates[-1]

    oracle = pycolmap.Reconstruction(str(args.shared / "oracle" / "sacre_coeur_sfm"))
    centre = lambda im: im.cam_from_world().inverse().translation if callable(im.cam_from_world) \
        else im.cam_from_world.inverse().translation
    ours = {im.name: centre(im) for im in rec.images.values()}
    theirs = {im.name: centre(im) for im in oracle.images.values()}
    names = sorted(set(ours) & set(theirs))
    src, dst = np.array([ours[n] for n in names]), np.array([theirs[n] for n in names])
    s, R, t = umeyama(src, dst)
    residual = np.linalg.norm((s * src @ R.T + t) - dst, axis=1)

    def to_oracle(T):  # x_oracle = s R x_ours + t; camera coordinates scaled by s to the oracle's units
        Rc, tc = T[:, :3], T[:, 3]
        return np.hstack([Rc @ R.T, (s * tc - Rc @ R.T @ t)[:, None]])

    poses = [to_oracle(e["cam_from_world"]) for e in estimates]
    T0 = poses[estimates.index(best)]
    for e, T in zip(estimates, poses):
        dR = np.degrees(np.arccos(np.clip((np.trace(T[:, :3] @ T0[:, :3].T) - 1) / 2, -1, 1)))
        e["rotation_from_chosen_deg"] = float(dR)
        e["centre_from_chosen"] = float(np.linalg.norm(-T[:, :3].T @ T[:, 3] + T0[:, :3].T @ T0[:, 3]))
        print(f"scale {e['scale']}: {dR:.2f} deg, {e['centre_from_chosen']:.3f} from the chosen pose")
    C = lambda T: -T[:, :3].T @ T[:, 3]
    spread_t = max(np.linalg.norm(C(T) - C(T0)) for T in poses)
    spread_R = max(np.degrees(np.arccos(np.clip((np.trace(T[:, :3] @ T0[:, :3].T) - 1) / 2, -1, 1)))
                   for T in poses)
    depths = []
    for im in oracle.images.values():
        Tm = (im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world).matrix()
        xyz = np.array([oracle.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()])
        depths.append(np.linalg.norm(xyz @ Tm[:, :3].T + Tm[:, 3], axis=1))
    median_distance = float(np.median(np.concatenate(depths)))
    out = {"query": "sacre_coeur/query/night.jpg", "frame": "oracle/sacre_coeur_sfm",
           "camera": {"model": "SIMPLE_PINHOLE", "width": camera.width, "height": camera.height,
                      "params": list(camera.params[:3])},
           "cam_from_world": T0.tolist(),
           "estimates": [{k: v for k, v in e.items() if k != "cam_from_world"} for e in estimates],
           "spread": {"centre": float(spread_t), "rotation_deg": float(spread_R),
                      "centre_relative": float(spread_t / median_distance)},
           "alignment": {"images": len(names), "scale": float(s), "rms_centre_residual": float(np.sqrt(
               (residual ** 2).mean())), "max_centre_residual": float(residual.max())},
           "median_camera_to_point_distance": median_distance,
           "method": "scripts/register_night.py (docs/night.md)"}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps({k: out[k] for k in ("spread", "alignment", "median_camera_to_point_distance")}, indent=1))
    print(f"written: {args.output}")


if __name__ == "__main__":
    main()
