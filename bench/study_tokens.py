"""Token design study for issue 19: which point tokens and which symmetry handling let force estimates
transfer from the 0 deg training orientation to the held-out test orientations (90, 180 deg).

A fast ridge-regression rung, no network: each frame's set of point tokens is pooled into a fixed-length
vector (see `token_study.pool`), optionally with lagged frames of the 16-frame clip, and a closed-form ridge maps it
to (Fx, Fy, Fz) N in the sensor (= object) frame. The ridge strength is chosen per component on the
validation split (0 deg, unseen recordings); test figures are pooled over the test split (90 and 180 deg)
and given per orientation. Nothing is fitted on test data.

Point sources, channels, pooling and symmetry handlings: `bench/token_study.py`.

Run (about 8 min on one core for all sections, plus ~2 min to read and cache the MCAPs the first time;
sections can be run alone):

    cd <repo> && OMP_NUM_THREADS=1 PYTHONPATH=$PWD python bench/study_tokens.py --data /work/main/data \\
        --presets glove colon --sections repro channels symmetry origin pool lags camera ladder estimated

Loaded point sets are cached under --cache (default /tmp/study_tokens_cache) to make re-runs fast.
"""


from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from token_study import Design, Rec, evaluate, load_preset

# ---- tables ----------------------------------------------------------------------------------------


def header(per: list[float]) -> str:
    cols = ["design (channels / pool / symmetry)", "D", "val R²", "test R²", "test RMSE", "Fx / Fy / Fz"]
    cols += [f"{a:g}° RMSE / R²" for a in per] + ["RMSE per test recording"]
    return "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols)


def row(label: str, res: dict) -> str:
    t = res["test"]
    cells = [label, str(res["dim"]), f"{res['val']['r2'].mean():.2f}", f"{t['r2'].mean():.2f}",
             f"{t['rmse'].mean():.2f}", " / ".join(f"{v:.2f}" for v in t["rmse"])]
    cells += [f"{m['rmse'].mean():.2f} / {m['r2'].mean():.2f}" for m in res["per"].values()]
    cells.append(" ".join(f"{v:.2f}" for v in res["rec"].values()))
    return "| " + " | ".join(cells) + " |"


def table(title: str, recs_by_preset: dict[str, list[Rec]], designs: list[tuple[str, Design]],
          z_shift_mm: float = 0.0) -> None:
    for preset, recs in recs_by_preset.items():
        per = sorted({r.orientation for r in recs if r.split == "test"})
        print(f"\n### {title}: {preset}\n")
        print(header(per))
        for label, d in designs:
            t0 = time.process_time()
            res = evaluate(recs, d, z_shift_mm)
            print(row(label or d.label(), res) + f" <!-- {time.process_time() - t0:.0f}s -->", flush=True)


PAPER = Design(("p", "v"), "ms", "none")
PAPER_M = replace(PAPER, sym="mirror")
DISP = Design(("d", "v"), "ms", "mirror")


def section_repro(data: dict) -> None:
    table("Repro of the issue's table (true points, true frame; pool mean+std)", data["visible"],
          [("paper p+v, visible", PAPER), ("paper p+v + mirror, visible", PAPER_M), ("d+v + mirror, visible", DISP)])
    table("Repro, whole surface", data["surface"], [("d+v + mirror, surface", DISP),
                                                     ("d+v+p0 m12 + mirror, surface", Design(("d", "v", "p0")))])


def section_channels(data: dict) -> None:
    chans = [("d",), ("d", "v"), ("d", "v", "p0"), ("d", "v", "z0n"), ("d", "v", "cyl0"), ("d", "v", "z0n", "cyl0"),
             ("dcyl", "vcyl", "z0n", "cyl0"), ("d", "v", "p"), ("dclip", "v", "p0"), ("p", "v")]
    designs = [("", Design(c, pool, "mirror")) for pool in ("ms", "m12") for c in chans]
    table("Per-point channels (true visible points, mirrored copies)", data["visible"], designs)


def section_symmetry(data: dict) -> None:
    designs = []
    for c in (("p", "v"), ("d", "v"), ("d", "v", "p0"), ("d", "v", "cyl0")):
        for s in ("none", "mirror", "canon", "absy", "rot4", "rot4m"):
            designs.append(("", Design(c, "m12", s)))
    table("Symmetry handling (true visible points, m12 pooling)", data["visible"], designs)


def section_origin(data: dict) -> None:
    designs = [("", PAPER_M), ("", Design(("d", "v", "p0"), "m12", "mirror")),
               ("", Design(("d", "v", "z0n", "cyl0"), "m12", "mirror")),
               ("", Design(("d", "v", "cyl0"), "m12", "mirror")),
               ("", Design(("d", "v"), "m12", "mirror")),
               ("", Design(("d", "v"), "bins", "mirror", zsource="z0")),
               ("", Design(("d", "v"), "bins", "mirror", zsource="z0n"))]
    for shift in (3.0, -3.0, 20.0, -20.0):
        table(f"Origin moved along Z by {shift:+g} mm on the test recordings (true visible points)",
              data["visible"], designs, z_shift_mm=shift)


