"""The compiled renderer kernels against plain float64 references: the z-buffer rasteriser against a
brute-force per-pixel ray test, perspective-correct interpolation against the exact surface points,
no cracks between neighbouring quads, and the shading against the textbook Blinn-Phong formula."""

from __future__ import annotations

import numpy as np
import pytest

from vfdata.calibration import PinholeCamera
from vfdata.sim.render import Light, Mesh, bump_in_frame, bumped_normals, grid_quads, rasterize, shade

CAM = PinholeCamera(90.0, 90.0, 39.5, 29.5, 80, 60)


def _random_quads(rng: np.random.Generator, count: int) -> Mesh:
    """Overlapping, slightly non-planar quads at 30-60 mm, each facing the camera."""
    verts, normals = [], []
    for _ in range(count):
        centre = np.array([rng.uniform(-12, 12), rng.uniform(-9, 9), rng.uniform(30, 60)])
        angle = rng.uniform(0, 2 * np.pi)
        size = rng.uniform(4, 12)
        corners = [centre + size * np.array([np.cos(angle + k * np.pi / 2), np.sin(angle + k * np.pi / 2), 0.0])
                   + np.array([0, 0, rng.uniform(-3, 3)]) for k in range(4)]
        verts += corners
        normals += [np.array([0.0, 0.0, -1.0])] * 4
    verts = np.array(verts)
    return Mesh(verts, np.arange(len(verts)).reshape(-1, 4), np.array(normals), verts.copy())


def _reference(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel centre, brute force in float64: the depth (mm, inf where nothing) of the nearest of
    the quads' triangles (0, 1, 2) and (0, 2, 3), by intersecting the pixel's ray with each triangle,
    and a map of pixels within 1e-6 px of a triangle's edge (either answer is right there)."""
    ys, xs = np.mgrid[:CAM.height, :CAM.width]
    rays = np.stack([(xs - CAM.cx) / CAM.fx, (ys - CAM.cy) / CAM.fy, np.ones_like(xs, float)], -1).reshape(-1, 3)
    best = np.full(len(rays), np.inf)
    edge = np.zeros(len(rays), bool)
    uv = CAM.project(mesh.verts)
    pix = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    for quad in mesh.quads:
        for tri in ((quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])):
            a, b, c = (uv[i] for i in tri)
            det = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            if abs(det) < 1e-12:
                continue
            # Screen-space barycentric coordinates; the pixel is inside where all are >= 0.
            l1 = ((pix[:, 0] - a[0]) * (c[1] - a[1]) - (pix[:, 1] - a[1]) * (c[0] - a[0])) / det
            l2 = ((b[0] - a[0]) * (pix[:, 1] - a[1]) - (b[1] - a[1]) * (pix[:, 0] - a[0])) / det
            lam = np.stack([1 - l1 - l2, l1, l2])
            scale = np.abs(det) / np.array([np.hypot(*(c - b)), np.hypot(*(c - a)), np.hypot(*(b - a))])
            dist_px = lam * scale[:, None]  # distance to each edge in pixels
            inside = (dist_px >= 0).all(0)
            edge |= (np.abs(dist_px) < 1e-6).any(0) & (dist_px > -1e-6).all(0)
            # Ray-plane intersection: the depth of the triangle's plane along the pixel's ray.
            p0, p1, p2 = (mesh.verts[i] for i in tri)
            n = np.cross(p1 - p0, p2 - p0)
            t = (n @ p0) / (rays @ n)
            best = np.where(inside & (t < best), t, best)
    return best.reshape(CAM.height, CAM.width), edge.reshape(CAM.height, CAM.width)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_zbuffer_matches_a_brute_force_ray_test(seed):
    mesh = _random_quads(np.random.default_rng(seed), 12)
    frag = rasterize(CAM, mesh, cull_backfaces=False).interpolate()
    depth = np.full(CAM.height * CAM.width, np.inf)
    depth[frag.flat] = frag.depth
    depth = depth.reshape(CAM.height, CAM.width)
    ref, edge = _reference(mesh)
    assert np.isfinite(ref).sum() > 1000
    # Coverage agrees everywhere but exactly on edges.
    assert ((np.isfinite(depth) != np.isfinite(ref)) & ~edge).sum() == 0
    # The nearest surface's depth, except where two surfaces are within float32 rounding.
    both = np.isfinite(depth) & np.isfinite(ref) & ~edge
    err = np.abs(depth[both] - ref[both])
    assert np.mean(err < 1e-3) > 0.999
    assert err.max() < 1.0  # (a near-tie between overlapping quads picks either)
    # Perspective-correct interpolation: the attributes are the vertices' camera coordinates, so at
    # each fragment they are the 3D point seen there.
    point = frag.position(CAM)
    np.testing.assert_allclose(frag.attrs, point, atol=2e-3)
    assert frag.box[0] == frag.px.min() and frag.box[2] == frag.px.max() + 1
    assert frag.box[1] == frag.py.min() and frag.box[3] == frag.py.max() + 1


