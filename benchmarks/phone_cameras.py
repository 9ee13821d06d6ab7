"""Cameras of phone clips against a reference: tomgs' built-in tracker beside pycolmap's incremental SfM.

    python -m benchmarks.phone_cameras ../shared/data/phone/{dog,juggle,blocks,cat}.mp4 [--step 3] [--side 640]
    python -m benchmarks.phone_cameras --smoke      # a 12-frame synthetic orbit (known cameras) on the CPU

tomgs runs as a fit runs it (`estimate_cameras` on every frame at the clip's size). The reference is
pycolmap (`pip install pycolmap`; an optional import of this script only, never of tomgs): every
--step-th frame at --side pixels, SIFT, sequential matching, one shared SIMPLE_PINHOLE camera,
incremental mapping with the initial pair's angle lowered to 4 degrees (hand-held clips move little).
Without pycolmap the reference's columns say so and only tomgs' run.

Per clip: tomgs' mode (fixed cameras: every frame "fixed"), focal, median reprojection error and time;
the reference's registered frames, focal and mean reprojection error. Both focals are in pixels of
the clip's own frames. Motion: each side's largest rotation from the first frame (degrees) and its path
length over the median depth of the first frame's points ("path/depth"); the reference's image motion
("still px": the largest median shift of the verified SIFT matches over its matched pairs, clip pixels),
which shows a fixed camera where SfM cannot start. On the frames both have, after re-anchoring both on
the first of them: the rotation error (largest, degrees) and the path error (largest camera-centre
error after a similarity alignment over the reference's path length). Writes phone_cameras.md / .json.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from tomgs import estimate_cameras, read_video
from tomgs.poses.synthetic import make_clip, orbit, trajectory_errors

if __package__:
    from .common import environment, markdown_table, output_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, markdown_table, output_folder, write_report

NAME = "phone_cameras"


def rotation_deg(R: np.ndarray) -> np.ndarray:
    """Angles in degrees of rotations R [N,3,3]."""
    cos = (np.einsum("nii->n", R) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def motion(c2w: np.ndarray, depth: float) -> tuple[float, float]:
    """(largest rotation from frame 0 in degrees, path length / depth) of c2w [N,4,4]."""
    rel = np.linalg.inv(c2w[0]) @ c2w
    path = np.linalg.norm(np.diff(rel[:, :3, 3], axis=0), axis=1).sum()
    return float(rotation_deg(rel[:, :3, :3]).max()), float(path / depth) if depth > 0 else float("nan")


def run_tomgs(clip: Path) -> dict:
    """The built-in tracker on every frame of `clip`, as a fit runs it."""
    video = read_video(clip)
    t0 = time.perf_counter()
    cams, _, _, rep = estimate_cameras(video)
    seconds = time.perf_counter() - t0
    rot, path = motion(cams.c2w, 1.0)  # tomgs' gauge: the median depth of frame 0's points is 1
    return dict(frames=len(cams.c2w), size=[cams.width, cams.height], mode=rep.mode, focal=float(cams.focal),
                fixed=len(cams.c2w) if rep.mode == "fixed" else 0, reproj_px=rep.reproj_px, seconds=seconds,
                rotation_deg=rot, path_over_depth=path, c2w=cams.c2w, indices=np.asarray(cams.frame_indices),
                notes=rep.notes)


def pycolmap_or_none():
    try:
        import pycolmap
    except ImportError:
        return None
    return pycolmap


def match_shift(pycolmap, db_path: Path) -> float:
    """The largest median shift (pixels of the images in the database) of the verified matches of a
    matched pair: under a pixel for a fixed camera whatever moves in front of it."""
    db = pycolmap.Database.open(db_path)
    try:
        keys = {im.image_id: db.read_keypoints(im.image_id)[:, :2] for im in db.read_all_images()}
        worst = 0.0
        for pair, geometry in zip(*db.read_two_view_geometries()):
            m = geometry.inlier_matches
            if len(m) < 15:
                continue
            a, b = pycolmap.pair_id_to_image_pair(pair)
            worst = max(worst, float(np.median(np.linalg.norm(keys[a][m[:, 0]] - keys[b][m[:, 1]], axis=1))))
    finally:
        db.close()
    return worst


def run_reference(pycolmap, clip: Path, work: Path, step: int, side: int) -> dict:
    """pycolmap's incremental SfM on every `step`-th frame of `clip` at `side` pixels: its focal (in the
    clip's pixels), registered frames, cameras c2w [N,4,4] with their source frame numbers."""
    from PIL import Image

    video = read_video(clip, frames=f"::{step}", max_side=side)
    images = work / "images"
    images.mkdir(parents=True, exist_ok=True)
    for k, frame in zip(video.indices, video.frames):
        Image.fromarray(frame).save(images / f"{int(k):06d}.jpg", quality=95)
    db = work / "database.db"
    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = 4096
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 8
    pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.multiple_models = False
    options.mapper.init_min_tri_angle = 4.0
    options.mapper.init_min_num_inliers = 50
    (work / "sparse").mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(db, images, work / "sparse", options=options)
    seconds = time.perf_counter() - t0
    full = read_video(clip, frames="0:1").frames.shape[2]
    to_clip = full / video.frames.shape[2]  # reference pixels -> the clip's pixels
    out = dict(frames=len(video.indices), registered=0, focal=None, reproj_px=None, seconds=seconds,
               still_px=match_shift(pycolmap, db) * to_clip, rotation_deg=None, path_over_depth=None)
    if not models:
        return out
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    ims = sorted(rec.images.values(), key=lambda im: im.name)
    c2w = np.stack([np.linalg.inv(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]])) for im in ims])
    first = ims[0]
    X = np.array([rec.points3D[p.point3D_id].xyz for p in first.points2D if p.has_point3D()])
    depth = float(np.median((X @ c2w[0, :3, :3] - c2w[0, :3, 3] @ c2w[0, :3, :3])[:, 2])) if len(X) else 0.0
    rot, path = motion(c2w, depth)
    (camera,) = rec.cameras.values()
    out.update(registered=len(ims), focal=float(camera.params[0]) * to_clip,
               reproj_px=float(rec.compute_mean_reprojection_error()) * to_clip, rotation_deg=rot,
               path_over_depth=path, c2w=c2w, indices=np.array([int(Path(im.name).stem) for im in ims]))
    return out


