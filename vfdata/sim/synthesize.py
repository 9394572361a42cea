"""`vfdata synth`: a preset's recordings, made in worker processes, and the dataset manifest.

Determinism: each recording depends only on (seed, its index) (vfdata.sim.simulation) and is written
deterministically (vfdata.sim.raw_writer); workers run single-threaded BLAS, so the output does not
depend on the number of workers.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import yaml
from tqdm import tqdm

from vfdata.atomic import atomic_output
from vfdata.errors import InputError, OutputExistsError
from vfdata.sim.presets import Preset, counted_splits, get_preset
from vfdata.sim.raw_writer import (
    IMAGE_FORMATS,
    N_MATERIAL_POINTS,
    check_image_format,
    generator_key,
    ground_truth_images,
    number,
    point_visibility,
    write_recording,
)
from vfdata.sim.render import warm_up
from vfdata.sim.simulation import Recording, build_recording, grasped_nodes, sensor_samples, simulate
from vfdata.threads import set_threads

# Names other modules and benchmarks import from here since before the split.
__all__ = [
    "IMAGE_FORMATS",
    "N_MATERIAL_POINTS",
    "Recording",
    "build_recording",
    "generator_key",
    "grasped_nodes",
    "ground_truth_images",
    "manifest",
    "point_visibility",
    "sensor_samples",
    "simulate",
    "synthesize",
    "write_recording",
]


def manifest(preset: Preset, root: str) -> dict:
    """The dataset manifest (docs/architecture.md) of a preset, with recordings under `root`."""
    return {
        "name": preset.name,
        "root": root,
        "recordings": [{"id": r.id, "orientation_deg": number(r.orientation_deg), "split": r.split}
                       for r in preset.recordings],
    }


def _is_complete(folder: Path, key: dict) -> bool:
    params = folder / "ground_truth" / "params.json"
    if not params.is_file():
        return False
    try:
        stored = json.loads(params.read_text())
    except (OSError, ValueError):
        return False
    return all(stored.get(k) == v for k, v in key.items())


_COUNTER = None


def _init_worker(counter) -> None:
    global _COUNTER
    _COUNTER = counter
    set_threads(1)


def _make_one(args: tuple[str, int, int, str, int | None, str, tuple[float, ...] | None, dict | None]) -> str:
    """Worker: make one recording (the parent already checked what may be replaced)."""
    preset_name, seed, index, out_dir, frames, image_format, test_orientations, split_recordings = args
    preset = get_preset(preset_name, test_orientations, split_recordings)
    plan = next(r for r in preset.recordings if r.index == index)
    rec = build_recording(plan, seed, frames, preset.width, preset.height)
    target = Path(out_dir) / plan.id
    key = generator_key(preset_name, seed, plan, rec.frames, image_format)
    if _is_complete(target, key):
        if _COUNTER is not None:
            with _COUNTER.get_lock():
                _COUNTER.value += rec.frames
        return "kept"
    with atomic_output(target, overwrite=True) as tmp:
        tmp.mkdir()
        write_recording(rec, tmp, preset_name, seed, _COUNTER, image_format, test_orientations, split_recordings)
    return "made"


def synthesize(preset: str, out_dir: str | Path, seed: int = 0, workers: int = 1, progress: bool = True,
               frames: int | None = None, overwrite: bool = False, image_format: str = "jpeg",
               test_orientations: Sequence[float] | None = None,
               split_recordings: Mapping[str, int] | None = None) -> Path:
    """Write the preset's recordings under out_dir (one raw folder each, with ground_truth/) and
    `<preset>.manifest.yaml`; returns the manifest path. The stereo views are JPEG (quality 95) or,
    with image_format='png', lossless PNG. `test_orientations` (degrees about the vertical) replace
    the preset's test orientations, spread over its test recordings (presets.with_test_orientations);
    `split_recordings` ({"train": 10, "val": 3}) sets how many training and validation recordings
    (tissues) it has (presets.with_split_recordings).
    Recordings already made with the same generator settings are kept; other existing ones are
    refused unless `overwrite`."""
    if test_orientations is not None:
        test_orientations = tuple(float(a) for a in test_orientations)
    split_recordings = dict(counted_splits(split_recordings)) or None
    p = get_preset(preset, test_orientations, split_recordings)
    check_image_format(image_format)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    if frames is not None and frames < 1:
        raise InputError(out, "--frames must be at least 1")
    if not overwrite:
        for plan in p.recordings:
            target = out / plan.id
            if target.exists():
                key = generator_key(preset, seed, plan, plan.frames if frames is None else frames, image_format)
                if not _is_complete(target, key):
                    raise OutputExistsError(target)
    total = sum(r.frames if frames is None else frames for r in p.recordings)
    jobs = [(preset, int(seed), r.index, str(out), frames, image_format, test_orientations, split_recordings)
            for r in p.recordings]
    # Workers are fresh processes with single-threaded BLAS: faster on few cores, and the same
    # floating-point results whatever the number of workers.
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["MKL_NUM_THREADS"] = "1"
    # Compile the renderer's kernels here, once (or load them from numba's cache), so that no worker
    # compiles them (each would, at the same time, on a first run).
    warm_up()
    ctx = mp.get_context("spawn")
    counter = ctx.Value("q", 0)
    with ProcessPoolExecutor(max_workers=max(1, int(workers)), mp_context=ctx, initializer=_init_worker,
                             initargs=(counter,)) as pool, \
            tqdm(total=total, unit="frame", desc=f"synth {preset}", disable=not progress) as bar:
        futures = [pool.submit(_make_one, job) for job in jobs]
        while not all(f.done() for f in futures):
            time.sleep(0.2)
            bar.update(counter.value - bar.n)
        for f in futures:
            f.result()
        bar.update(counter.value - bar.n)
    path = out / f"{preset}.manifest.yaml"
    with atomic_output(path, overwrite=True) as tmp:
        tmp.write_text(yaml.safe_dump(manifest(p, "."), sort_keys=False))
    return path
