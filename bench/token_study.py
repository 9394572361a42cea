"""The token study's data and its one evaluation (`bench/study_tokens.py` prints the tables): point
sets read from simulated recordings, per-point channels, pooling into a fixed-length vector per frame,
symmetry copies, and a closed-form ridge scored on validation and test.

Point sources (the rungs of the attribution ladder):
- `surface`: 256 simulator material points drawn from the whole surface, all valid (what no camera sees);
- `visible`: 256 material points drawn among those visible in frame 0, valid where visible (true frame);
- `gtmcap`: the `<id>.gt.mcap` tracks (true material points through our mask and estimated object frame);
- `processed`: the `<id>.processed.mcap` tracks (our depth, mask, object frame and geometry tracker).

Per-point channels (object frame unless `frame=camera`): `p` position, `v` velocity (mm/s, central
differences as `vfdata.clips.tokens.velocities`), `d` displacement p_t - p_0 from the recording's first frame,
`p0` reference position, `z0` its z only, `z0n` its z relative to the frame-0 cloud's z-range (0..1),
`cyl0` (r0, cos th0, sin th0) around the object's Z axis (th from X = up), `dcyl`/`vcyl` displacement /
velocity in the local cylindrical basis (radial, tangential, axial), `dclip` p_t - p_{t-15}.

Pooling over the valid points of a frame: `m1` (mean of each channel), `ms` (mean and std), `m12` (mean and
the mean of every pairwise product of channels: the first and second moments of the token set, what a set
model with a quadratic per-point map and mean pooling can read), `bins` (mean of the non-position channels
in bins of reference z x angle around the axis, plus each bin's share of points).

Symmetry: `none`; `mirror` (training copies mirrored across the object's XZ plane: y, vy, Fy negated);
`canon` (each recording mirrored to the flank its frame 0 shows, `vfdata.clips.tokens.seen_side`, at test too);
`absy` (position channels read |y|, |sin th|; no copies); `rot4` / `rot4m` (training copies rotated by
90/180/270 deg about Z, forces with them; `m`: and mirrored).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vfdata.clips.tokens import seen_side, segments, velocities
from vfdata.manifest import load_manifest
from vfdata.recording import Recording
from vfdata.recording.derived import read_tracks

NUM_POINTS = 256
CLIP = 16
STATIC_CHANNELS = ("p0", "z0", "z0n", "cyl0")  # reference channels: fixed per point, not pooled per bin


# ---- data -----------------------------------------------------------------------------------------


@dataclass
class Rec:
    id: str
    split: str
    orientation: float
    times_ns: np.ndarray  # (F,)
    force_n: np.ndarray  # (F, 3) sensor / object frame
    points: np.ndarray  # (F, N, 3) mm, the source's object frame
    valid: np.ndarray  # (F, N) bool
    rotation: np.ndarray  # the source's object frame in the left camera: cam = R p + o
    origin: np.ndarray


def _load_source(entry, source: str, force: str, seed: int = 0) -> Rec:
    gt = entry.raw / "ground_truth"
    times = np.loadtxt(entry.raw / "frames.csv", delimiter=",", skiprows=1, dtype=np.int64, ndmin=2)[:, 1]
    if source in ("surface", "visible"):
        pts_cam = np.load(gt / "points.npy")
        vis = np.load(gt / "visible.npy") if (gt / "visible.npy").is_file() else np.ones(pts_cam.shape[:2], bool)
        frame = json.loads((gt / "object_frame.json").read_text())
        rot, org = np.asarray(frame["rotation"], float), np.asarray(frame["origin_mm"], float)
        rng = np.random.default_rng([seed, int(entry.id.split("_")[-1])])
        pool = np.arange(pts_cam.shape[1]) if source == "surface" else np.flatnonzero(vis[0])
        keep = np.sort(rng.choice(pool, size=min(NUM_POINTS, len(pool)), replace=False))
        points = (pts_cam[:, keep].astype(np.float64) - org) @ rot
        valid = np.ones(points.shape[:2], bool) if source == "surface" else vis[:, keep].astype(bool)
    else:
        path = entry.processed if source == "processed" else entry.processed.with_name(f"{entry.id}.gt.mcap")
        tracks = read_tracks(path)
        times, points, valid = tracks.times_ns, tracks.points_object_mm, tracks.visible
        rot, org = tracks.frame.rotation, tracks.frame.origin
    if force == "npy" and source in ("surface", "visible"):
        f = np.load(gt / "force.npy")[:, :3].astype(np.float64)
    else:
        with Recording.open(entry.mcap) as rec:
            f = rec.force_at(times)[:, :3].astype(np.float64)
    return Rec(entry.id, entry.split, entry.orientation_deg, times, f, points.astype(np.float32),
               np.asarray(valid, bool), rot, org)


def load_preset(data: Path, preset: str, source: str, force: str, cache: Path) -> list[Rec]:
    """All recordings of a preset's manifest for one point source, cached as one npz per recording."""
    entries = load_manifest(data / preset / f"{preset}.manifest.yaml").entries
    recs = []
    for e in entries:
        fn = cache / f"{e.id}-{source}-{force}.npz"
        if fn.is_file():
            z = np.load(fn)
            recs.append(Rec(e.id, e.split, e.orientation_deg, z["t"], z["f"], z["p"], z["v"], z["R"], z["o"]))
            continue
        r = _load_source(e, source, force)
        cache.mkdir(parents=True, exist_ok=True)
        np.savez(fn, t=r.times_ns, f=r.force_n, p=r.points, v=r.valid, R=r.rotation, o=r.origin)
        recs.append(r)
    return recs


