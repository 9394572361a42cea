"""Stereo endoscope rendering of quad meshes: z-buffer rasterisation, perspective-correct
interpolation, texturing and shading, each one compiled loop over the pixels (vfdata.sim.kernels);
blur and sensor noise with OpenCV. The textures themselves are made in vfdata.sim.texture.

Scene layers, composited per pixel by depth: a static layer (tissue bed and fixture, rendered once
per recording and view), the deforming tube, and the instrument. Lighting: a point light at the scope
tip (between the lenses) with inverse-square falloff, wrapped Lambert diffuse (soft, like tissue with
subsurface scattering), wet Blinn-Phong highlights broken up by a bump map and a gloss map, lens
vignetting, a slight optical blur and sensor noise.

Camera frames follow vfdata.calibration: x right, y down, z forward, mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.sim import kernels

_NEAR_MM = 2.0


# --- geometry helpers -----------------------------------------------------------------------------


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None,
            roll_rad: float = 0.0) -> np.ndarray:
    """Rotation (3, 3) whose columns are the camera x (right), y (down), z (forward) axes in the world
    frame, for a camera at `eye` looking at `target` with world `up` up in the image."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    if roll_rad:
        c, s = np.cos(roll_rad), np.sin(roll_rad)
        x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation matrix about a unit axis."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)


@dataclass
class Mesh:
    """Quads over vertices, with per-vertex unit normals, per-vertex attributes to interpolate
    (perspective-correct) and per-quad attributes (constant over a quad)."""

    verts: np.ndarray    # (N, 3) mm
    quads: np.ndarray    # (Q, 4) vertex indices, any winding
    normals: np.ndarray  # (N, 3)
    attrs: np.ndarray    # (N, A) e.g. texture coordinates; A may be 0
    face_attrs: np.ndarray | None = None  # (Q, F) e.g. material ids, tangents

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Mesh:
        return Mesh(self.verts @ rotation.T + translation, self.quads, self.normals @ rotation.T, self.attrs,
                    self.face_attrs)

    def shifted(self, offset: np.ndarray) -> Mesh:
        """The same mesh with every vertex moved by `offset` (mm), e.g. into the right camera."""
        return Mesh(self.verts + offset, self.quads, self.normals, self.attrs, self.face_attrs)

    @staticmethod
    def concat(meshes: list[Mesh]) -> Mesh:
        offsets = np.cumsum([0] + [len(m.verts) for m in meshes[:-1]])
        faces = None if any(m.face_attrs is None for m in meshes) else np.concatenate([m.face_attrs for m in meshes])
        return Mesh(
            np.concatenate([m.verts for m in meshes]),
            np.concatenate([m.quads + o for m, o in zip(meshes, offsets, strict=True)]),
            np.concatenate([m.normals for m in meshes]),
            np.concatenate([m.attrs for m in meshes]),
            faces,
        )


def grid_quads(rows: int, cols: int, wrap_cols: bool) -> np.ndarray:
    """Quads (Q, 4) of a rows x cols vertex grid (row-major), optionally closed across columns."""
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols if wrap_cols else cols - 1), indexing="ij")
    c1 = (c + 1) % cols
    q = np.stack([r * cols + c, (r + 1) * cols + c, (r + 1) * cols + c1, r * cols + c1], axis=-1)
    return q.reshape(-1, 4)