def compare(ours: dict, ref: dict) -> dict:
    """Focal ratio, and on the frames both have (re-anchored on the first of them) the largest rotation
    error in degrees and the largest camera-centre error after a similarity alignment over the
    reference's path length."""
    if not ref.get("registered"):
        return dict(focal_ratio=None, rotation_error_deg=None, path_error=None)
    pos = {int(k): i for i, k in enumerate(ours["indices"])}
    both = [(pos[int(k)], i) for i, k in enumerate(ref["indices"]) if int(k) in pos]
    a = ours["c2w"][[i for i, _ in both]]
    b = ref["c2w"][[j for _, j in both]]
    a, b = np.linalg.inv(a[0]) @ a, np.linalg.inv(b[0]) @ b
    path, rot = trajectory_errors(a, b)
    return dict(focal_ratio=ours["focal"] / ref["focal"], rotation_error_deg=rot, path_error=path)


def smoke_clip(folder: Path) -> tuple[Path, np.ndarray, float]:
    """A 12-frame synthetic orbit as a folder of PNGs: (folder, its c2w [T,4,4], its focal)."""
    from PIL import Image

    clip = make_clip(orbit(12, strafe=2.4), width=240, height=180, focal=200.0, mover=False, seed=3)
    folder.mkdir(parents=True, exist_ok=True)
    for k, frame in enumerate(clip.frames):
        Image.fromarray(frame).save(folder / f"{k:05d}.png")
    return folder, clip.c2w, float(clip.K[0, 0])


HEAD = ["clip", "frames", "tomgs mode", "tomgs focal", "fixed frames", "tomgs reproj px", "tomgs rot deg",
        "tomgs path/depth", "tomgs s", "ref registered", "ref focal", "ref reproj px", "ref rot deg",
        "ref path/depth", "ref still px", "ref s", "focal ratio", "rot error deg", "path error"]


def row_of(r: dict) -> list:
    t, c, d = r["tomgs"], r["reference"], r["compare"]
    reg = "pycolmap not installed" if c is None else f"{c['registered']}/{c['frames']}"
    c = c or {}
    reproj = t["reproj_px"] if np.isfinite(t["reproj_px"]) else None  # a fixed camera has no error to measure
    return [r["clip"], t["frames"], t["mode"], t["focal"], t["fixed"], reproj, t["rotation_deg"],
            t["path_over_depth"], t["seconds"], reg, c.get("focal"), c.get("reproj_px"), c.get("rotation_deg"),
            c.get("path_over_depth"), c.get("still_px"), c.get("seconds"), d.get("focal_ratio"),
            d.get("rotation_error_deg"), d.get("path_error")]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clips", nargs="*", type=Path, help="videos or folders of frames")
    ap.add_argument("--step", type=int, default=3, help="the reference sees every STEP-th frame")
    ap.add_argument("--side", type=int, default=640, help="the reference's frames' long side (px)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--smoke", action="store_true", help="a 12-frame synthetic orbit, CPU, seconds")
    args = ap.parse_args(argv)
    out = output_folder(args.out, args.smoke, NAME)
    pycolmap = pycolmap_or_none()
    truth = None
    if args.smoke:
        clip, c2w, focal = smoke_clip(out / "smoke_clip")
        args.clips, args.step, args.side, truth = [clip], 1, 240, dict(c2w=c2w, focal=focal)
    if not args.clips:
        ap.error("give clips (videos or folders of frames), or --smoke")
    rows = []
    for clip in args.clips:
        ours = run_tomgs(clip)
        ref = None
        if pycolmap is not None:
            with tempfile.TemporaryDirectory(prefix="tomgs-colmap-") as work:
                ref = run_reference(pycolmap, clip, Path(work), args.step, args.side)
        row = dict(clip=clip.stem if clip.is_file() else clip.name, tomgs=ours, reference=ref,
                   compare=compare(ours, ref) if ref is not None else {})
        if truth is not None:
            row["truth"] = dict(focal=truth["focal"], path_error=trajectory_errors(ours["c2w"], truth["c2w"])[0])
        rows.append(row)
        print(row_of(row), flush=True)
    for r in rows:  # the JSON keeps the figures, not the cameras
        for side in (r["tomgs"], r["reference"] or {}):
            side.pop("c2w", None)
            side["indices"] = None
    body = (("pycolmap is not installed: the reference's columns are empty (`pip install pycolmap`)\n\n"
             if pycolmap is None else "") + markdown_table(HEAD, [row_of(r) for r in rows]))
    write_report(out, NAME, "Phone clips' cameras: tomgs against pycolmap", environment("cpu", NAME, argv),
                 body, rows)


if __name__ == "__main__":
    main()
