"""What could more source views add where they do not help? Reads two `deepstereo eval`
runs of one scene that differ in the number of source views (`--json` and `--images` of
each, e.g. 4 and 8 views) and scores, against the held-out photographs, each run's
renders and an *oracle* that takes, per pixel, whichever render is closer (L1 over RGB)
to the photograph, and the two renders' mean. The oracle sees the photograph, so its
gain over the first run bounds what choosing between the two renders per pixel could
give; two renders that differ only by noise still gain a little from it.
Renders are read from their 8-bit PNGs, the photographs with ffmpeg (area-scaled to the
renders' size when `eval --downscale` was used), so PSNRs differ from `eval`'s by up to
about 0.15 dB; both runs are read alike. Needs numpy (python/requirements.txt) and ffmpeg.
Usage: python python/oracle_views.py A.json B.json A_IMAGES B_IMAGES PHOTO_DIR
"""
import json
import subprocess
import sys

import numpy as np


def read_rgb(path, size=None):
    """An image as float [H, W, 3] in [0, 1], scaled to size (w, h) with ffmpeg's area filter."""
    vf = f"scale={size[0]}:{size[1]}:flags=area" if size else "null"
    raw = subprocess.run(
        ["ffmpeg", "-v", "error", "-i", path, "-vf", vf, "-f", "rawvideo", "-pix_fmt", "rgb24", "-"],
        capture_output=True, check=True).stdout
    if size is None:
        probe = subprocess.run(
            ["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries",
             "stream=width,height", "-of", "csv=p=0", path],
            capture_output=True, text=True, check=True).stdout.strip().split(",")
        size = (int(probe[0]), int(probe[1]))
    return np.frombuffer(raw, np.uint8).reshape(size[1], size[0], 3) / 255.0


def psnr(a, b):
    return 10 * np.log10(1 / np.mean((a - b) ** 2))


def main(a_json, b_json, a_dir, b_dir, photos):
    a_views = json.load(open(a_json))["per_view"]
    b_views = json.load(open(b_json))["per_view"]
    rows = []
    print("view  A  B  oracle  mean(A,B)")
    for va, vb in zip(a_views, b_views):
        i = va["target"]
        assert vb["target"] == i, "the two runs hold out different views"
        a = read_rgb(f"{a_dir}/view_{i:03d}.png")
        b = read_rgb(f"{b_dir}/view_{i:03d}.png")
        truth = read_rgb(f"{photos}/{va['name']}", (a.shape[1], a.shape[0]))
        closer = (np.abs(a - truth).sum(-1) <= np.abs(b - truth).sum(-1))[..., None]
        row = [psnr(a, truth), psnr(b, truth), psnr(np.where(closer, a, b), truth),
               psnr((a + b) / 2, truth)]
        rows.append(row)
        print(i, " ".join(f"{x:.2f}" for x in row))
    print("mean", " ".join(f"{x:.2f}" for x in np.mean(rows, 0)))


if __name__ == "__main__":
    if len(sys.argv) != 6:
        sys.exit(__doc__)
    main(*sys.argv[1:])