def axis_frame(p0: np.ndarray, p1: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Length of the segment p0 -> p1 and a right-handed orthonormal frame (a along it, u, v across)."""
    axis = p1 - p0
    length = float(np.sqrt(axis @ axis))
    a = axis / length
    ref = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = _cross(a, ref)
    u /= np.sqrt(u @ u)
    return length, a, u, _cross(a, u)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of 3-vectors (a tenth of np.cross's overhead, which dominates at this size)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def cylinder_mesh(p0: np.ndarray, p1: np.ndarray, radius: float, n_around: int, material: float,
                  cap0: bool = False, cap1: bool = True) -> Mesh:
    """A cylinder from p0 to p1 with optional flat caps; face_attrs = [material id]."""
    length, a, u, v = axis_frame(p0, p1)
    ang = 2 * np.pi * np.arange(n_around) / n_around
    ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v  # (n, 3) radial directions
    verts = np.concatenate([p0 + radius * ring, p1 + radius * ring])
    normals = np.concatenate([ring, ring])
    quads = [grid_quads(2, n_around, wrap_cols=True)]
    for cap, centre, sign in ((cap0, p0, -1.0), (cap1, p1, 1.0)):
        if not cap:
            continue
        base = len(verts)
        verts = np.concatenate([verts, centre + radius * ring, centre[None]])
        normals = np.concatenate([normals, np.tile(sign * a, (n_around + 1, 1))])
        k = np.arange(n_around)
        quads.append(np.stack([base + k, base + (k + 1) % n_around, np.full(n_around, base + n_around),
                               np.full(n_around, base + n_around)], axis=1))
    quads = np.concatenate(quads)
    return Mesh(verts, quads, normals, np.zeros((len(verts), 0)), np.full((len(quads), 1), material))


@lru_cache(maxsize=8)
def _capped_tube_template(n_around: int, pieces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit cylinder along local z from 0 to 1, cut into `pieces` that get longer away from z = 0,
    with a flat cap at z = 0: local vertex coordinates (cos, sin, t) (V, 3), quads, and which
    vertices belong to the cap (their normal is -axis)."""
    t = np.linspace(0.0, 1.0, pieces + 1) ** 2
    ang = 2 * np.pi * np.arange(n_around) / n_around
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    side = np.concatenate([np.repeat(ring, pieces + 1, axis=0).reshape(n_around, pieces + 1, 2).transpose(1, 0, 2),
                           np.repeat(t[:, None, None], n_around, axis=1)], axis=2).reshape(-1, 3)
    cap = np.concatenate([np.concatenate([ring, np.zeros((n_around, 1))], axis=1), [[0.0, 0.0, 0.0]]])
    k = np.arange(n_around)
    base = len(side)
    cap_quads = np.stack([base + k, base + (k + 1) % n_around, np.full(n_around, base + n_around),
                          np.full(n_around, base + n_around)], axis=1)
    quads = np.concatenate([grid_quads(pieces + 1, n_around, wrap_cols=True), cap_quads])
    is_cap = np.concatenate([np.zeros(len(side), bool), np.ones(len(cap), bool)])
    return np.concatenate([side, cap]), quads, is_cap


def capped_tube_mesh(p0: np.ndarray, p1: np.ndarray, radius: float, n_around: int, material: float,
                     pieces: int = 1) -> Mesh:
    """A cylinder from p0 to p1 capped at p0, its side cut into `pieces` that get longer toward p1;
    face_attrs = [material id]. Built from a cached template: cheap enough to rebuild every frame."""
    local, quads, is_cap = _capped_tube_template(n_around, pieces)
    length, a, u, v = axis_frame(p0, p1)
    radial = local[:, :1] * u + local[:, 1:2] * v
    verts = p0 + radius * radial + length * local[:, 2:3] * a
    normals = np.where(is_cap[:, None], -a, radial)
    return Mesh(verts, quads, normals, np.zeros((len(verts), 0)), np.full((len(quads), 1), material))


# Corners of the unit box (x, y, z in -1, 1) and its six faces as corner indices, counter-clockwise
# seen from outside.
_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
_BOX_FACES = np.array([(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)])


def box_mesh(centre: np.ndarray, axes: np.ndarray, half: np.ndarray, material: float,
             taper: float = 1.0) -> Mesh:
    """A box (flat-shaded faces) with local axes as columns of `axes` and half sizes `half`; `taper`
    scales the +axis0 end's cross-section (a jaw narrowing toward its tip)."""
    local = _BOX_CORNERS * half
    local[_BOX_CORNERS[:, 0] > 0, 1:] *= taper
    face_pts = (centre + local @ axes.T)[_BOX_FACES]  # (6, 4, 3)
    e1, e2 = (face_pts[:, 1] - face_pts[:, 0]).T, (face_pts[:, 3] - face_pts[:, 0]).T
    n = np.stack([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]], 1)
    n /= np.sqrt((n * n).sum(axis=1, keepdims=True))
    outward = ((face_pts.sum(axis=1) / 4 - centre) * n).sum(axis=1) >= 0
    n *= np.where(outward, 1.0, -1.0)[:, None]
    return Mesh(face_pts.reshape(24, 3), np.arange(24).reshape(6, 4), np.repeat(n, 4, axis=0),
                np.zeros((24, 0)), np.full((6, 1), material))


