"""Every episode of a LeRobot dataset -> a folder of recording MCAPs and a dataset manifest of them
(`vfdata convert DATASET OUT_DIR`), so that `vfdata experiment OUT_DIR/<name>.manifest.yaml` runs on it.

The folder is written whole or not at all (a temporary folder beside it, renamed at the end): a
problem in any episode is one InputError naming the file, and nothing is left. Each manifest entry
keeps the dataset and its episode (`raw:`, `episode:`), so a deleted MCAP is converted again by
`vfdata experiment`. Splits: the episode's own (our exports keep each recording's), else info.json
`splits` (or `--splits NAME=START:STOP`), else train."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from tqdm import tqdm

from vfdata.atomic import atomic_output, check_output
from vfdata.conversion.lerobot_episodes import convert_lerobot_episode
from vfdata.conversion.options import ConvertOptions
from vfdata.errors import InputError
from vfdata.lerobot.features import choose_features
from vfdata.lerobot.folder import DatasetFolder, read_dataset
from vfdata.manifest import (
    DERIVED_SUFFIX,
    RECORDING_META_KEYS,
    SPLITS,
    ManifestEntry,
    load_manifest,
    write_manifest,
)
from vfdata.recording import Recording


def parse_splits(items: list[str], where: str = "--splits") -> dict[str, str]:
    """`--splits train=0:8,val=8:9` (repeatable) -> {"train": "0:8", ...}: info.json's notation."""
    splits: dict[str, str] = {}
    for item in items:
        for pair in item.split(","):
            name, sep, span = pair.partition("=")
            name, span = name.strip(), span.strip()
            start, colon, stop = span.partition(":")
            if not sep or name not in SPLITS or not colon or not start.isdigit() or not stop.isdigit() \
                    or int(start) >= int(stop):
                raise InputError(where, f"'{pair}' is not SPLIT=START:STOP (SPLIT one of {', '.join(SPLITS)}, episodes "
                                        "START <= i < STOP)")
            if name in splits:
                raise InputError(where, f"'{name}' is given twice")
            splits[name] = span
    return splits


def episode_meta_pairs(items: list[str]) -> tuple[list[str], dict[int, list[str]]]:
    """`--meta` items split into those for every episode and those for some: `N:KEY=VALUE` (episode N)
    or `A-B:KEY=VALUE` (episodes A to B, both included)."""
    common: list[str] = []
    scoped: dict[int, list[str]] = {}
    for item in items:
        head, colon, rest = item.partition(":")
        first, dash, last = head.partition("-")
        if colon and "=" in rest and first.isdigit() and (not dash or last.isdigit()) and "=" not in head:
            for episode in range(int(first), int(last if dash else first) + 1):
                scoped.setdefault(episode, []).append(rest)
        else:
            common.append(item)
    return common, scoped


def convert_lerobot_dataset(src: str | Path, out_dir: str | Path, overwrite: bool = False,
                            options: ConvertOptions | None = None, topics: dict[str, str] | None = None,
                            calibration: str | Path | None = None, meta: dict | None = None,
                            splits: dict[str, str] | None = None, episode_meta: dict[int, dict] | None = None,
                            clock: str = "timestamp") -> Path:
    """Convert every episode of the LeRobot dataset at `src` into `out_dir` (created) as `<id>.mcap`,
    with `<dataset name>.manifest.yaml` listing them. `meta`: metadata keys for every episode,
    `episode_meta`: for some ({episode: {key: value}}, `--meta N:KEY=VALUE`). Returns the manifest's path."""
    options = options or ConvertOptions()
    src, out_dir = Path(src), Path(out_dir)
    ds = read_dataset(src)
    if splits:
        ds = dataclasses.replace(ds, splits=splits)
    choose_features(ds, topics)  # a dataset without a view or a force fails here, before any decoding
    unknown = sorted(set(episode_meta or {}) - {e.index for e in ds.episodes})
    if unknown:
        raise InputError("--meta", f"names episode {unknown[0]}, which the dataset does not have")
    inputs = [src, *([calibration] if calibration else [])]
    check_output(out_dir, overwrite, inputs=inputs)
    inner = dataclasses.replace(options, progress=False)
    with atomic_output(out_dir, overwrite, inputs=inputs) as tmp:
        tmp.mkdir()
        entries = []
        for episode in tqdm(ds.episodes, desc=f"convert {ds.name}", unit="episode", disable=not options.progress):
            part = tmp / f".episode_{episode.index:06d}.mcap"
            given = {**(meta or {}), **(episode_meta or {}).get(episode.index, {})}
            convert_lerobot_episode(src, episode.index, part, options=inner, topics=topics, calibration=calibration,
                                    meta=given, dataset=ds, clock=clock)
            entries.append(_entry(ds, episode.index, part, tmp, src, topics, calibration, given))
        ids = [e.id for e in entries]
        if len(set(ids)) != len(ids):
            twice = next(i for i in ids if ids.count(i) > 1)
            raise InputError(src, f"two episodes are both recording '{twice}' (their ids come from the episodes' "
                                  "metadata or --meta id=): convert them one at a time with --episode N")
        for entry in entries:
            (tmp / f".episode_{entry.episode:06d}.mcap").rename(entry.mcap)
        manifest = write_manifest(tmp / f"{ds.name}.manifest.yaml", ds.name, entries, relative_to=tmp)
    return out_dir / manifest.name


def _entry(ds: DatasetFolder, index: int, mcap: Path, folder: Path, src: Path, topics: dict | None,
           calibration: str | Path | None, given: dict) -> ManifestEntry:
    """The manifest entry of a converted episode: what `vfdata experiment` needs to convert it again."""
    with Recording(mcap) as rec:
        meta = rec.metadata
    rid = meta.recording_id
    if not rid or Path(rid).name != rid or rid.startswith("."):
        raise InputError(ds.info_path, f"episode {index}: recording id {rid!r} cannot name a file (give --meta id=NAME "
                                       "with --episode N)")
    split = meta.split if meta.split in SPLITS else "train"
    recording_meta = {k: given[k] for k in RECORDING_META_KEYS if k in given} or None
    prompt = given.get("prompt")
    if prompt is None and given.get("prompt_box") is not None:  # a prompt a manifest entry can carry
        box = given["prompt_box"]
        prompt = "box:" + (box if isinstance(box, str) else ",".join(f"{v:g}" for v in box))
    return ManifestEntry(rid, meta.orientation_deg, split, src.resolve(), folder / f"{rid}.mcap",
                         folder / f"{rid}{DERIVED_SUFFIX}", prompt=prompt,
                         calibration=Path(calibration).resolve() if calibration else None,
                         recording_meta=recording_meta, topics=dict(topics) if topics else None, episode=index)


def manifest_note(manifest: Path) -> str | None:
    """What `vfdata experiment` will miss in a manifest written here (None when it has every split)."""
    present = {e.split for e in load_manifest(manifest).entries}
    missing = [s for s in SPLITS if s not in present]
    if not missing:
        return None
    return (f"{manifest}: no {' or '.join(missing)} episodes (the dataset's info.json names no such split): "
            "`vfdata experiment` needs train, val and test; convert again with --splits train=A:B,val=B:C,test=C:D")
