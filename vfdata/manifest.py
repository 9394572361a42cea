"""Dataset manifests (`datasets/<name>.manifest.yaml`): which recordings a dataset has, their split,
orientation and files. The one reader of manifests; docs/architecture.md shows the format.

```yaml
name: glove
root: ../data/glove       # folder with the recordings, relative to this file
recordings:
  - id: glove_000         # raw folder <root>/<id>/ (or a bag: raw: <file or folder>),
    orientation_deg: 0    #   converted <root>/<id>.mcap, derived <root>/<id>.processed.mcap
    split: train          #   (each overridable with raw:, mcap:, processed:)
    frames: [0, 700]      # optional: only frames [start, stop) of the recording (splits in time)
    prompt: box:10,20,300,400   # optional: the first frame's tissue prompt for `vfdata process`
    calibration: cal.yaml # optional: an RGB-D folder's rgbd_calibration.yaml kept outside it, or a
                          #   bag's stereo calibration.yaml (instead of its CameraInfo)
    meta: meta.yaml       # optional: an RGB-D folder's meta.yaml kept outside it (both relative to root)
    gravity_up: [0, 0, 1] # optional, given to the conversion (`vfdata convert --meta`, docs/bags.md):
    tissue: glove         #   up in the ECM pose's frame, the tissue, the force sensor's frame turned
    sensor_to_object: xyz_deg:0,0,90   # into the object's; with orientation_deg and prompt
    topics: {left: /cam/left/image_raw, right: /cam/right/image_raw, force: /ati/wrench}   # a bag's
  - id: lab_ep3           # an episode of a LeRobot dataset (docs/lerobot.md): raw: names the dataset
    raw: ../lerobot/lab   #   folder, episode: its index, topics: its features (left, right, color,
    episode: 3            #   depth, force, pose)
    split: test
```

Entries that name one recording (the same `mcap:`) split it in time: each needs `frames:`, and
stretches of different splits must lie a clip's length apart (`check_guard_gaps`), so that no
clip's frames, nor its displacement's recent past, reach into another split.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, replace
from itertools import combinations
from pathlib import Path
from typing import Literal

import yaml

from vfdata.errors import InputError

Split = Literal["train", "val", "test"]
SPLITS: tuple[str, ...] = ("train", "val", "test")
DERIVED_SUFFIX = ".processed.mcap"
RECORDING_META_KEYS = ("gravity_up", "tissue", "sensor_to_object")  # entry keys given to the conversion
TOPIC_KEYS = ("left", "right", "left_info", "right_info", "force", "pose", "color", "depth")  # color, depth: LeRobot


@dataclass(frozen=True)
class ManifestEntry:
    """One recording of a dataset, with absolute paths."""

    id: str
    orientation_deg: float
    split: str
    raw: Path  # raw recording folder or bag (simulator ground truth lives in raw/ground_truth)
    mcap: Path  # the recording MCAP (images, force, ECM pose)
    processed: Path  # the derived MCAP (mask, depth, cloud, tracks)
    frames: tuple[int, int] | None = None  # [start, stop) frame range, None: every frame
    prompt: str | None = None  # first-frame tissue prompt ("box:..." or "points:...")
    calibration: Path | None = None  # RGB-D folder's rgbd_calibration.yaml, or a bag's calibration.yaml
    meta: Path | None = None  # raw folder: its meta.yaml when kept outside it
    # What a bag (or raw folder) does not say, given to its conversion as `vfdata convert --meta` pairs:
    # gravity_up, tissue, sensor_to_object (docs/bags.md); orientation_deg and prompt go with them.
    recording_meta: dict | None = None
    topics: dict | None = None  # a bag's topics: left, right, left_info, right_info, force, pose
    episode: int | None = None  # raw is a LeRobot dataset: this episode of it

    def conversion_meta(self) -> dict:
        """The metadata keys a conversion of this entry's raw recording is given."""
        meta = {"orientation_deg": self.orientation_deg, **(self.recording_meta or {})}
        if self.prompt is not None:
            meta["prompt"] = self.prompt
        return meta

    @property
    def ground_truth(self) -> Path:
        return self.raw / "ground_truth"

    def with_processed(self, path: Path) -> ManifestEntry:
        return replace(self, processed=Path(path))


@dataclass(frozen=True)
class Manifest:
    """A dataset: its name, the file it was read from and its recordings in file order."""

    name: str
    path: Path
    entries: tuple[ManifestEntry, ...]

    def ids(self, splits: tuple[str, ...] = ("train", "val")) -> dict[str, list[str]]:
        """The recordings' ids of each of `splits`, in file order (an empty list for a split without any)."""
        return {split: [e.id for e in self.entries if e.split == split] for split in splits}

    def split(self, split: str) -> list[ManifestEntry]:
        """The recordings of one split (train, val or test); an InputError when there are none."""
        if split not in SPLITS:
            raise InputError(self.path, f"split '{split}' is not one of {', '.join(SPLITS)}")
        chosen = [e for e in self.entries if e.split == split]
        if not chosen:
            raise InputError(self.path, f"no '{split}' recordings in the manifest")
        return chosen

    def __iter__(self) -> Iterator[ManifestEntry]:
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)


def _frames(path: Path, rid: str, value) -> tuple[int, int] | None:
    if value is None:
        return None
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value) or not 0 <= value[0] < value[1]):
        raise InputError(path, f"recording '{rid}': frames must be [start, stop] with 0 <= start < stop, got {value!r}")
    return int(value[0]), int(value[1])