def section_pool(data: dict) -> None:
    designs = []
    for c in (("d", "v"), ("d", "v", "z0n", "cyl0")):
        for pool_, extra in (("m1", {}), ("ms", {}), ("m12", {}), ("bins", dict(zbins=4, abins=4)),
                             ("bins", dict(zbins=6, abins=6)), ("bins", dict(zbins=3, abins=2))):
            designs.append(("", Design(c, pool_, "mirror", **extra)))
    table("Pooling (true visible points, mirrored copies)", data["visible"], designs)


def section_lags(data: dict) -> None:
    designs = []
    for c in (("d", "v"), ("d", "v", "z0n", "cyl0")):
        for lags in ((0,), (0, 5, 10, 15), (0, 3, 7, 11, 15)):
            designs.append(("", Design(c, "m12", "mirror", lags=lags)))
    table("Temporal context (true visible points, m12, mirrored copies)", data["visible"], designs)


def section_camera(data: dict) -> None:
    designs = []
    for c in (("p", "v"), ("d", "v"), ("d", "v", "p0")):
        for pool_ in ("ms", "m12"):
            designs.append(("", Design(c, pool_, "mirror")))
            designs.append(("", Design(c, pool_, "none", frame="camera")))
    table("Object vs camera frame (true visible points)", data["visible"], designs)


LADDER = [("paper p+v (ms, none)", PAPER), ("paper p+v (ms, mirror)", PAPER_M),
          ("d+v (ms, mirror)", DISP),
          ("d+v (m12, mirror)", Design(("d", "v"), "m12", "mirror")),
          ("d+v (m12, mirror, lags 0,5,10,15)", Design(("d", "v"), "m12", "mirror", lags=(0, 5, 10, 15))),
          ("d+v+cyl0 (m12, mirror)", Design(("d", "v", "cyl0"), "m12", "mirror")),
          ("d+v+p0 (m12, mirror)", Design(("d", "v", "p0"), "m12", "mirror")),
          ("d+v+p0 (m12, rot4m)", Design(("d", "v", "p0"), "m12", "rot4m")),
          ("paper p+v (ms) CAMERA", replace(PAPER, frame="camera")),
          ("d+v (ms) CAMERA", replace(DISP, sym="none", frame="camera")),
          ("d+v (m12) CAMERA", Design(("d", "v"), "m12", "none", frame="camera"))]


def section_ladder(data: dict) -> None:
    for source in ("surface", "visible", "gtmcap", "processed"):
        table(f"Ladder rung '{source}' (sensor force from the recording MCAP)", data[f"{source}-mcap"], LADDER)


def section_estimated(data: dict) -> None:
    lags = (0, 5, 10, 15)
    designs = [("", Design(("d",), "m12", "mirror")), ("", Design(("d",), "m12", "mirror", lags=lags)),
               ("", Design(("d", "v"), "m12", "none")), ("", Design(("d", "v"), "m12", "canon")),
               ("", Design(("d", "v"), "m12", "rot4m")), ("", Design(("d", "v", "z0n"), "m12", "mirror")),
               ("", Design(("d", "v", "cyl0"), "m12", "mirror", lags=lags)),
               ("", Design(("d", "v", "cyl0"), "m12", "rot4m")),
               ("", Design(("dcyl", "vcyl", "cyl0"), "m12", "mirror")),
               ("", Design(("d", "v", "p"), "m12", "mirror"))]
    table("More designs on the estimated tracks ('processed')", data["processed-mcap"], designs)


def section_rotations(data: dict) -> None:
    lags = (0, 5, 10, 15)
    designs = [("", Design(("d", "v"), "m12", sym)) for sym in ("mirror", "rot4m", "rot8m", "rot12m", "rot30m")]
    designs += [("", Design(("d", "v", "cyl0"), "m12", sym)) for sym in ("mirror", "rot4m", "rot8m", "rot12m")]
    designs += [("", Design(("d", "v", "cyl0"), "m12", "rot8m", lags=lags))]
    table("Rotations about the object's Z on the estimated tracks ('processed')", data["processed-mcap"], designs)


SECTIONS = {"repro": section_repro, "channels": section_channels, "symmetry": section_symmetry,
            "origin": section_origin, "pool": section_pool, "lags": section_lags, "camera": section_camera,
            "ladder": section_ladder, "estimated": section_estimated,
            "rotations": section_rotations}


class _Lazy(dict):
    """source name -> {preset: recordings}, loaded on first use ('<source>' uses force.npy for the
    true-point sources, '<source>-mcap' the recording MCAP's force)."""

    def __init__(self, data: Path, presets: list[str], cache: Path):
        super().__init__()
        self.args = (data, presets, cache)

    def __missing__(self, key: str) -> dict[str, list[Rec]]:
        data, presets, cache = self.args
        source, _, force = key.partition("-")
        value = {p: load_preset(data, p, source, force or "npy", cache) for p in presets}
        self[key] = value
        return value


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("data"))
    ap.add_argument("--presets", nargs="+", default=["glove", "colon"])
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=list(SECTIONS))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/study_tokens_cache"))
    args = ap.parse_args(argv)
    data = _Lazy(args.data, args.presets, args.cache)
    for name in args.sections:
        t0 = time.time()
        SECTIONS[name](data)
        print(f"\n<!-- section {name}: {time.time() - t0:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