# ---- tokens and pooling ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Design:
    channels: tuple[str, ...] = ("d", "v")
    pool: str = "m12"
    sym: str = "mirror"
    lags: tuple[int, ...] = (0,)
    frame: str = "object"
    zbins: int = 4
    abins: int = 4
    zsource: str = "z0n"  # bins along absolute z0 ("z0") or relative z ("z0n")

    def label(self) -> str:
        extra = f" {self.zbins}x{self.abins}/{self.zsource}" if self.pool == "bins" else ""
        lags = "" if self.lags == (0,) else f" lags{','.join(map(str, self.lags))}"
        cam = " CAMERA" if self.frame == "camera" else ""
        return f"{'+'.join(self.channels)} | {self.pool}{extra} | {self.sym}{lags}{cam}"


def _rotz(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _cyl_basis(p0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    th = np.arctan2(p0[..., 1], p0[..., 0])
    er = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
    et = np.stack([-np.sin(th), np.cos(th), np.zeros_like(th)], -1)
    return er, et


def point_channels(points: np.ndarray, valid: np.ndarray, times_ns: np.ndarray, design: Design
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(tokens (F, N, C), ok (F, N), z-coordinate for bins (N,), angle th0 (N,)) of one recording whose
    points are already in the frame the design reads (mirrored / rotated / shifted as wanted)."""
    runs = segments(times_ns)
    fps = 1e9 / float(np.median(np.diff(times_ns)))
    ok = valid & np.isfinite(points).all(-1)
    p = np.where(ok[..., None], points, 0.0).astype(np.float64)
    ok_ref = ok[0]
    p0 = p[0]
    need_v = any(c in ("v", "vcyl") for c in design.channels)
    okv = ok.copy()
    if need_v:
        v = velocities(p, runs, fps)
        prev, nxt = ok.copy(), ok.copy()
        for a, b in runs:
            prev[a + 1:b] = ok[a:b - 1]
            nxt[a:b - 1] = ok[a + 1:b]
        okv = ok & prev & nxt
    seen0 = ok_ref & np.isfinite(p0).all(-1)
    zlo, zhi = (np.percentile(p0[seen0, 2], [2, 98]) if seen0.sum() > 2 else (0.0, 1.0))
    z0n = (p0[:, 2] - zlo) / max(zhi - zlo, 1e-6)
    th0 = np.arctan2(p0[:, 1], p0[:, 0])
    absy = design.sym == "absy"
    F, N = p.shape[:2]
    parts = []
    for c in design.channels:
        if c == "p":
            q = p.copy()
            if absy:
                q[..., 1] = np.abs(q[..., 1])
            parts.append(q)
        elif c == "v":
            parts.append(v)
        elif c == "d":
            parts.append(p - p0)
        elif c == "p0":
            q = np.broadcast_to(p0, (F, N, 3)).copy()
            if absy:
                q[..., 1] = np.abs(q[..., 1])
            parts.append(q)
        elif c == "z0":
            parts.append(np.broadcast_to(p0[:, 2:3], (F, N, 1)))
        elif c == "z0n":
            parts.append(np.broadcast_to(z0n[:, None], (F, N, 1)))
        elif c == "cyl0":
            r0 = np.hypot(p0[:, 0], p0[:, 1])
            s = np.abs(np.sin(th0)) if absy else np.sin(th0)
            parts.append(np.broadcast_to(np.stack([r0, np.cos(th0), s], -1), (F, N, 3)))
        elif c in ("dcyl", "vcyl"):
            er, et = _cyl_basis(p0)
            w = (p - p0) if c == "dcyl" else v
            parts.append(np.stack([(w * er).sum(-1), (w * et).sum(-1), w[..., 2]], -1))
        elif c == "dclip":
            lagged = np.empty_like(p)
            for a, b in runs:
                idx = np.maximum(np.arange(a, b) - (CLIP - 1), a)
                lagged[a:b] = p[idx]
            parts.append(p - lagged)
        else:
            raise ValueError(f"unknown channel {c!r}")
    tokens = np.concatenate(parts, -1)
    m = okv & ok_ref[None] if need_v else ok & ok_ref[None]
    zb = p0[:, 2] if design.zsource == "z0" else z0n
    return tokens, m, zb, th0


def pool(tokens: np.ndarray, ok: np.ndarray, zb: np.ndarray, th0: np.ndarray, design: Design,
         dynamic: np.ndarray, zedges: np.ndarray) -> np.ndarray:
    """(F, D) pooled features of the valid tokens of each frame."""
    w = ok.astype(np.float64)
    cnt = np.maximum(w.sum(1, keepdims=True), 1.0)
    mean = np.einsum("fn,fnc->fc", w, tokens) / cnt
    if design.pool == "m1":
        return np.concatenate([mean, w.mean(1, keepdims=True)], 1)
    if design.pool == "ms":
        sq = np.einsum("fn,fnc->fc", w, tokens ** 2) / cnt
        return np.concatenate([mean, np.sqrt(np.maximum(sq - mean ** 2, 0)), w.mean(1, keepdims=True)], 1)
    if design.pool == "m12":
        iu = np.triu_indices(tokens.shape[-1])
        outer = np.einsum("fn,fnc,fnd->fcd", w, tokens, tokens) / cnt[..., None]
        return np.concatenate([mean, outer[:, iu[0], iu[1]], w.mean(1, keepdims=True)], 1)
    if design.pool == "bins":
        zi = np.clip(np.searchsorted(zedges, zb) - 1, 0, design.zbins - 1)
        ai = np.clip(((th0 + np.pi) / (2 * np.pi) * design.abins).astype(int), 0, design.abins - 1)
        b = zi * design.abins + ai
        dyn = tokens[..., dynamic]
        out = []
        for k in range(design.zbins * design.abins):
            wk = w * (b == k)[None]
            ck = wk.sum(1, keepdims=True)
            out.append(np.einsum("fn,fnc->fc", wk, dyn) / np.maximum(ck, 1.0))
            out.append(ck / tokens.shape[1])
        return np.concatenate(out + [mean], 1)
    raise ValueError(f"unknown pool {design.pool!r}")


def _dynamic_index(design: Design) -> np.ndarray:
    widths = {"z0": 1, "z0n": 1}
    idx, at = [], 0
    for c in design.channels:
        n = widths.get(c, 3)
        if c not in STATIC_CHANNELS:
            idx.extend(range(at, at + n))
        at += n
    return np.asarray(idx, int)


def with_lags(x: np.ndarray, times_ns: np.ndarray, lags: tuple[int, ...]) -> np.ndarray:
    if lags == (0,):
        return x
    out = []
    for a, b in segments(times_ns):
        cols = [x[np.maximum(np.arange(a, b) - lag, a)] for lag in lags]
        out.append(np.concatenate(cols, 1))
    return np.concatenate(out, 0)


@dataclass
class View:
    """One recording as the design sees it: a mirror/rotation about Z and an origin shift along Z."""

    mirror: bool = False
    rot_deg: float = 0.0
    z_shift_mm: float = 0.0


def features(rec: Rec, design: Design, view: View, zedges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(X (F, D), y (F, 3)) of one recording under one view."""
    pts = rec.points.astype(np.float64)
    f = rec.force_n.copy()
    if design.frame == "camera":
        pts = pts @ rec.rotation.T + rec.origin
    else:
        pts = pts.copy()
        pts[..., 2] -= view.z_shift_mm  # the origin moved by +shift along Z
        m = _rotz(view.rot_deg) @ np.diag([1.0, -1.0 if view.mirror else 1.0, 1.0])
        pts = pts @ m.T
        f = f @ m.T
    tokens, ok, zb, th0 = point_channels(pts, rec.valid, rec.times_ns, design)
    x = pool(tokens, ok, zb, th0, design, _dynamic_index(design), zedges)
    return with_lags(x, rec.times_ns, design.lags), f


def _side(rec: Rec) -> float:
    return seen_side(rec.points[0], rec.valid[0])


def train_views(rec: Rec, design: Design) -> list[View]:
    if design.frame == "camera":
        return [View()]
    s = {"none": [View()], "absy": [View()], "mirror": [View(), View(mirror=True)],
         "canon": [View(mirror=_side(rec) < 0)],
         "rot4": [View(rot_deg=a) for a in (0, 90, 180, 270)],
         "rot4m": [View(mirror=m, rot_deg=a) for a in (0, 90, 180, 270) for m in (False, True)],
         "rot8m": [View(mirror=m, rot_deg=a) for a in range(0, 360, 45) for m in (False, True)],
         "rot12m": [View(mirror=m, rot_deg=a) for a in range(0, 360, 30) for m in (False, True)],
         # only small turns about the axis (the camera's view of the tube varies a little between recordings)
         "rot30m": [View(mirror=m, rot_deg=a) for a in (-30, -15, 0, 15, 30) for m in (False, True)]}
    return s[design.sym]


def test_view(rec: Rec, design: Design, z_shift_mm: float = 0.0) -> View:
    mirror = design.sym == "canon" and design.frame == "object" and _side(rec) < 0
    return View(mirror=mirror, z_shift_mm=z_shift_mm)


# ---- ridge and metrics -----------------------------------------------------------------------------

LAMBDAS = np.logspace(-5, 2, 8)


def metrics(pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """RMSE (3,) and R^2 (3,) pooled over frames, as vfmodels.evaluation.metrics.force_metrics."""
    ok = np.isfinite(true).all(1)
    pred, true = pred[ok], true[ok]
    se = ((pred - true) ** 2).sum(0)
    ss = ((true - true.mean(0)) ** 2).sum(0)
    return {"rmse": np.sqrt(se / len(true)), "r2": 1 - se / ss}


class Ridge:
    """Closed-form ridge on standardised features and targets; lambda (relative to n) per output chosen
    on validation R^2."""

    def fit(self, x: np.ndarray, y: np.ndarray, xv: np.ndarray, yv: np.ndarray) -> Ridge:
        ok = np.isfinite(y).all(1)
        x, y = x[ok], y[ok]
        self.mx, self.sx = x.mean(0), x.std(0) + 1e-9
        self.my, self.sy = y.mean(0), y.std(0) + 1e-9
        z = (x - self.mx) / self.sx
        t = (y - self.my) / self.sy
        evals, evecs = np.linalg.eigh(z.T @ z)
        zt = evecs.T @ (z.T @ t)
        n = len(z)
        ws = [evecs @ (zt / (evals + lam * n)[:, None]) for lam in LAMBDAS]
        zv = (xv - self.mx) / self.sx
        scores = np.array([metrics(zv @ w * self.sy + self.my, yv)["r2"] for w in ws])  # (L, 3)
        best = scores.argmax(0)
        self.w = np.stack([ws[best[k]][:, k] for k in range(3)], 1)
        self.lam = LAMBDAS[best]
        return self

    def predict(self, x: np.ndarray) -> np.ndarray:
        return ((x - self.mx) / self.sx) @ self.w * self.sy + self.my


# ---- one evaluation --------------------------------------------------------------------------------


def _zedges(train: list[Rec], design: Design) -> np.ndarray:
    if design.zsource == "z0n":
        return np.linspace(0.0, 1.0, design.zbins + 1)
    z = np.concatenate([r.points[0][r.valid[0], 2] for r in train])
    return np.quantile(z, np.linspace(0, 1, design.zbins + 1))


def evaluate(recs: list[Rec], design: Design, z_shift_mm: float = 0.0) -> dict:
    train = [r for r in recs if r.split == "train"]
    zedges = _zedges(train, design)
    xs, ys = [], []
    for r in train:
        for v in train_views(r, design):
            x, y = features(r, design, v, zedges)
            xs.append(x)
            ys.append(y)
    out: dict = {}
    held = {}
    for split in ("val", "test"):
        xl, yl, ol, sl, il = [], [], [], [], []
        for r in recs:
            if r.split != split:
                continue
            view = test_view(r, design, z_shift_mm if split == "test" else 0.0)
            x, y = features(r, design, view, zedges)
            xl.append(x)
            yl.append(r.force_n)
            ol.append(np.full(len(x), r.orientation))
            sl.append(np.full(len(x), -1.0 if view.mirror else 1.0))
            il.append(np.full(len(x), r.id))
        held[split] = (np.concatenate(xl), np.concatenate(yl), np.concatenate(ol), np.concatenate(sl),
                       np.concatenate(il))
    xv, _, _, sv, _ = held["val"]
    yv_view = held["val"][1] * np.stack([np.ones_like(sv), sv, np.ones_like(sv)], 1)
    model = Ridge().fit(np.concatenate(xs), np.concatenate(ys), xv, yv_view)
    for split, (x, y, o, s, ids) in held.items():
        pred = model.predict(x) * np.stack([np.ones_like(s), s, np.ones_like(s)], 1)  # back to sensor Fy
        out[split] = metrics(pred, y)
        if split == "test":
            out["per"] = {float(a): metrics(pred[o == a], y[o == a]) for a in np.unique(o)}
            out["rec"] = {i: metrics(pred[ids == i], y[ids == i])["rmse"].mean() for i in np.unique(ids)}
    out["dim"] = xs[0].shape[1]
    return out
