"""The simulated operating scene: world, fixture and tissue placement, endoscope pose, instrument,
and the per-frame stereo rendering of it all.

Frames: world W (+Z up, mm here; the ECM pose is written in metres), object frame O (the fixture:
origin at the clamp centre, X up, Z along the tube toward its free end, Y = Z x X), left camera C
(x right, y down, z forward), right camera = C shifted by the baseline along x.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.sim.render import (
    Fragments,
    Light,
    Mesh,
    NoisePool,
    blur,
    box_mesh,
    bump_in_frame,
    bumped_normals,
    capped_tube_mesh,
    cylinder_mesh,
    finish,
    grid_quads,
    rasterize,
    rotation_about,
    shade,
    tone_map,
    vignette,
)
from vfdata.sim.texture import Palette, fractal_noise, make_texture
from vfdata.sim.tissue import SurfaceMap, Tube, outward_normals

# Instrument and fixture materials: (albedo linear RGB, gloss, shininess).
MATERIALS = {
    0: ((0.03, 0.03, 0.035), 0.35, 25.0),   # shaft: black composite
    1: ((0.42, 0.42, 0.44), 1.6, 70.0),     # wrist and jaws: stainless steel
    2: ((0.30, 0.31, 0.33), 0.9, 40.0),     # clamp: anodised aluminium
    3: ((0.05, 0.05, 0.06), 0.4, 20.0),     # sensor body and post
}
SHAFT, STEEL, CLAMP, SENSOR = 0, 1, 2, 3
_ALBEDO = np.array([MATERIALS[m][0] for m in range(len(MATERIALS))], np.float32).T  # (3, materials)
_GLOSS = np.array([MATERIALS[m][1] for m in range(len(MATERIALS))], np.float32)
_SHININESS = np.array([MATERIALS[m][2] for m in range(len(MATERIALS))], np.float32)


@dataclass
class CameraSetup:
    camera: PinholeCamera
    baseline_mm: float
    rotation_wc: np.ndarray      # (3, 3) columns: camera axes in the world frame
    position_w_mm: np.ndarray    # (3,)

    def object_to_camera(self, rotation_wo: np.ndarray, origin_w_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = self.rotation_wc.T @ rotation_wo
        t = self.rotation_wc.T @ (origin_w_mm - self.position_w_mm)
        return r, t


@dataclass
class SceneSpec:
    """Everything about a recording's scene that does not change over time."""

    tube: Tube
    orientation_deg: float
    rotation_wo: np.ndarray          # object axes in the world frame
    origin_w_mm: np.ndarray          # clamp centre in the world frame
    cam: CameraSetup
    rcm_o_mm: np.ndarray             # instrument remote centre of motion (object frame)
    grasp_point_o_mm: np.ndarray     # rest grasp point (object frame)
    tube_palette: Palette
    bed_palette: Palette
    bed_depth_mm: float              # bed surface below the clamp centre
    sensor_offset_mm: float
    exposure: float = 1.0
    noise_sigma: float = 2.2
    blur_sigma: float = 0.6
    bump_strength: float = 1.2
    dense_s: int = 48
    dense_theta: int = 40
    tex_size: tuple[int, int] = (512, 512)

    def object_to_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """(rotation, translation mm) taking object-frame points to the left camera frame."""
        return self.cam.object_to_camera(self.rotation_wo, self.origin_w_mm)


