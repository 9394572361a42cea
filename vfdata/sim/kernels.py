"""Compiled per-pixel kernels of the renderer (numba): z-buffer rasterisation of quad meshes,
perspective-correct interpolation, bump mapping, shading and tone mapping.

Each kernel is one loop over the pixels (or triangles) that does in one pass what numpy needs a dozen
array passes for. They run single-threaded (a synthesis worker is one process per core) and in a fixed
order, so their output is the same from run to run. The machine code is cached in the user's own
cache folder (vfdata.sim.jit_cache; never beside this file), so only the first process ever compiles;
later processes load it in a fraction of a second. `error_model="numpy"`: a division by
zero gives inf / nan as in numpy instead of raising (and the loops need no check for it). `nogil`: a
kernel lets the synthesis' encoder thread run beside it.

Conventions: pixel (x, y) has its centre at image coordinates (x, y); vertex coordinates are in the
camera frame (x right, y down, z forward, mm).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from vfdata.sim.jit_cache import enable_cache

_JIT = {"cache": enable_cache(), "error_model": "numpy", "nogil": True}

# Sub-pixel precision of the rasteriser's edge tests: vertices snap to 1/256 pixel, and the tests are
# exact integer arithmetic, so triangles sharing an edge cover every pixel along it exactly once.
_SUBPIXEL = 256


# --- rasterisation ----------------------------------------------------------------------------------


@njit(**_JIT)
def _visible_quads(uv: np.ndarray, z: np.ndarray, verts: np.ndarray, normals: np.ndarray, quads: np.ndarray,
                   width: int, height: int, near: float, cull: bool) -> np.ndarray:
    """Indices of the quads worth drawing: every corner beyond the near plane, the corners' bounding
    box overlapping the image and, with `cull`, facing the camera ((sum of corners) . (sum of corner
    normals) < 0)."""
    keep = np.empty(len(quads), np.int64)
    count = 0
    for q in range(len(quads)):
        ok = True
        umin = vmin = np.inf
        umax = vmax = -np.inf
        for k in range(4):
            i = quads[q, k]
            if not z[i] > near:
                ok = False
                break
            umin = min(umin, uv[i, 0])
            umax = max(umax, uv[i, 0])
            vmin = min(vmin, uv[i, 1])
            vmax = max(vmax, uv[i, 1])
        if not ok or umax < -1 or umin > width or vmax < -1 or vmin > height:
            continue
        if cull:
            facing = 0.0
            for c in range(3):
                sp = 0.0
                sn = 0.0
                for k in range(4):
                    sp += verts[quads[q, k], c]
                    sn += normals[quads[q, k], c]
                facing += sp * sn
            if facing >= 0:
                continue
        keep[count] = q
        count += 1
    return keep[:count]


@njit(**_JIT)
def _triangle_planes(uv: np.ndarray, chans: np.ndarray, quads: np.ndarray, drawn: np.ndarray) -> np.ndarray:
    """Per triangle (2 k: corners 0, 1, 2 of quad drawn[k]; 2 k + 1: corners 0, 2, 3), the screen-plane
    coefficients (A, B, C) with A x + B y + C = f at its corners, for each channel f of `chans`
    (N, C): (T, C, 3) float32 (a triangle's coefficients together: the interpolation reads them
    together). Degenerate triangles get the constant f at corner 0."""
    n_chan = chans.shape[1]
    coef = np.empty((2 * len(drawn), n_chan, 3), np.float32)
    for k in range(len(drawn)):
        q = drawn[k]
        for half in range(2):
            t = 2 * k + half
            i0, i1, i2 = quads[q, 0], quads[q, 1 + half], quads[q, 2 + half]
            x0, y0 = uv[i0, 0], uv[i0, 1]
            dx1, dy1 = uv[i1, 0] - x0, uv[i1, 1] - y0
            dx2, dy2 = uv[i2, 0] - x0, uv[i2, 1] - y0
            det = dx1 * dy2 - dx2 * dy1
            inv = 1.0 / det if abs(det) > 1e-9 else 0.0
            for c in range(n_chan):
                f0 = chans[i0, c]
                df1 = chans[i1, c] - f0
                df2 = chans[i2, c] - f0
                a = (df1 * dy2 - df2 * dy1) * inv
                b = (dx1 * df2 - dx2 * df1) * inv
                cc = f0 - a * x0 - b * y0
                if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(cc)):
                    a = b = cc = 0.0
                coef[t, c, 0] = a
                coef[t, c, 1] = b
                coef[t, c, 2] = cc
    return coef


@njit(**_JIT)
def _fixed(x: float) -> int:
    """Pixel coordinate -> fixed point (nearest 1/_SUBPIXEL pixel)."""
    return int(math.floor(x * _SUBPIXEL + 0.5))


@njit(**_JIT)
def _edge_owned(dx: int, dy: int) -> bool:
    """Whether pixels exactly on an edge with direction (dx, dy) belong to the triangle: of the two
    triangles that share an edge (and run along it in opposite directions) exactly one owns it."""
    return dy > 0 or (dy == 0 and dx < 0)


@njit(**_JIT)
def _zbuffer(uv: np.ndarray, quads: np.ndarray, drawn: np.ndarray, coef: np.ndarray, width: int,
             height: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Nearest triangle per pixel (largest 1/z) of the drawn quads' triangles, in a buffer covering
    their bounding box clipped to the image: (triangle index or -1 (h, w) int32, 1/z (h, w) float64,
    x0, y0 of the box)."""
    x0 = width
    y0 = height
    x1 = y1 = 0
    for k in range(len(drawn)):
        for j in range(4):
            i = quads[drawn[k], j]
            x0 = min(x0, int(math.floor(max(uv[i, 0], -1.0))))
            x1 = max(x1, int(math.ceil(min(uv[i, 0], width + 1.0))))
            y0 = min(y0, int(math.floor(max(uv[i, 1], -1.0))))
            y1 = max(y1, int(math.ceil(min(uv[i, 1], height + 1.0))))
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1 + 1, width), min(y1 + 1, height)
    w, h = max(x1 - x0, 0), max(y1 - y0, 0)
    ids = np.full((h, w), -1, np.int32)
    inv_z = np.zeros((h, w), np.float64)
    s = _SUBPIXEL
    for k in range(len(drawn)):
        q = drawn[k]
        for half in range(2):
            t = 2 * k + half
            i0, i1, i2 = quads[q, 0], quads[q, 1 + half], quads[q, 2 + half]
            # Corners in fixed point, relative to the box.
            ax = _fixed(uv[i0, 0] - x0)
            ay = _fixed(uv[i0, 1] - y0)
            bx = _fixed(uv[i1, 0] - x0)
            by = _fixed(uv[i1, 1] - y0)
            cx = _fixed(uv[i2, 0] - x0)
            cy = _fixed(uv[i2, 1] - y0)
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if area == 0:
                continue
            if area < 0:  # wind it positively: the inside is where every edge function is >= 0
                bx, by, cx, cy = cx, cy, bx, by
            # Pixel range of the triangle's bounding box (pixel centres at multiples of s).
            px0 = max((min(ax, bx, cx) + s - 1) // s, 0)
            px1 = min(max(ax, bx, cx) // s, w - 1)
            py0 = max((min(ay, by, cy) + s - 1) // s, 0)
            py1 = min(max(ay, by, cy) // s, h - 1)
            if px1 < px0 or py1 < py0:
                continue
            # Edge functions e(x, y) = (ex1 - ex0) (y - ey0) - (ey1 - ey0) (x - ex0) per edge, with the
            # pixels exactly on an edge that the triangle does not own biased out.
            bias0 = 0 if _edge_owned(bx - ax, by - ay) else -1
            bias1 = 0 if _edge_owned(cx - bx, cy - by) else -1
            bias2 = 0 if _edge_owned(ax - cx, ay - cy) else -1
            a_z, b_z, c_z = coef[t, 0, 0], coef[t, 0, 1], coef[t, 0, 2]
            for py in range(py0, py1 + 1):
                yy = py * s
                e0 = (bx - ax) * (yy - ay) - (by - ay) * (px0 * s - ax) + bias0
                e1 = (cx - bx) * (yy - by) - (cy - by) * (px0 * s - bx) + bias1
                e2 = (ax - cx) * (yy - cy) - (ay - cy) * (px0 * s - cx) + bias2
                step0, step1, step2 = -(by - ay) * s, -(cy - by) * s, -(ay - cy) * s
                row_z = b_z * (py + y0) + c_z
                for px in range(px0, px1 + 1):
                    if e0 >= 0 and e1 >= 0 and e2 >= 0:
                        iz = a_z * (px + x0) + row_z
                        if iz > inv_z[py, px]:
                            inv_z[py, px] = iz
                            ids[py, px] = t
                    e0 += step0
                    e1 += step1
                    e2 += step2
    return ids, inv_z, x0, y0


@njit(**_JIT)
def _collect(ids: np.ndarray, inv_z: np.ndarray, x0: int, y0: int, width: int):
    """The covered pixels of a z-buffer in row-major order: flat image indices, depth (mm), x, y,
    triangle; and the box (x0, y0, x1, y1, exclusive) holding them. One pass, into arrays sized for a
    full buffer (allocating is free; a counting pass first would cost as much as this one)."""
    h, w = ids.shape
    flat = np.empty(h * w, np.int64)
    depth = np.empty(h * w, np.float32)
    fx = np.empty(h * w, np.float32)
    fy = np.empty(h * w, np.float32)
    tri = np.empty(h * w, np.int64)
    bx0, by0, bx1, by1 = w, h, -1, -1
    n = 0
    for y in range(h):
        row_start = n
        for x in range(w):
            t = ids[y, x]
            if t >= 0:
                flat[n] = (y + y0) * width + x + x0
                depth[n] = 1.0 / max(inv_z[y, x], 1e-9)
                fx[n] = x + x0
                fy[n] = y + y0
                tri[n] = t
                n += 1
        if n > row_start:
            by0 = min(by0, y)
            by1 = y
            bx0 = min(bx0, int(fx[row_start]) - x0)
            bx1 = max(bx1, int(fx[n - 1]) - x0)
    box = (bx0 + x0, by0 + y0, bx1 + x0 + 1, by1 + y0 + 1) if n else (0, 0, 0, 0)
    return flat[:n], depth[:n], fx[:n], fy[:n], tri[:n], box


@njit(**_JIT)
def select(keep: np.ndarray, flat: np.ndarray, depth: np.ndarray, px: np.ndarray, py: np.ndarray,
           tri: np.ndarray):
    """The fragments (flat, depth, x, y, triangle) where `keep` (P,) is true: a third of the time of
    five boolean selections in numpy."""
    count = 0
    for i in range(len(keep)):
        if keep[i]:
            count += 1
    out_flat = np.empty(count, flat.dtype)
    out_depth = np.empty(count, depth.dtype)
    out_px = np.empty(count, px.dtype)
    out_py = np.empty(count, py.dtype)
    out_tri = np.empty(count, tri.dtype)
    n = 0
    for i in range(len(keep)):
        if keep[i]:
            out_flat[n] = flat[i]
            out_depth[n] = depth[i]
            out_px[n] = px[i]
            out_py[n] = py[i]
            out_tri[n] = tri[i]
            n += 1
    return out_flat, out_depth, out_px, out_py, out_tri


@njit(**_JIT)
def rasterize_quads(verts: np.ndarray, normals: np.ndarray, attrs: np.ndarray, quads: np.ndarray, fx: float,
                    fy: float, cx: float, cy: float, width: int, height: int, near: float, cull: bool):
    """Rasterise a quad mesh (vertices (N, 3) mm in the camera frame, unit normals (N, 3), vertex
    attributes (N, A), quads (Q, 4)) with a z-buffer, each quad as the triangles (0, 1, 2) and
    (0, 2, 3). Returns the covered pixels in row-major order (flat index, depth mm, x, y, triangle
    2 k + half of quad drawn[k]), drawn, the triangles' plane coefficients of 1/z, normal / z and
    attrs / z (T, 1 + 3 + A, 3) float32, and the box holding the pixels."""
    n = len(verts)
    uv = np.empty((n, 2), np.float64)
    z = verts[:, 2].copy()
    n_attr = attrs.shape[1]
    chans = np.empty((n, 4 + n_attr), np.float64)
    for i in range(n):
        iz = 1.0 / z[i] if z[i] > near else 0.0
        uv[i, 0] = fx * verts[i, 0] * iz + cx
        uv[i, 1] = fy * verts[i, 1] * iz + cy
        chans[i, 0] = iz
        for c in range(3):
            chans[i, 1 + c] = normals[i, c] * iz
        for c in range(n_attr):
            chans[i, 4 + c] = attrs[i, c] * iz
    drawn = _visible_quads(uv, z, verts, normals, quads, width, height, near, cull)
    coef = _triangle_planes(uv, chans, quads, drawn)
    ids, inv_z, x0, y0 = _zbuffer(uv, quads, drawn, coef, width, height)
    flat, depth, px, py, tri, box = _collect(ids, inv_z, x0, y0, width)
    return flat, depth, px, py, tri, drawn, coef, box


@njit(**_JIT)
def interpolate(coef: np.ndarray, tri: np.ndarray, px: np.ndarray, py: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Perspective-correct values (C - 1, P) float32 of channels 1.. of the plane coefficients (T, C, 3)
    (channel / z) at the fragments: (A x + B y + C) * z."""
    count = coef.shape[1] - 1
    out = np.empty((count, len(tri)), np.float32)
    for i in range(len(tri)):
        t = tri[i]
        x, y, d = px[i], py[i], depth[i]
        for c in range(count):
            out[c, i] = (coef[t, c + 1, 0] * x + coef[t, c + 1, 1] * y + coef[t, c + 1, 2]) * d
    return out


@njit(**_JIT)
def face_values(face_attrs: np.ndarray, drawn: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(F, P) per-quad attributes (Q, F) of the quads covering each fragment."""
    out = np.empty((face_attrs.shape[1], len(tri)), face_attrs.dtype)
    for i in range(len(tri)):
        q = drawn[tri[i] >> 1]
        for f in range(face_attrs.shape[1]):
            out[f, i] = face_attrs[q, f]
    return out


@njit(**_JIT)
def positions(px: np.ndarray, py: np.ndarray, depth: np.ndarray, fx: float, fy: float, cx: float,
              cy: float) -> np.ndarray:
    """(3, P) float32 camera-frame points (mm) of pixels at depths (mm)."""
    out = np.empty((3, len(depth)), np.float32)
    for i in range(len(depth)):
        z = np.float64(depth[i])
        out[0, i] = (px[i] - cx) * z / fx
        out[1, i] = (py[i] - cy) * z / fy
        out[2, i] = z
    return out


@njit(**_JIT)
def unit_columns(v: np.ndarray) -> np.ndarray:
    """(3, P) float32 columns of v scaled to unit length."""
    out = np.empty((3, v.shape[1]), np.float32)
    for i in range(v.shape[1]):
        a, b, c = np.float64(v[0, i]), np.float64(v[1, i]), np.float64(v[2, i])
        s = 1.0 / max(math.sqrt(a * a + b * b + c * c), 1e-12)
        out[0, i], out[1, i], out[2, i] = a * s, b * s, c * s
    return out


# --- texturing and shading ---------------------------------------------------------------------------


@njit(**_JIT)
def bump_along(normal: np.ndarray, tangent_v: np.ndarray, grad_u: np.ndarray, grad_v: np.ndarray,
               strength: float) -> np.ndarray:
    """Unit normals (3, P) float32 perturbed by bump gradients (u across, v along the tangent): the
    tangent along v (3, P) is orthogonalised against the normal, the one along u is normal x it."""
    out = np.empty((3, normal.shape[1]), np.float32)
    for i in range(normal.shape[1]):
        nx, ny, nz = np.float64(normal[0, i]), np.float64(normal[1, i]), np.float64(normal[2, i])
        tx, ty, tz = np.float64(tangent_v[0, i]), np.float64(tangent_v[1, i]), np.float64(tangent_v[2, i])
        d = tx * nx + ty * ny + tz * nz
        tx, ty, tz = tx - d * nx, ty - d * ny, tz - d * nz
        s = 1.0 / math.sqrt(max(tx * tx + ty * ty + tz * tz, 1e-24))
        tx, ty, tz = tx * s, ty * s, tz * s
        ux, uy, uz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
        gu = -strength * grad_u[i]
        gv = -strength * grad_v[i]
        ox, oy, oz = nx + gu * ux + gv * tx, ny + gu * uy + gv * ty, nz + gu * uz + gv * tz
        s = 1.0 / math.sqrt(max(ox * ox + oy * oy + oz * oz, 1e-24))
        out[0, i], out[1, i], out[2, i] = ox * s, oy * s, oz * s
    return out


@njit(**_JIT)
def bump_framed(normal: np.ndarray, frame: np.ndarray, grad_u: np.ndarray, grad_v: np.ndarray,
                strength: float) -> np.ndarray:
    """Unit normals (3, P) float32 perturbed by bump gradients in a given tangent frame (6, P): unit
    tangents across (u, rows 0-2) and along (v, rows 3-5) the texture."""
    out = np.empty((3, normal.shape[1]), np.float32)
    for i in range(normal.shape[1]):
        gu = -strength * grad_u[i]
        gv = -strength * grad_v[i]
        ox = normal[0, i] + gu * frame[0, i] + gv * frame[3, i]
        oy = normal[1, i] + gu * frame[1, i] + gv * frame[4, i]
        oz = normal[2, i] + gu * frame[2, i] + gv * frame[5, i]
        s = 1.0 / math.sqrt(max(ox * ox + oy * oy + oz * oz, 1e-24))
        out[0, i], out[1, i], out[2, i] = ox * s, oy * s, oz * s
    return out


# Lobes below e^-60 are invisible (and tinier values would be denormal floats, which the CPU handles
# some hundred times slower).
LOBE_FLOOR = -60.0
# The glint lobe is the specular lobe to the 8th power: only lobes above e^(LOBE_FLOOR / 8) matter.
_GLINT_BASE = math.exp(LOBE_FLOOR / 8)


@njit(**_JIT)
def shade_terms(position: np.ndarray, normal: np.ndarray, gloss: np.ndarray, scale: np.ndarray,
                light: np.ndarray, intensity: float, wrap: float, ambient: float) -> np.ndarray:
    """The first half of vfdata.sim.render.shade: per fragment (3, P) float32, the diffuse factor (times
    the albedo), the specular weight (gloss times the light's falloff; 0 where the light is behind the
    surface) and the cosine to the half vector (clamped to [1e-6, 1]), whose power is the specular
    lobe. `gloss` and `scale` (float32) hold one value per fragment or a single value for all.
    Float32 throughout and no branches, so that the loop runs on SIMD lanes."""
    f32 = np.float32
    n = position.shape[1]
    out = np.empty((3, n), np.float32)
    g_step = 1 if len(gloss) > 1 else 0
    k_step = 1 if len(scale) > 1 else 0
    lx, ly, lz = f32(light[0]), f32(light[1]), f32(light[2])
    half = f32(math.sqrt(0.5))
    one = f32(1.0)
    zero = f32(0.0)
    power = f32(intensity)
    wrap32 = f32(wrap)
    diffuse_norm = f32(1.0 / (1.0 + wrap))
    ambient32 = f32(ambient)
    for i in range(n):
        px, py, pz = position[0, i], position[1, i], position[2, i]
        nx, ny, nz = normal[0, i], normal[1, i], normal[2, i]
        dx, dy, dz = lx - px, ly - py, lz - pz                     # to the light
        inv_dist = one / math.sqrt(dx * dx + dy * dy + dz * dz)
        inv_view = -one / math.sqrt(px * px + py * py + pz * pz)  # v = -p / |p|
        ndl = (nx * dx + ny * dy + nz * dz) * inv_dist
        ndv = (nx * px + ny * py + nz * pz) * inv_view
        ldv = (dx * px + dy * py + dz * pz) * inv_dist * inv_view
        # Cosine to the half vector: (n.l + n.v) / |l + v|, |l + v|^2 = 2 + 2 l.v.
        ndh = (ndl + ndv) * half / math.sqrt(max(ldv + one, f32(1e-6)))
        k = scale[i * k_step]
        falloff = inv_dist * inv_dist * power * k
        out[0, i] = max(ndl + wrap32, zero) * falloff * diffuse_norm + ambient32 * k
        out[1, i] = gloss[i * g_step] * falloff if ndl > zero else zero
        out[2, i] = min(max(ndh, f32(1e-6)), one)
    return out


@njit(**_JIT)
def shade_combine(albedo: np.ndarray, terms: np.ndarray, lobe: np.ndarray, gloss: np.ndarray,
                  glint: float) -> np.ndarray:
    """The second half of vfdata.sim.render.shade: radiance (3, P) float32 = albedo (3, P) x diffuse +
    weight x (lobe + glint x gloss x lobe^8), from shade_terms' (3, P) and the lobe (P,) (floored at
    e^LOBE_FLOOR)."""
    f32 = np.float32
    n = albedo.shape[1]
    out = np.empty((3, n), np.float32)
    g_step = 1 if len(gloss) > 1 else 0
    glint32 = f32(glint)
    base = f32(_GLINT_BASE)
    zero = f32(0.0)
    for i in range(n):
        l1 = lobe[i]
        l8 = max(l1, base)  # (no denormals in the powers of lobes that do not count)
        l8 *= l8
        l8 *= l8
        l8 *= l8
        sharp = l8 * gloss[i * g_step] * glint32 if l1 > base else zero
        spec = terms[1, i] * (l1 + sharp)
        d = terms[0, i]
        for c in range(3):
            out[c, i] = albedo[c, i] * d + spec
    return out


@njit(**_JIT)
def tone_map(linear: np.ndarray, lut: np.ndarray, scale: float) -> np.ndarray:
    """Display values (3, P) uint8 of linear radiance (3, P) by a table over [0, (len - 1) / scale].
    Clamped with selects, not branches (nan goes to 0), so that the loop runs on SIMD lanes."""
    out = np.empty(linear.shape, np.uint8)
    top = np.float32(len(lut) - 1)
    scale32 = np.float32(scale)
    zero = np.float32(0.0)
    for c in range(linear.shape[0]):
        for i in range(linear.shape[1]):
            x = linear[c, i] * scale32
            x = x if x > zero else zero
            x = x if x < top else top
            out[c, i] = lut[np.int32(x)]
    return out