def test_neighbouring_quads_leave_no_cracks():
    """A bumpy grid of small quads seen from above: every pixel inside its outline is covered."""
    rows, cols = 25, 31
    y, x = np.mgrid[-12:12:rows * 1j, -15:15:cols * 1j]
    rng = np.random.default_rng(5)
    z = 40 + rng.uniform(-1.0, 1.0, x.shape)
    x = x + rng.uniform(-0.3, 0.3, x.shape)  # irregular, so that edges cross pixel centres at odd places
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    mesh = Mesh(verts, grid_quads(rows, cols, wrap_cols=False), np.tile([0.0, 0.0, -1.0], (len(verts), 1)),
                np.zeros((len(verts), 0)))
    frag = rasterize(CAM, mesh)
    covered = np.zeros(CAM.height * CAM.width, bool)
    covered[frag.flat] = True
    covered = covered.reshape(CAM.height, CAM.width)
    # The outline's interior, conservatively: inside the projected inner rows and columns.
    uv = CAM.project(verts).reshape(rows, cols, 2)
    x0, x1 = uv[:, 0, 0].max() + 1, uv[:, -1, 0].min() - 1
    y0, y1 = uv[0, :, 1].max() + 1, uv[-1, :, 1].min() - 1
    inner = covered[int(np.ceil(y0)):int(y1) + 1, int(np.ceil(x0)):int(x1) + 1]
    assert inner.size > 1000
    assert inner.all()
    assert len(np.unique(frag.flat)) == len(frag.flat)


def test_back_faces_and_the_near_plane_are_dropped():
    quad = np.array([[-5.0, -5, 30], [5, -5, 30], [5, 5, 30], [-5, 5, 30]])
    facing = Mesh(quad, np.arange(4)[None], np.tile([0.0, 0, -1], (4, 1)), np.zeros((4, 0)))
    away = Mesh(quad, np.arange(4)[None], np.tile([0.0, 0, 1], (4, 1)), np.zeros((4, 0)))
    near = Mesh(quad * [1, 1, 0.05], np.arange(4)[None], np.tile([0.0, 0, -1], (4, 1)), np.zeros((4, 0)))
    assert len(rasterize(CAM, facing).flat) > 100
    assert len(rasterize(CAM, away).flat) == 0
    assert len(rasterize(CAM, away, cull_backfaces=False).flat) == len(rasterize(CAM, facing).flat)
    assert len(rasterize(CAM, near).flat) == 0


def _blinn_phong(p, n, albedo, gloss, shininess, light, scale, wrap, ambient, glint):
    """Textbook float64 version of vfdata.sim.render.shade, with explicit light, view and half vectors."""
    to_light = light.position[:, None] - p
    dist = np.linalg.norm(to_light, axis=0)
    l_dir = to_light / dist
    v_dir = -p / np.linalg.norm(p, axis=0)
    h = l_dir + v_dir
    h /= np.linalg.norm(h, axis=0)
    ndl = (n * l_dir).sum(0)
    ndh = np.clip((n * h).sum(0), 1e-6, 1)
    falloff = light.intensity * scale / dist**2
    lobe = np.maximum(ndh**shininess, np.exp(-60.0))
    spec = gloss * (lobe + glint * gloss * lobe**8) * (ndl > 0) * falloff
    diffuse = np.maximum(ndl + wrap, 0) / (1 + wrap) * falloff + ambient * scale
    return albedo * diffuse + spec


def test_shading_matches_the_textbook_formula():
    rng = np.random.default_rng(0)
    count = 5000
    p = np.stack([rng.uniform(-30, 30, count), rng.uniform(-25, 25, count), rng.uniform(40, 120, count)])
    n = rng.normal(size=(3, count))
    n[2] = -np.abs(n[2]) - 0.3  # mostly toward the camera, some grazing or away from the light
    n /= np.linalg.norm(n, axis=0)
    albedo = rng.uniform(0.1, 0.9, (3, count))
    gloss = rng.uniform(0, 1.5, count)
    scale = rng.uniform(0.5, 1, count)
    light = Light(np.array([2.2, 0.0, 0.0]), 6000.0)
    for shininess, glint in ((40.0, 3.0), (rng.uniform(10, 80, count), 0.0)):
        got = shade(p.astype(np.float32), n.astype(np.float32), albedo.astype(np.float32),
                    gloss.astype(np.float32), shininess, light, scale.astype(np.float32), glint=glint)
        want = _blinn_phong(p, n, albedo, gloss, shininess, light, scale, 0.35, 0.04, glint)
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-5)


def test_bump_mapping_tilts_the_normal_within_its_frame():
    rng = np.random.default_rng(1)
    count = 1000
    n = rng.normal(size=(3, count))
    n /= np.linalg.norm(n, axis=0)
    along = rng.normal(size=(3, count))
    gu, gv = rng.normal(0, 0.2, count), rng.normal(0, 0.2, count)
    # Reference: the tangent along v made orthogonal to n, the one across is n x it.
    tv = along - (along * n).sum(0) * n
    tv /= np.linalg.norm(tv, axis=0)
    tu = np.cross(n.T, tv.T).T
    want = n - 1.5 * (gu * tu + gv * tv)
    want /= np.linalg.norm(want, axis=0)
    f32 = np.float32
    got = bumped_normals(n.astype(f32), along.astype(f32), gu.astype(f32), gv.astype(f32), 1.5)
    np.testing.assert_allclose(got, want, atol=1e-5)
    frame = np.concatenate([tu, tv]).astype(f32)
    got = bump_in_frame(n.astype(f32), frame, gu.astype(f32), gv.astype(f32), 1.5)
    np.testing.assert_allclose(got, want, atol=1e-5)
