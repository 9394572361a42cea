"""Small RGB-D raw folders made by the tests: a tilted flat board with a dome of tissue on it, pressed
in its middle a little more each frame, filmed by a depth camera (and an unregistered colour one)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from tests.rawfixtures import make_raw

DEPTH_SIZE = 64
COLOR_SIZE = 48
FX = 80.0
BOARD_MM = 500.0  # depth of the board at the image centre
TILT_MM_PER_PX = 2.0  # the board recedes towards the top of the image
DOME_MM = 25.0  # height of the tissue above the board
DOME_CENTRE = (32.0, 34.0)
DOME_RADIUS_PX = 16.0
PRESS_MM_PER_FRAME = 0.8


def depth_frame(i: int, size: int = DEPTH_SIZE) -> np.ndarray:
    """Depth (size, size) float mm of frame i: board plus dome, the dome's middle pressed in."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    # a plane is linear in inverse depth over the pixels: 1/z = 1/BOARD_MM + b (v - size/2)
    board = 1.0 / (1.0 / BOARD_MM + TILT_MM_PER_PX / BOARD_MM ** 2 * (v - size / 2))
    r = np.hypot(u - DOME_CENTRE[0], v - DOME_CENTRE[1]) / DOME_RADIUS_PX
    dome = np.where(r < 1, DOME_MM * np.sqrt(np.clip(1 - r ** 2, 0, 1)), 0.0)
    press = PRESS_MM_PER_FRAME * i * np.exp(-(r * 3) ** 2)
    return board - dome + press


def make_rgbd(folder: Path, n: int = 12, *, color: bool = True, calibration: bool = True, holes: bool = True) -> Path:
    """An RGB-D raw folder (docs/raw_layout.md): depth/ 16-bit mm, color/ (optional), frames.csv,
    force.csv (a rostopic export whose fz follows the press), rgbd_calibration.yaml, meta.yaml."""
    make_raw(folder, n=n, width=COLOR_SIZE, height=COLOR_SIZE, force_rate_hz=30.0, pose=False, rostopic=True)
    for name in ("left", "right"):
        shutil.rmtree(folder / name)
    (folder / "calibration.yaml").unlink()
    (folder / "depth").mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        depth = np.rint(depth_frame(i)).astype(np.uint16)
        if holes:
            depth[rng.integers(0, DEPTH_SIZE, 5), rng.integers(0, DEPTH_SIZE, 5)] = 0
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), depth)
    if color:
        (folder / "color").mkdir()
        for i in range(n):
            image = np.full((COLOR_SIZE, COLOR_SIZE, 3), 200, np.uint8)
            cv2.circle(image, (24, 25), 12, (60, 40, 160 + i), -1)
            cv2.imwrite(str(folder / "color" / f"{i:06d}.png"), image)
    if calibration:
        c = (DEPTH_SIZE - 1) / 2
        cc = (COLOR_SIZE - 1) / 2
        (folder / "rgbd_calibration.yaml").write_text(
            f"depth: {{width: {DEPTH_SIZE}, height: {DEPTH_SIZE}, fx: {FX}, fy: {FX}, cx: {c}, cy: {c}}}\n"
            f"color: {{width: {COLOR_SIZE}, height: {COLOR_SIZE}, fx: 70.0, fy: 70.0, cx: {cc}, cy: {cc}}}\n"
            "assumptions: [principal point at the centre]\n")
    (folder / "meta.yaml").write_text("study: test\ntissue: dome\norientation_deg: 0\nprompt_box: [8, 10, 56, 58]\n")
    return folder
