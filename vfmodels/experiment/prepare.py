"""Step 1 of an experiment: every recording of the manifest converted (raw folder or bag ->
`<id>.mcap`) and processed once per tracker the chosen variants need (`<id>.processed.mcap`,
`<id>.klt.mcap`, ...). Existing outputs are kept, so a grid resumes where it stopped."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from vfdata.conversion.bag_scan import is_bag
from vfdata.conversion.bag_topics import BagTopics
from vfdata.conversion.bags import convert_bag
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.conversion.raw_rgbd import convert_rgbd_folder, is_rgbd_folder
from vfdata.device import shared_device_options
from vfdata.errors import InputError
from vfdata.executor import run_jobs
from vfdata.lerobot.folder import is_lerobot_dataset
from vfdata.manifest import ManifestEntry
from vfdata.processing import ProcessOptions, process_recording
from vfdata.recording import Recording
from vfdata.rig import rig_for
from vfdata.threads import set_threads
from vfmodels.experiment.variants import PROCESSINGS, derived_name


@dataclass(frozen=True)
class ProcessJob:
    """One recording processed with one tracker (plain values: it crosses to a worker process)."""

    src: str
    out: str
    tracker: str
    depth: str
    segment: str
    prompt: str | None
    max_frames: int | None
    device: str = "cpu"  # the tracker's (`vfdata.device`)


def derived_path(entry: ManifestEntry, tracker: str) -> Path:
    """The derived file of the entry's recording (named after its MCAP, so entries that split one
    recording in time share it)."""
    return entry.mcap.with_name(derived_name(entry.mcap.name.removesuffix(".mcap"), tracker))


def convert(entry: ManifestEntry, progress: bool = False) -> None:
    """`<id>.mcap` from the entry's raw folder (stereo or RGB-D), bag or LeRobot episode, unless it exists."""
    if entry.mcap.is_file():
        return
    if not entry.raw.exists():
        raise InputError(entry.raw, f"recording {entry.id}: neither the raw folder or bag nor {entry.mcap.name} "
                                    "exists (for simulated data run `vfdata synth --preset NAME DIR` first)")
    options = ConvertOptions(progress=progress)
    if is_lerobot_dataset(entry.raw):
        # pyarrow and PyAV (the `lerobot` extra) only for a manifest that names a LeRobot dataset
        from vfdata.conversion.lerobot_episodes import convert_lerobot_episode

        convert_lerobot_episode(entry.raw, entry.episode or 0, entry.mcap, options=options, topics=entry.topics,
                                calibration=entry.calibration, meta=entry.conversion_meta())
    elif is_bag(entry.raw):
        lerobot_keys = {"color", "depth"} & set(entry.topics or {})
        if lerobot_keys:
            raise InputError(entry.raw, f"recording {entry.id}: topics {', '.join(sorted(lerobot_keys))} are "
                                        "features of a LeRobot dataset, not a bag's")
        convert_bag(entry.raw, entry.mcap, options=options, topics=BagTopics(**(entry.topics or {})),
                    calibration=entry.calibration, meta=entry.conversion_meta())
    elif is_rgbd_folder(entry.raw):
        convert_rgbd_folder(entry.raw, entry.mcap, options=options, calibration=entry.calibration, meta=entry.meta)
    else:
        convert_raw_folder(entry.raw, entry.mcap, options=options, meta=entry.recording_meta)


def convert_all(entries: list[ManifestEntry], progress: bool = True) -> float:
    """`convert` every entry; wall seconds."""
    started = time.perf_counter()
    for entry in tqdm(entries, desc="convert", unit="recording", disable=not progress):
        convert(entry)
    return time.perf_counter() - started


def any_depth_only(entries: list[ManifestEntry]) -> bool:
    """Whether a converted recording sees only depth (an RGB-D one: `Rig.depth_only`): its image trackers
    would see the depth drawn as grey."""
    for mcap in {entry.mcap for entry in entries}:
        with Recording(mcap) as rec:
            if rig_for(rec).depth_only:
                return True
    return False


def process(job: ProcessJob) -> str:
    """Run one job; one torch/BLAS thread, since recordings run side by side in processes."""
    set_threads(1)
    tracker_options = shared_device_options(job.tracker, job.device)
    process_recording(job.src, job.out, ProcessOptions(depth=job.depth, segment=job.segment, tracker=job.tracker,
                                                       prompt=job.prompt, max_frames=job.max_frames,
                                                       tracker_options=tracker_options, progress=False))
    return job.out


def prepare(entries: list[ManifestEntry], trackers: list[str], depth: str = "sgbm", segment: str = "colortrack",
            prompt: str | None = None, max_frames: int | None = None, workers: int = 1,
            progress: bool = True, executor: str = "local", ray_address: str | None = None,
            device: str = "cpu") -> dict[str, float]:
    """Convert what is missing, then process every recording for each processing (`PROCESSINGS` key;
    outputs that exist are kept; `prompt` for entries without their own), one job per recording and
    processing on `executor` (`vfdata.executor`). Returns wall seconds per step."""
    seconds = {"convert": convert_all(entries, progress)}
    jobs = []
    for name in trackers:
        recipe = PROCESSINGS[name]
        jobs += [ProcessJob(str(e.mcap), str(derived_path(e, name)), recipe.tracker, recipe.depth or depth,
                            recipe.segment or segment, e.prompt or prompt, max_frames, device)
                 for e in entries if not derived_path(e, name).is_file()]
    jobs = list({job.out: job for job in jobs}.values())  # entries splitting one recording share its jobs
    started = time.perf_counter()
    with tqdm(total=len(jobs), desc="process", unit="recording", disable=not progress or not jobs) as bar:
        for _ in run_jobs(process, jobs, executor, workers, ray_address):
            bar.update()
    seconds["process"] = time.perf_counter() - started
    return seconds