# --- rasterisation ---------------------------------------------------------------------------------


@dataclass
class Fragments:
    """Per-pixel samples of one layer: flat pixel indices (P,), depth (P,) mm, pixel coordinates, the
    covering triangle (triangles 2 k and 2 k + 1 are the halves of mesh quad drawn[k]), and, once
    `interpolate` ran, the mesh's normals then vertex attributes (3 + A, P) float32, perspective-correct."""

    flat: np.ndarray
    depth: np.ndarray
    px: np.ndarray
    py: np.ndarray
    tri: np.ndarray          # (P,) index of the covering triangle among the drawn ones
    drawn: np.ndarray        # (D,) mesh index of each drawn quad
    coef: np.ndarray         # (T, C, 3) screen-plane coefficients of 1/z and channel/z per triangle
    box: tuple[int, int, int, int] = (0, 0, 0, 0)  # x0, y0, x1, y1 (exclusive) holding every fragment
    values: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> Fragments:
        """The fragments where `keep` (P,) bool is true (the box is kept: it still holds them)."""
        picked = kernels.select(keep, self.flat, self.depth, self.px, self.py, self.tri)
        values = None if self.values is None else self.values[:, keep]
        return Fragments(*picked, self.drawn, self.coef, self.box, values)

    def interpolate(self) -> Fragments:
        self.values = kernels.interpolate(self.coef, self.tri, self.px, self.py, self.depth)
        return self

    def face(self, face_attrs: np.ndarray) -> np.ndarray:
        """(F, P) per-quad attributes (Q, F) of the covering quads."""
        return kernels.face_values(np.ascontiguousarray(face_attrs), self.drawn, self.tri)

    @property
    def normal(self) -> np.ndarray:
        """(3, P) unit normals."""
        return kernels.unit_columns(self.values[:3])

    @property
    def attrs(self) -> np.ndarray:
        return self.values[3:]

    def position(self, camera: PinholeCamera) -> np.ndarray:
        """(3, P) camera-frame positions (mm)."""
        return kernels.positions(self.px, self.py, self.depth, camera.fx, camera.fy, camera.cx, camera.cy)


def rasterize(camera: PinholeCamera, mesh: Mesh, cull_backfaces: bool = True) -> Fragments:
    """Rasterise the mesh (vertices in this camera's frame) into fragments of the nearest surface: a
    z-buffer over the quads' triangles (each quad split along its 0-2 diagonal; depths exact for the
    planar triangles), pixels covered where their centre is inside a triangle (exact fixed-point edge
    tests: no cracks or double cover between neighbours). Quads with a corner nearer than the near
    plane are dropped, and, with `cull_backfaces`, those facing away (by their vertex normals). Call
    `.interpolate()` on (a subset of) the result for normals and attributes."""
    f64 = np.float64
    flat, depth, px, py, tri, drawn, coef, box = kernels.rasterize_quads(
        np.ascontiguousarray(mesh.verts, f64), np.ascontiguousarray(mesh.normals, f64),
        np.ascontiguousarray(mesh.attrs, f64), np.ascontiguousarray(mesh.quads, np.int64),
        float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), int(camera.width),
        int(camera.height), _NEAR_MM, bool(cull_backfaces))
    return Fragments(flat, depth, px, py, tri, drawn, coef, box)


# --- shading ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Light:
    position: np.ndarray  # (3,) camera frame, mm
    intensity: float      # radiance scale: a white surface facing the light at distance d gets I/d^2


_TONE_BINS = 4096
_TONE_MAX = 4.0


def _tone_curve(x: np.ndarray) -> np.ndarray:
    y = x / (1.0 + 0.25 * x)
    return 255.0 * np.power(np.clip(y * 1.25, 0, 1), 1 / 2.2)


_TONE_LUT = np.round(_tone_curve(np.linspace(0, _TONE_MAX, _TONE_BINS))).astype(np.uint8)


