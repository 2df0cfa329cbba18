"""``pixloc queries``: a query list with intrinsics for uncalibrated photos, from their EXIF."""

import argparse
from collections import Counter
from pathlib import Path

from pipeline.exif import DEFAULT_FOCAL_FACTOR, exif_camera, find_images, format_line
from pipeline.textfiles import write_atomic

SOURCES = {"35mm-equivalent": "from the 35 mm equivalent focal length",
           "focal-plane": "from the focal length and the focal plane resolution",
           "default": "without EXIF focal length: {factor} x the larger image side (a guess: check their results)"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", type=Path, nargs="+", help="image folders (searched recursively) or files")
    p.add_argument("--out", type=Path, default=Path("queries_with_intrinsics.txt"),
                   help="query list to write (default queries_with_intrinsics.txt); names are relative to the "
                        "folder given, so pass that folder as --query-images to pixloc localize")
    p.add_argument("--default-focal", type=float, default=DEFAULT_FOCAL_FACTOR, metavar="FACTOR",
                   help=f"focal length of images without EXIF, times their larger side (default "
                        f"{DEFAULT_FOCAL_FACTOR}, COLMAP's)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    found = find_images(args.images)
    if not found:
        raise ValueError(f"No images ({', '.join(s for s in ('.jpg', '.png', '.tif'))}, ...) under "
                         f"{', '.join(map(str, args.images))}.")
    cameras, skipped = [], []
    for name, path in found:
        if any(c.isspace() for c in name):
            skipped.append((name, "the name has white space, which a query list cannot hold: rename the file"))
            continue
        try:
            cameras.append(exif_camera(path, name, args.default_focal))
        except (OSError, ValueError) as e:
            skipped.append((name, str(e)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, "# name MODEL width height params (from EXIF, pixloc queries)\n"
                 + "".join(format_line(c) + "\n" for c in cameras))
    by = Counter(c.source for c in cameras)
    print(f"{len(cameras)} of {len(found)} images -> {args.out}")
    for source, text in SOURCES.items():
        if by[source]:
            print(f"  {by[source]} {text.format(factor=args.default_focal)}")
    defaulted = [c.name for c in cameras if c.source == "default"]
    if defaulted:
        print(f"    {', '.join(defaulted[:5])}{' ...' if len(defaulted) > 5 else ''}")
    for name, reason in skipped:
        print(f"  skipped {name}: {reason}")
    return 1 if skipped else 0