def _under(root: Path, relative) -> Path:
    """root / relative with `..` removed lexically: the root folder (for outputs) may not exist yet,
    and the OS cannot walk `..` out of a folder that does not exist."""
    return Path(os.path.normpath(root / str(relative)))


def _entry(path: Path, root: Path, item) -> ManifestEntry:
    if not isinstance(item, dict) or "id" not in item or item.get("split") not in SPLITS:
        raise InputError(path, f"recording entry {item!r} needs an id and a split (train, val or test)")
    rid = str(item["id"])
    try:
        orientation = float(item.get("orientation_deg", 0.0))
    except (TypeError, ValueError):
        raise InputError(path, f"recording '{rid}': orientation_deg must be a number") from None
    prompt = item.get("prompt")
    if prompt is not None and not isinstance(prompt, str):
        raise InputError(path, f"recording '{rid}': prompt must be text such as box:x0,y0,x1,y1")
    extra = {key: _under(root, item[key]) if item.get(key) is not None else None for key in ("calibration", "meta")}
    recording_meta = {key: item[key] for key in RECORDING_META_KEYS if item.get(key) is not None} or None
    topics = item.get("topics")
    if topics is not None and (not isinstance(topics, dict) or not set(topics) <= set(TOPIC_KEYS)
                               or not all(isinstance(v, str) for v in topics.values())):
        raise InputError(path, f"recording '{rid}': topics must map some of {', '.join(TOPIC_KEYS)} to topic names")
    episode = item.get("episode")
    if episode is not None and (isinstance(episode, bool) or not isinstance(episode, int) or episode < 0):
        raise InputError(path, f"recording '{rid}': episode must be a LeRobot episode index (0, 1, ...), not "
                               f"{episode!r}")
    return ManifestEntry(
        rid, orientation, item["split"], _under(root, item.get("raw", rid)),
        _under(root, item.get("mcap", f"{rid}.mcap")), _under(root, item.get("processed", f"{rid}{DERIVED_SUFFIX}")),
        _frames(path, rid, item.get("frames")), prompt, **extra, recording_meta=recording_meta, topics=topics,
        episode=episode,
    )


def check_guard_gaps(manifest: Manifest, gap_frames: int) -> None:
    """Entries sharing one recording (the same mcap) must each name `frames`, and two of different
    splits must lie at least `gap_frames` frames apart (a clip's length); an InputError naming the
    manifest and both entries otherwise."""
    by_recording: dict[Path, list[ManifestEntry]] = defaultdict(list)
    for entry in manifest.entries:
        by_recording[entry.mcap].append(entry)
    for entries in by_recording.values():
        if len(entries) < 2:
            continue
        for a, b in combinations(entries, 2):
            if a.frames is None or b.frames is None:
                raise InputError(manifest.path, f"recordings '{a.id}' and '{b.id}' share {a.mcap.name}: each needs "
                                                "frames: [start, stop]")
            if a.split == b.split:
                continue
            first, second = sorted((a, b), key=lambda e: e.frames)
            apart = second.frames[0] - first.frames[1]
            if apart < gap_frames:
                what = "overlap" if apart < 0 else f"are {apart} frames apart"
                raise InputError(manifest.path, f"'{first.id}' ({first.split}, frames {list(first.frames)}) and "
                                                f"'{second.id}' ({second.split}, frames {list(second.frames)}) of "
                                                f"{a.mcap.name} {what}: splits of one recording need a guard gap of "
                                                f"a clip's length ({gap_frames} frames)")


def load_manifest(path: str | Path) -> Manifest:
    """The manifest at `path` (docs/architecture.md), paths made absolute relative to its `root`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "dataset manifest not found")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not a valid YAML manifest ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict) or not isinstance(data.get("recordings"), list) or not data["recordings"]:
        raise InputError(path, "a manifest needs a non-empty 'recordings' list")
    root = (path.parent / str(data.get("root", "."))).resolve()
    entries = tuple(_entry(path, root, item) for item in data["recordings"])
    ids = [e.id for e in entries]
    if len(set(ids)) != len(ids):
        raise InputError(path, "recording ids are not unique")
    return Manifest(str(data.get("name", path.stem.removesuffix(".manifest"))), path.resolve(), entries)


def write_manifest(path: str | Path, name: str, entries: list[ManifestEntry], relative_to: Path | None = None) -> Path:
    """A manifest with absolute paths (so it can live anywhere), e.g. one per tracker's derived files;
    with `relative_to`, paths relative to that folder (`root: .`: the manifest moves with its folder,
    which must be where it is written, or one that will be renamed to it)."""
    path = Path(path)

    def where(p: Path) -> str:
        return str(p) if relative_to is None else os.path.relpath(p, relative_to)

    recordings = []
    for e in entries:
        item = {"id": e.id, "orientation_deg": e.orientation_deg, "split": e.split, "raw": where(e.raw),
                "mcap": where(e.mcap), "processed": where(e.processed)}
        if e.episode is not None:
            item["episode"] = e.episode
        if e.frames is not None:
            item["frames"] = list(e.frames)
        if e.prompt is not None:
            item["prompt"] = e.prompt
        for key in ("calibration", "meta"):
            if getattr(e, key) is not None:
                item[key] = where(getattr(e, key))
        item.update(e.recording_meta or {})
        if e.topics:
            item["topics"] = dict(e.topics)
        recordings.append(item)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    head = {"name": name} if relative_to is None else {"name": name, "root": "."}
    tmp.write_text(yaml.safe_dump({**head, "recordings": recordings}, sort_keys=False))
    tmp.replace(path)
    return path