def tone_map(linear: np.ndarray) -> np.ndarray:
    """Linear radiance (3, P) -> display values (3, P) uint8 (soft shoulder, then sRGB-like gamma), by
    table."""
    return kernels.tone_map(linear, _TONE_LUT, (_TONE_BINS - 1) / _TONE_MAX)


def _per_fragment(x: np.ndarray | float) -> np.ndarray:
    """A per-fragment (P,) or constant parameter as a float32 vector (of length 1 if constant)."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(x, np.float32)).ravel())


def shade(position: np.ndarray, normal: np.ndarray, albedo: np.ndarray, gloss: np.ndarray | float,
          shininess: np.ndarray | float, light: Light, scale: np.ndarray | float = 1.0,
          wrap: float = 0.35, ambient: float = 0.04, glint: float = 0.0) -> np.ndarray:
    """Linear RGB radiance (3, P) of surface points (3, P) with unit normals (3, P) and albedo (3, P)
    lit by a point light near the camera, times `scale` (e.g. the lens vignetting). Wrapped Lambert
    diffuse plus Blinn-Phong specular; `glint` adds a sharp second lobe (8 times the exponent) where
    the surface is wettest (the small saturated sparkles of a moist tissue film).

    Two compiled passes around the power of the half-vector cosine, which is taken with OpenCV's
    vectorised float32 log and exp (a compiled loop calling the maths library's would run several
    times slower); lobes are floored at e^-60 (invisible)."""
    gloss = _per_fragment(gloss)
    terms = kernels.shade_terms(position, normal, gloss, _per_fragment(scale),
                                np.asarray(light.position, np.float64), float(light.intensity), float(wrap),
                                float(ambient))
    log_lobe = _log(terms[2])
    log_lobe *= np.asarray(shininess, np.float32)
    np.maximum(log_lobe, np.float32(kernels.LOBE_FLOOR), out=log_lobe)
    return kernels.shade_combine(np.ascontiguousarray(albedo), terms, _exp(log_lobe), gloss, float(glint))


def _exp(x: np.ndarray) -> np.ndarray:
    # OpenCV returns None for an empty array.
    return cv2.exp(x).reshape(x.shape) if x.size else x.copy()


def _log(x: np.ndarray) -> np.ndarray:
    return cv2.log(x).reshape(x.shape) if x.size else x.copy()


def bumped_normals(normal: np.ndarray, tangent_s: np.ndarray, grad_u: np.ndarray, grad_v: np.ndarray,
                   strength: float) -> np.ndarray:
    """Unit normals (3, P) perturbed by a bump map's gradients (u around the tube, v along it).
    `normal`: (3, P), near unit length (interpolated unit normals: the result is normalised anyway);
    `tangent_s`: (3, P) unit directions along v, orthogonalised here against the normal."""
    return kernels.bump_along(normal, tangent_s, grad_u, grad_v, float(strength))


def bump_in_frame(normal: np.ndarray, frame: np.ndarray, grad_u: np.ndarray, grad_v: np.ndarray,
                  strength: float) -> np.ndarray:
    """Unit normals (3, P) perturbed by a bump map's gradients in a given tangent frame: `frame` (6, P)
    holds the unit tangents across (u) and along (v) the texture, e.g. one frame per quad. `normal`
    need not be exactly unit length (the result is normalised)."""
    return kernels.bump_framed(normal, frame, grad_u, grad_v, float(strength))


def vignette(camera: PinholeCamera, strength: float = 1.0) -> np.ndarray:
    """(H, W) cos^4-like lens falloff."""
    u = (np.arange(camera.width) - camera.cx) / camera.fx
    v = (np.arange(camera.height) - camera.cy) / camera.fy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    return (1.0 / (1.0 + strength * r2) ** 2).astype(np.float32)


class NoisePool:
    """Sensor noise: a few pre-drawn Gaussian noise fields, cropped at random offsets per frame (much
    cheaper than drawing a fresh field, and indistinguishable for our purposes). Each field is kept as
    its positive and negative parts so that adding it is two saturating uint8 operations."""

    def __init__(self, rng: np.random.Generator, height: int, width: int, sigma: float, count: int = 4):
        self.h, self.w = height, width
        pad = 64
        self.fields = []
        for _ in range(count):
            n = np.round(rng.standard_normal((height + pad, width + pad, 3), dtype=np.float32) * np.float32(sigma))
            self.fields.append((np.clip(n, 0, 255).astype(np.uint8), np.clip(-n, 0, 255).astype(np.uint8)))
        self.pad = pad

    def draw(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        pos, neg = self.fields[int(rng.integers(len(self.fields)))]
        y, x = rng.integers(0, self.pad, 2)
        return pos[y:y + self.h, x:x + self.w], neg[y:y + self.h, x:x + self.w]


_BLUR_RADIUS = 2


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Optical blur. A 5-tap kernel holds a Gaussian of sigma <= 0.8 px to within 2.5 sigma (and runs
    in half the time of the kernel OpenCV would size for it)."""
    if sigma <= 0:
        return img
    return cv2.GaussianBlur(img, (2 * _BLUR_RADIUS + 1,) * 2, sigma)


