"""Checks a camera path's geometry against the capture it was made from.

    deepstereo inspect --scene SCENE --json > scene.json
    deepstereo render --scene SCENE --path --frames 8 --out OUT
    python python/path_check.py scene.json OUT/cameras.json

Both files are in `inspect --json`'s layout (world-to-camera `R` row-major, `t`, OpenCV
axes). It prints, for the path's cameras: their distance to the point the captured
cameras look at (least squares over their optical axes) in units of the captured
cameras' median distance to it, the largest angle between a path camera's axis and the
direction to that point, and, for every capture, how far the path's centres stray from
the captured centres' mean against the captured ones' own largest distance from it.
Exit status 1 when a check of `--expect orbit` (distances 0.6-1.5x, facing within 5
degrees) or `--expect within` (the path inside the capture's spread) fails.
"""

import argparse
import json
import sys

import numpy as np


def cameras(path):
    with open(path) as f:
        views = json.load(f)["views"]
    out = []
    for v in views:
        r = np.array(v["R"], dtype=float).reshape(3, 3)
        t = np.array(v["t"], dtype=float)
        out.append((-r.T @ t, r[2]))  # centre, optical axis (third row of R)
    return out


def look_at(cams):
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in cams:
        m = np.eye(3) - np.outer(d, d)
        a += m
        b += m @ c
    return np.linalg.solve(a, b)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene_json")
    ap.add_argument("cameras_json")
    ap.add_argument("--expect", choices=["orbit", "within"])
    a = ap.parse_args()
    rig, path = cameras(a.scene_json), cameras(a.cameras_json)
    centres = np.array([c for c, _ in rig])
    mean = centres.mean(axis=0)
    spread = np.linalg.norm(centres - mean, axis=1).max()
    stray = max(np.linalg.norm(c - mean) for c, _ in path)
    p = look_at(rig)
    med = np.median(np.linalg.norm(centres - p, axis=1))
    ratios = [np.linalg.norm(c - p) / med for c, _ in path]
    facing = [np.degrees(np.arccos(np.clip(d @ (p - c) / np.linalg.norm(p - c), -1, 1)))
              for c, d in path]
    print(f"{len(path)} path cameras, {len(rig)} captured")
    print(f"distance to the look-at point: {min(ratios):.2f}-{max(ratios):.2f} x the captured median")
    print(f"largest angle from facing it: {max(facing):.2f} degrees")
    print(f"largest distance from the captured mean centre: {stray:.4g} (captured: {spread:.4g}, {stray / spread:.2f}x)")
    ok = True
    if a.expect == "orbit":
        ok = 0.6 <= min(ratios) and max(ratios) <= 1.5 and max(facing) < 5.0
    elif a.expect == "within":
        ok = stray <= spread
    print("ok" if ok else "FAILED")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