def object_rotation(orientation_deg: float) -> np.ndarray:
    """Object axes in the world: X up, Z horizontal at `orientation_deg` about the vertical."""
    phi = np.radians(orientation_deg)
    x = np.array([0.0, 0.0, 1.0])
    z = np.array([np.cos(phi), np.sin(phi), 0.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


@dataclass
class StereoFrame:
    left: np.ndarray         # (H, W, 3) uint8 BGR (OpenCV's order: written without conversion)
    right: np.ndarray
    depth_mm: np.ndarray     # (H, W) float32 left z-depth, 0 where nothing
    mask: np.ndarray         # (H, W) bool: tube visible in the left view


@dataclass
class _StaticView:
    color: np.ndarray        # (3, H*W) uint8 display values (planes)
    depth: np.ndarray        # (H*W,) float32 mm, inf where nothing
    vignette: np.ndarray     # (H*W,) float32
    blurred: np.ndarray      # (H, W, 3) uint8: the colour, optically blurred
    empty: np.ndarray        # flat indices of the pixels where the static layer has nothing (depth inf)


@dataclass
class SceneRenderer:
    """Renders the scene: static layer once per view, then tube and instrument per frame."""

    spec: SceneSpec
    rng: np.random.Generator
    views: list[_StaticView] = field(init=False)

    def __post_init__(self) -> None:
        spec = self.spec
        th, tw = spec.tex_size
        self.tube_texture = make_texture(self.rng, th, tw, spec.tube_palette)
        self.bed_texture = make_texture(self.rng, 1024, 1024, spec.bed_palette)
        self.r_co, self.t_co = spec.object_to_camera()
        cam = spec.cam.camera
        self.light = Light(np.array([spec.cam.baseline_mm / 2, 0.0, 0.0]),
                           spec.exposure * float(np.linalg.norm(self.t_co + self.r_co @ spec.grasp_point_o_mm)) ** 2)
        self.noise = NoisePool(self.rng, cam.height, cam.width, spec.noise_sigma)
        # The tube's dense render grid: S rows along the tube (+ an apex row), T + 1 columns (the seam
        # column repeated so texture coordinates do not wrap inside a quad).
        tube = spec.tube
        s = np.linspace(0.0, tube.arc_length_mm, spec.dense_s)
        theta = np.linspace(0.0, 2 * np.pi, spec.dense_theta + 1)
        self.surface: SurfaceMap = tube.surface_map(s, theta)
        self.tube_quads = grid_quads(spec.dense_s + 1, spec.dense_theta + 1, wrap_cols=False)
        self.tube_quads_t = np.ascontiguousarray(self.tube_quads.T)
        uu, vv = np.meshgrid(theta / (2 * np.pi) * tw, s / tube.arc_length_mm * (th - 1), indexing="xy")
        apex_uv = np.stack([theta / (2 * np.pi) * tw, np.full_like(theta, th - 1)], axis=1)
        self.tube_uv = np.concatenate([np.stack([uu.ravel(), vv.ravel()], 1), apex_uv])
        # One bed and one fixture for both views: the background is a single 3D surface, so stereo
        # matching on it recovers its true depth.
        self.bed = self._bed_mesh().transformed(self.r_co, self.t_co)
        self.fixture = self._fixture_mesh().transformed(self.r_co, self.t_co)
        self.views = [self._render_static(k) for k in range(2)]

    # --- static layer ------------------------------------------------------------------------------

    def _view_offset(self, view: int) -> np.ndarray:
        return np.array([self.spec.cam.baseline_mm * view, 0.0, 0.0])

    def _light(self, view: int) -> Light:
        return Light(self.light.position - self._view_offset(view), self.light.intensity)

    def _fixture_mesh(self) -> Mesh:
        spec = self.spec
        r0 = spec.tube.ring_r[0]
        z_sensor = -spec.sensor_offset_mm
        clamp = cylinder_mesh(np.array([0, 0, -8.0]), np.array([0, 0, 1.5]), r0 + 2.5, 32, CLAMP, True, True)
        sensor = cylinder_mesh(np.array([0, 0, z_sensor - 8.0]), np.array([0, 0, -8.0]), 14.0, 32, SENSOR,
                               True, True)
        post = cylinder_mesh(np.array([-spec.bed_depth_mm - 5, 0, z_sensor - 4.0]),
                             np.array([-10.0, 0, z_sensor - 4.0]), 5.0, 20, SENSOR, False, False)
        return Mesh.concat([clamp, sensor, post])

    def _bed_mesh(self) -> Mesh:
        """A bumpy bed of other tissue under the fixture (object frame)."""
        spec = self.spec
        n = 120
        half = 420.0
        g = np.linspace(-half, half, n)
        yy, zz = np.meshgrid(g, g + spec.tube.shape.length_mm / 2, indexing="ij")
        height = 9.0 * fractal_noise(self.rng, n, n, 3, 2) + 4.0 * fractal_noise(self.rng, n, n, 9, 1)
        xx = -spec.bed_depth_mm + height.astype(np.float64)
        verts = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
        gy = np.gradient(xx, g, axis=0)
        gz = np.gradient(xx, g, axis=1)
        normals = np.stack([np.ones_like(gy), -gy, -gz], axis=-1).reshape(-1, 3)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        scale = 1024 / 240.0  # texture pixels per mm; the texture wraps
        uv = np.stack([yy.ravel() * scale, zz.ravel() * scale], axis=1)
        return Mesh(verts, grid_quads(n, n, wrap_cols=False), normals, uv)

    def _render_static(self, view: int) -> _StaticView:
        spec = self.spec
        cam = spec.cam.camera
        shift = self._view_offset(view)
        bed = self.bed.transformed(np.eye(3), -shift)
        fixture = self.fixture.transformed(np.eye(3), -shift)
        light = self._light(view)
        hw = cam.height * cam.width
        depth = np.full(hw, np.inf, np.float32)
        color = np.zeros((3, hw), np.uint8)
        vig = vignette(cam).ravel()
        bed_frag = rasterize(cam, bed, cull_backfaces=False)
        fix_frag = rasterize(cam, fixture)
        depth[bed_frag.flat] = bed_frag.depth
        fix_frag = fix_frag.subset(fix_frag.depth < depth[fix_frag.flat]).interpolate()
        depth[fix_frag.flat] = fix_frag.depth
        bed_frag = bed_frag.subset(depth[bed_frag.flat] == bed_frag.depth).interpolate()
        albedo, gloss, bump = self.bed_texture.sample(bed_frag.attrs[0], bed_frag.attrs[1])
        tangent = np.tile(self.r_co[:, 2:3].astype(np.float32), (1, len(bed_frag.flat)))
        normal = bumped_normals(bed_frag.values[:3], tangent, bump[0], bump[1], 3.0 * spec.bump_strength)
        color[:, bed_frag.flat] = tone_map(shade(bed_frag.position(cam), normal, albedo, gloss,
                                                 spec.bed_palette.shininess, light, vig[bed_frag.flat], glint=3.0))
        color[:, fix_frag.flat] = self._shade_materials(fix_frag, fixture, cam, light, vig[fix_frag.flat])
        blurred = blur(cv2.merge(list(color.reshape(3, cam.height, cam.width)[::-1])), spec.blur_sigma)  # BGR
        return _StaticView(color, depth, vig, blurred, np.flatnonzero(np.isinf(depth)))

    @staticmethod
    def _shade_materials(frag: Fragments, mesh: Mesh, cam: PinholeCamera, light: Light,
                         vignetting: np.ndarray) -> np.ndarray:
        """(3, P) display values of instrument / fixture fragments by their quads' material ids."""
        mat = np.rint(frag.face(mesh.face_attrs)[0]).astype(np.intp)
        return tone_map(shade(frag.position(cam), frag.normal, _ALBEDO.take(mat, axis=1), _GLOSS.take(mat),
                              _SHININESS.take(mat), light, vignetting, wrap=0.0, ambient=0.03))

    # --- dynamic objects -----------------------------------------------------------------------------

    def tube_mesh(self, nodes_o: np.ndarray) -> Mesh:
        """Dense tube surface in the left camera frame from node positions (object frame)."""
        nodes_c = nodes_o @ self.r_co.T + self.t_co
        p, ps, pt = self.surface.evaluate(nodes_c)
        n = outward_normals(ps, pt)
        # Close the free end with an apex row: a short dome beyond the last ring.
        last, prev = p[-1].mean(0), p[-2].mean(0)
        axis = last - prev
        axis /= np.linalg.norm(axis)
        r_last = np.linalg.norm(p[-1] - last, axis=1).mean()
        apex = last + 0.55 * r_last * axis
        cols = p.shape[1]
        verts = np.concatenate([p.reshape(-1, 3), np.tile(apex, (cols, 1))])
        normals = np.concatenate([n.reshape(-1, 3), np.tile(axis, (cols, 1))])
        # The bump map's tangent frame (around, along the tube), one per quad: the quads are small, and
        # the bump only tilts the normal a little within it.
        along = np.concatenate([ps.reshape(-1, 3), ps[-1]])
        q = self.tube_quads_t
        t = along[q[0]] + along[q[1]] + along[q[2]] + along[q[3]]
        nq = normals[q[0]] + normals[q[1]] + normals[q[2]] + normals[q[3]]
        nq /= np.maximum(np.linalg.norm(nq, axis=1, keepdims=True), 1e-12)
        t -= np.einsum("qx,qx->q", t, nq)[:, None] * nq
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        frame = np.concatenate([np.cross(nq, t), t], axis=1).astype(np.float32)
        return Mesh(verts, self.tube_quads, normals, self.tube_uv, frame)

    def instrument_mesh(self, grasp_o: np.ndarray, twist_rad: float, jaw_rad: float) -> Mesh:
        """Grasper (jaws, wrist, shaft) in the left camera frame, for a grasp point (object frame),
        a twist about the tube axis and a jaw opening angle."""
        spec = self.spec
        rot = rotation_about(np.array([0.0, 0, 1]), twist_rad)
        a = np.array([0.0, 0, 1])            # along the tube
        n = rot @ np.array([0.0, 1, 0])      # jaw closing direction
        b = rot @ np.array([1.0, 0, 0])      # up, out of the tissue
        shaft_dir = spec.rcm_o_mm - grasp_o
        shaft_dir /= np.linalg.norm(shaft_dir)
        side = 1.0 if np.dot(shaft_dir, a) >= 0 else -1.0
        hinge = grasp_o + side * 6.0 * a + 2.4 * b
        parts = []
        for sign in (-1.0, 1.0):
            open_rot = rotation_about(b, sign * side * (jaw_rad / 2 + np.radians(2.0)))
            d = open_rot @ (-side * a)
            nn = open_rot @ n
            centre = hinge + 6.0 * d + sign * 1.25 * nn - 0.4 * b
            parts.append(box_mesh(centre, np.stack([d, nn, b], axis=1), np.array([6.2, 1.0, 1.9]), STEEL,
                                  taper=0.6))
        wrist_end = hinge + 9.0 * shaft_dir
        parts.append(capped_tube_mesh(hinge - 1.0 * shaft_dir, wrist_end, 3.2, 16, STEEL))
        # The shaft reaches past the endoscope's near plane, where whole quads are dropped: it is cut
        # into pieces (shortest at the wrist).
        parts.append(capped_tube_mesh(wrist_end, spec.rcm_o_mm + 40.0 * shaft_dir, 4.2, 20, SHAFT, pieces=10))
        mesh = Mesh.concat(parts)
        return mesh.transformed(self.r_co, self.t_co)

    # --- frame ---------------------------------------------------------------------------------------

    def render(self, nodes_o: np.ndarray, grasp_o: np.ndarray, twist_rad: float, jaw_rad: float) -> StereoFrame:
        spec = self.spec
        cam = spec.cam.camera
        tube = self.tube_mesh(nodes_o)
        tool = self.instrument_mesh(grasp_o, twist_rad, jaw_rad)
        images, depth_left, mask_left = [], None, None
        for view in range(2):
            shift = -self._view_offset(view)
            static = self.views[view]
            light = self._light(view)
            t_frag = rasterize(cam, tube.shifted(shift))
            i_frag = rasterize(cam, tool.shifted(shift))
            # Per-pixel depth test against the static layer, then the instrument; the tube is seen
            # where its depth is the final one.
            depth = static.depth.copy()
            depth[t_frag.flat] = np.minimum(t_frag.depth, depth.take(t_frag.flat))
            i_frag = i_frag.subset(i_frag.depth < depth.take(i_frag.flat)).interpolate()
            depth[i_frag.flat] = i_frag.depth
            t_frag = t_frag.subset(depth.take(t_frag.flat) == t_frag.depth).interpolate()

            color = static.color.copy()
            planes = list(color)
            albedo, gloss, bump = self.tube_texture.sample(t_frag.attrs[0], t_frag.attrs[1])
            normal = bump_in_frame(t_frag.values[:3], t_frag.face(tube.face_attrs), bump[0], bump[1],
                                   spec.bump_strength)
            rad = shade(t_frag.position(cam), normal, albedo, gloss, spec.tube_palette.shininess, light,
                        static.vignette.take(t_frag.flat), glint=3.0)
            for plane, values in zip(planes, tone_map(rad), strict=True):
                plane[t_frag.flat] = values
            tool_color = self._shade_materials(i_frag, tool, cam, light, static.vignette.take(i_frag.flat))
            for plane, values in zip(planes, tool_color, strict=True):
                plane[i_frag.flat] = values
            boxes = [f.box for f in (t_frag, i_frag) if len(f.flat)]
            box = (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes),
                   max(b[3] for b in boxes)) if boxes else (0, 0, 0, 0)
            img = finish(color.reshape(3, cam.height, cam.width)[::-1], self.noise.draw(self.rng), spec.blur_sigma,
                         static.blurred, box)
            images.append(img)
            if view == 0:
                # Nothing at all (depth 0) can only be where the static layer has nothing.
                seen = depth.take(static.empty)
                depth[static.empty] = np.where(np.isinf(seen), np.float32(0.0), seen)
                depth_left = depth.reshape(cam.height, cam.width)
                mask_left = np.zeros(cam.height * cam.width, bool)
                mask_left[t_frag.flat] = True
                mask_left = mask_left.reshape(cam.height, cam.width)
        return StereoFrame(images[0], images[1], depth_left, mask_left)