def finish(planes: np.ndarray, noise: tuple[np.ndarray, np.ndarray], blur_sigma: float,
           blurred_static: np.ndarray | None = None, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Display image (H, W, 3) uint8 from colour planes (3, H, W) uint8, with optical blur and sensor
    noise (saturating). The layers are composited as planes: scattering one byte per pixel into each
    plane is three times faster than scattering RGB triplets.

    With `blurred_static` (the blurred image of the static layer alone) and `box` (x0, y0, x1, y1
    holding every pixel that differs from it), only the box and its surroundings are blurred again:
    the result is the same as blurring the whole image."""
    h, w = planes.shape[1:]
    positive, negative = noise
    if blurred_static is None or box is None:
        img = cv2.add(blur(cv2.merge(list(planes)), blur_sigma), positive)
    else:
        img = cv2.add(blurred_static, positive)  # a new image, the static one unchanged
        r = _BLUR_RADIUS
        # Output pixels within r of the box change; blurring them needs r more pixels around.
        x0, y0 = max(box[0] - r, 0), max(box[1] - r, 0)
        x1, y1 = min(box[2] + r, w), min(box[3] + r, h)
        if x1 > x0 and y1 > y0:
            cx0, cy0, cx1, cy1 = max(x0 - r, 0), max(y0 - r, 0), min(x1 + r, w), min(y1 + r, h)
            crop = blur(cv2.merge(list(planes[:, cy0:cy1, cx0:cx1])), blur_sigma)
            img[y0:y1, x0:x1] = cv2.add(crop[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0], positive[y0:y1, x0:x1])
    return cv2.subtract(img, negative, dst=img)


def warm_up() -> None:
    """Compile the renderer's kernels (first use on this machine: about 10 s of CPU) or load them from
    numba's cache (a fraction of a second), by rendering a small box the ways the scene does. The
    synthesis calls it once before starting its worker processes, so that they all load, none compiles."""
    cam = PinholeCamera(80.0, 80.0, 31.5, 23.5, 64, 48)
    box = box_mesh(np.array([0.0, 0.0, 40.0]), np.eye(3), np.array([8.0, 6.0, 5.0]), 1.0)
    textured = Mesh(box.verts, box.quads, box.normals, box.verts[:, :2] * 4.0, np.ones((6, 6), np.float32))
    light = Light(np.array([2.0, 0.0, 0.0]), 1600.0)
    for mesh in (box, textured):
        frag = rasterize(cam, mesh, cull_backfaces=mesh is box)
        frag = frag.subset(frag.depth > 0).interpolate()
        material = frag.face(mesh.face_attrs)
        frag.face(mesh.face_attrs.astype(np.int64))  # (the fixture's material ids are integers)
        ones = np.ones(len(frag.flat), np.float32)
        normal = frag.normal
        if mesh is textured:
            normal = bump_in_frame(frag.values[:3], material, ones, ones, 1.0)
            normal = bumped_normals(normal, normal[::-1].copy(), ones, ones, 1.0)
        albedo = np.full((3, len(ones)), 0.5, np.float32)
        tone_map(shade(frag.position(cam), normal, albedo, ones, 30.0, light, ones, glint=3.0))
