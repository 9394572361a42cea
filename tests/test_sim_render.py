"""Rendering of the simulated scene: the mask follows the projected geometry, the depth is the
visible surface's, and stereo matching on a rendered pair recovers that depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vfdata.sim.presets import get_preset
from vfdata.sim.render import rasterize
from vfdata.sim.scene import SceneRenderer
from vfdata.sim.synthesize import build_recording, grasped_nodes


@pytest.fixture(scope="module")
def scene():
    rec = build_recording(get_preset("mini").recordings[0], seed=3, frames=2)
    model = rec.model
    model.relax(tol_n=1e-8)
    nodes = grasped_nodes(model, rec.grasp_fraction * model.tube.shape.length_mm)
    grasp = model.x[nodes].mean(0)
    renderer = SceneRenderer(rec.spec, np.random.default_rng(0))
    frame = renderer.render(model.nodes, grasp, 0.0, 0.0)
    return rec, renderer, frame


def _splat_tube(rec, renderer, samples=(600, 360)):
    """Independent check: project a dense sampling of the tube surface with a z-buffer. Returns the
    covered pixels, the depth with pin holes filled, and the raw splat depth (inf where no sample)."""
    tube = rec.spec.tube
    cam = rec.spec.cam.camera
    s = np.linspace(0, tube.arc_length_mm, samples[0])
    th = np.linspace(0, 2 * np.pi, samples[1], endpoint=False)
    p, _, _ = tube.surface_map(s, th).evaluate(rec.model.nodes)
    pc = p.reshape(-1, 3) @ renderer.r_co.T + renderer.t_co
    uv = cam.project(pc)
    u = np.floor(uv[:, 0] + 0.5).astype(int)
    v = np.floor(uv[:, 1] + 0.5).astype(int)
    ok = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    zbuf = np.full(cam.height * cam.width, np.inf)
    np.minimum.at(zbuf, v[ok] * cam.width + u[ok], pc[ok, 2])
    zbuf = zbuf.reshape(cam.height, cam.width)
    covered = np.isfinite(zbuf).astype(np.uint8)
    covered = cv2.morphologyEx(covered, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)).astype(bool)
    # Fill the splat's pin holes with the nearest surface around them (a 5x5 minimum).
    filled = cv2.erode(np.where(np.isfinite(zbuf), zbuf, 1e9).astype(np.float32), np.ones((5, 5), np.uint8))
    return covered, np.where(covered, filled, np.inf), zbuf


def test_mask_matches_projected_geometry(scene):
    rec, renderer, frame = scene
    covered, zbuf, _ = _splat_tube(rec, renderer)
    # Where the splat saw the tube and nothing in the rendered depth is in front of it (the jaws).
    z = np.where(np.isfinite(zbuf), zbuf, 0)
    in_front = (frame.depth_mm > 0) & (frame.depth_mm < z - 1.0) & np.isfinite(zbuf)
    expected = covered & ~in_front
    inter = (expected & frame.mask).sum()
    union = (expected | frame.mask).sum()
    assert frame.mask.sum() > 5000
    assert inter / union > 0.95


def test_depth_is_that_of_the_tube_inside_the_mask(scene):
    rec, renderer, frame = scene
    _, front, zbuf = _splat_tube(rec, renderer)
    # Pixels the splat hit on the front surface (not through a pin hole onto the back).
    with np.errstate(invalid="ignore"):  # inf - inf where the splat saw nothing
        both = frame.mask & np.isfinite(zbuf) & (np.abs(zbuf - front) < 1.0)
    both = cv2.erode(both.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    err = np.abs(frame.depth_mm[both] - zbuf[both])
    assert np.median(err) < 0.05  # mm
    assert np.percentile(err, 99) < 0.3
    assert (frame.depth_mm > 0).all()  # the bed fills the rest of the view


def _sgbm_depth(rec, frame) -> np.ndarray:
    """Depth (mm) from OpenCV SGBM on the pair as written to disk (JPEG, quality 95)."""
    cam = rec.spec.cam.camera

    def as_written(bgr: np.ndarray) -> np.ndarray:
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)

    block = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=96, blockSize=block, P1=8 * block**2,
                                 P2=32 * block**2, uniquenessRatio=5, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_HH)
    disparity = sgbm.compute(as_written(frame.left), as_written(frame.right)).astype(np.float32) / 16.0
    return cam.depth_from_disparity(disparity, rec.spec.cam.baseline_mm)


def test_sgbm_recovers_the_true_depth_inside_the_mask(scene):
    rec, _, frame = scene
    depth = _sgbm_depth(rec, frame)
    inside = cv2.erode(frame.mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    valid = inside & np.isfinite(depth)
    assert valid.sum() > 0.8 * inside.sum()
    rel = np.abs(depth[valid] - frame.depth_mm[valid]) / frame.depth_mm[valid]
    assert np.median(rel) < 0.02
    assert (rel < 0.05).mean() > 0.9


def test_background_is_one_surface_seen_by_both_views(scene):
    """The tissue bed behind the tube is a 3D surface rendered consistently in both views: stereo
    matching on it recovers its true depth too (away from the left border, which the right view
    does not see, and from the tube's and instrument's edges)."""
    rec, _, frame = scene
    depth = _sgbm_depth(rec, frame)
    background = (~frame.mask) & (frame.depth_mm > 0)
    background = cv2.erode(background.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    background[:, :100] = False
    valid = background & np.isfinite(depth)
    assert valid.sum() > 0.8 * background.sum()
    rel = np.abs(depth[valid] - frame.depth_mm[valid]) / frame.depth_mm[valid]
    assert np.median(rel) < 0.03
    assert (rel < 0.05).mean() > 0.75


def test_views_differ_by_the_baseline_disparity(scene):
    """A patch of the tube in the left view appears in the right view shifted left by f * b / z."""
    rec, _, frame = scene
    cam = rec.spec.cam.camera
    left = cv2.cvtColor(frame.left, cv2.COLOR_BGR2GRAY).astype(np.float32)
    right = cv2.cvtColor(frame.right, cv2.COLOR_BGR2GRAY).astype(np.float32)
    inside = cv2.erode(frame.mask.astype(np.uint8), np.ones((31, 31), np.uint8)).astype(bool)
    ys, xs = np.nonzero(inside)
    errors = []
    for k in np.linspace(0, len(ys) - 1, 12).astype(int):
        y, x = ys[k], xs[k]
        expected = cam.fx * rec.spec.cam.baseline_mm / frame.depth_mm[y, x]
        patch = left[y - 7:y + 8, x - 7:x + 8]
        costs = [np.square(right[y - 7:y + 8, x - d - 7:x - d + 8] - patch).sum() for d in range(0, 80)]
        errors.append(abs(int(np.argmin(costs)) - expected))
    assert np.median(errors) <= 1.0


def test_reblurring_only_around_the_moving_objects_equals_blurring_the_whole_image():
    from vfdata.sim.render import blur, finish

    rng = np.random.default_rng(1)
    static = rng.integers(0, 256, (3, 60, 80), dtype=np.uint8)
    blurred_static = blur(cv2.merge(list(static)), 0.7)
    zero = np.zeros((60, 80, 3), np.uint8)
    for box in ((10, 5, 30, 25), (0, 0, 12, 60), (70, 50, 80, 60)):
        planes = static.copy()
        x0, y0, x1, y1 = box
        planes[:, y0:y1, x0:x1] = rng.integers(0, 256, (3, y1 - y0, x1 - x0), dtype=np.uint8)
        whole = finish(planes, (zero, zero), 0.7)
        assert np.array_equal(finish(planes, (zero, zero), 0.7, blurred_static, box), whole)
        assert not np.array_equal(blurred_static, whole)


def test_a_mesh_out_of_view_gives_no_fragments(scene):
    rec, renderer, _ = scene
    behind = renderer.tube_mesh(rec.model.nodes).shifted(np.array([0.0, 0.0, -1000.0]))
    frag = rasterize(rec.spec.cam.camera, behind).interpolate()
    assert len(frag.flat) == 0 and frag.normal.shape == (3, 0) and frag.attrs.shape == (2, 0)
