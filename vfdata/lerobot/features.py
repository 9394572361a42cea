"""Which LeRobot features hold what (docs/lerobot.md, "Features").

`EXPORT_*`: the features `vfdata export --lerobot` writes, Open-H's names where Open-H has one
(`observation.images.<view>`, `observation.state`, `observation.meta.force_torque`: fx fy fz tx ty tz,
"N + N m") and `observation.meta.*` for the rest, as Open-H asks.

`choose_features`: for `vfdata convert`, which features of a dataset are the stereo pair (or the
colour view and the depth), the force/torque, the ECM pose, and our exact stamps and native force
samples when the dataset is one of our exports. Features are named with `--topics KEY=FEATURE`
(keys left, right, color, depth, force, pose; `pose=none` leaves the pose out), as a manifest's
`topics:` names a bag's topics; what is not named is found by the rules below, and an ambiguity is an
error that lists the candidates."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from vfdata.errors import InputError
from vfdata.lerobot.folder import DatasetFolder

LEFT = "observation.images.endoscope.left"  # Open-H's dVRK converter names the stereo endoscope so
RIGHT = "observation.images.endoscope.right"
FORCE = "observation.meta.force_torque"
FORCE_NAMES = ("fx", "fy", "fz", "tx", "ty", "tz")
FORCE_UNITS = "N + N m"  # Open-H's spelling
STATE = "observation.state"
STATE_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw")
STAMP = "observation.meta.stamp_ns"  # each frame's acquisition stamp, ns since the epoch (exact)
SAMPLES = "observation.meta.force_torque_samples"  # (W, 6) float64: the native samples since the last frame
SAMPLE_STAMPS = "observation.meta.force_torque_samples_stamp_ns"  # (W,) int64
SAMPLE_COUNT = "observation.meta.force_torque_samples_count"  # how many of the W rows are samples
TRACKS = "observation.meta.tracks"  # (N, 3) float32 tracked points, object frame, mm
TRACKS_VISIBLE = "observation.meta.tracks_visible"  # (N,) bool
FORCE_ESTIMATE = "observation.meta.force_estimate"  # (3,) float32 estimated force, object frame, N
RECORDING_KEY = "visionforce.recording"  # episode record: the recording's metadata record, JSON

TOPIC_KEYS = ("left", "right", "color", "depth", "force", "pose")
NONE = "none"
_SIDE = re.compile(r"(?<![a-z])(left|right)(?![a-z])", re.IGNORECASE)
_NUMERIC = ("float16", "float32", "float64", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64")


@dataclass(frozen=True)
class FeatureChoice:
    """The features a conversion reads; stereo (`left`, `right`) or RGB-D (`depth`, optional `color`)."""

    force: str
    force_columns: tuple[int, ...]  # columns of fx fy fz [tx ty tz] in the force feature
    left: str | None = None
    right: str | None = None
    color: str | None = None
    depth: str | None = None
    pose: str | None = None
    pose_columns: tuple[int, ...] = ()
    stamp: str | None = None  # our exact stamps, when present
    samples: bool = False  # our native-rate force windows, when present
    how: dict[str, str] = field(default_factory=dict)

    @property
    def is_rgbd(self) -> bool:
        return self.depth is not None


def feature_names(feature: dict) -> list[str] | None:
    """A feature's `names` as a flat list (LeRobot writes lists, dicts of lists and nested lists)."""
    names = feature.get("names")
    if isinstance(names, dict):
        names = next(iter(names.values()), None)
    if isinstance(names, list) and len(names) == 1 and isinstance(names[0], list):
        names = names[0]
    return [str(n) for n in names] if isinstance(names, list) else None


def parse_topics(items: list[str], where: str = "--topics") -> dict[str, str]:
    """`--topics left=FEATURE,right=FEATURE` (repeatable) -> {key: feature}."""
    asked: dict[str, str] = {}
    for item in items:
        for pair in item.split(","):
            key, sep, value = pair.partition("=")
            key, value = key.strip(), value.strip()
            if not sep or not value or key not in TOPIC_KEYS:
                raise InputError(where, f"'{pair}' is not KEY=FEATURE with KEY one of {', '.join(TOPIC_KEYS)}")
            if key in asked:
                raise InputError(where, f"'{key}' is given twice")
            asked[key] = value
    return asked


def choose_features(ds: DatasetFolder, asked: dict[str, str] | None = None) -> FeatureChoice:
    """The features to read from `ds`: those `asked` (checked), the others found (InputError naming
    info.json when something is missing or ambiguous)."""
    asked = dict(asked or {})
    where = ds.info_path
    how: dict[str, str] = {}
    for key, name in asked.items():
        if name != NONE and name not in ds.features:
            raise InputError(where, f"--topics {key}={name}: no such feature (features: {', '.join(ds.features)})")
    cameras = [k for k, f in ds.features.items() if f["dtype"] in ("video", "image")]
    views = _views(ds, asked, cameras, how)
    force, columns = _force(ds, asked.get("force"), how)
    pose, pose_columns = _pose(ds, asked.get("pose"), how)
    stamp = STAMP if ds.features.get(STAMP, {}).get("dtype") == "int64" else None
    samples = all(k in ds.features for k in (SAMPLES, SAMPLE_STAMPS, SAMPLE_COUNT))
    return FeatureChoice(force, columns, **views, pose=pose, pose_columns=pose_columns, stamp=stamp, samples=samples,
                         how=how)


def _camera(ds: DatasetFolder, name: str, key: str) -> str:
    if ds.features[name]["dtype"] not in ("video", "image"):
        raise InputError(ds.info_path, f"--topics {key}={name}: a {ds.features[name]['dtype']} feature, not images")
    return name


def _views(ds: DatasetFolder, asked: dict[str, str], cameras: list[str], how: dict[str, str]) -> dict:
    where = ds.info_path
    if "left" in asked or "right" in asked:
        left = asked.get("left") or _swap(asked["right"], "left")
        right = asked.get("right") or _swap(left, "right")
        if left not in ds.features or right not in ds.features:
            raise InputError(where, f"--topics: the other view of {left if left in ds.features else right} "
                                    f"({right if left in ds.features else left}) is not a feature: give both")
        how.update(left="given", right="given")
        return {"left": _camera(ds, left, "left"), "right": _camera(ds, right, "right")}
    if "depth" not in asked:
        pairs = sorted({tuple(sorted((c, _swap(c, "right")))) for c in cameras
                        if _SIDE.search(c) and _swap(c, "right") != c and _swap(c, "right") in cameras})
        pairs = [(a if "left" in a.lower() else b, b if "left" in a.lower() else a) for a, b in pairs]
        if len(pairs) > 1:  # e.g. Open-H's dVRK: the endoscope pair and the two wrist cameras
            preferred = [p for p in pairs if re.search(r"endo|stereo", p[0], re.IGNORECASE)]
            pairs = preferred if len(preferred) == 1 else pairs
        if len(pairs) > 1:
            raise InputError(where, "several stereo pairs (" + "; ".join(f"{a}, {b}" for a, b in pairs)
                             + "): choose one with --topics left=FEATURE,right=FEATURE")
        if pairs:
            how.update(left="auto-detected", right="auto-detected")
            return {"left": pairs[0][0], "right": pairs[0][1]}
    depth = asked.get("depth") or _one(where, [k for k in ds.features if "depth" in k.lower() and _is_depth(ds, k)],
                                        "depth", "no stereo pair (two image features whose names differ by "
                                                 "left/right) and no depth feature")
    if not _is_depth(ds, depth):
        raise InputError(where, f"--topics depth={depth}: depth must be an image or a (H, W) numeric feature, not "
                                f"{ds.features[depth]['dtype']} {list(ds.features[depth]['shape'])}")
    how["depth"] = "given" if "depth" in asked else "auto-detected"
    color = asked.get("color")
    if color is None:
        others = [c for c in cameras if c != depth and ds.features[c]["dtype"] in ("video", "image")
                  and ds.features[c]["shape"][-1] == 3]
        named = [c for c in others if re.search(r"color|colour|rgb", c, re.IGNORECASE)]
        color = (named or others)[0] if len(named or others) == 1 else None
        how["color"] = "auto-detected" if color else "none"
    else:
        color = None if color == NONE else _camera(ds, color, "color")
        how["color"] = "given"
    return {"depth": depth, "color": color}


def _is_depth(ds: DatasetFolder, key: str) -> bool:
    feature = ds.features[key]
    shape = feature["shape"]
    if feature["dtype"] == "image":
        return True
    return feature["dtype"] in _NUMERIC and (len(shape) == 2 or (len(shape) == 3 and 1 in (shape[0], shape[2])))


def _swap(name: str, side: str) -> str:
    return _SIDE.sub(lambda m: _case(side, m.group(0)), name)


def _case(word: str, like: str) -> str:
    return word.upper() if like.isupper() else word.capitalize() if like[0].isupper() else word


def _one(where, candidates: list[str], what: str, none: str) -> str:
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise InputError(where, f"{none}: name the {what} feature with --topics {what}=FEATURE")
    raise InputError(where, f"several {what} features ({', '.join(candidates)}): choose one with --topics "
                            f"{what}=FEATURE")


def _numeric(ds: DatasetFolder, name: str, key: str) -> dict:
    feature = ds.features[name]
    if feature["dtype"] not in _NUMERIC or len(feature["shape"]) != 1:
        raise InputError(ds.info_path, f"{key} feature {name}: {feature['dtype']} {list(feature['shape'])}, not a "
                                       "vector of numbers")
    return feature


def _force(ds: DatasetFolder, asked: str | None, how: dict[str, str]) -> tuple[str, tuple[int, ...]]:
    where = ds.info_path
    if asked is None:
        if FORCE in ds.features:
            name, how["force"] = FORCE, "Open-H name"
        else:
            named = [k for k, f in ds.features.items() if {"fx", "fy", "fz"} <= set(feature_names(f) or ())
                     and k != FORCE_ESTIMATE]
            name = _one(where, named, "force", f"no {FORCE} and no feature with names fx, fy, fz")
            how["force"] = "auto-detected (names fx, fy, fz)"
    else:
        name, how["force"] = asked, "given"
    feature = _numeric(ds, name, "force")
    names = [n.lower() for n in feature_names(feature) or ()]
    if {"fx", "fy", "fz"} <= set(names):
        columns = tuple(names.index(n) for n in FORCE_NAMES if n in names)
        if len(columns) not in (3, 6):
            raise InputError(where, f"force feature {name}: names {names} have fx fy fz but not all of tx ty tz")
        return name, columns
    size = feature["shape"][0]
    if size not in (3, 6):
        raise InputError(where, f"force feature {name} has {size} values: a force/torque is fx fy fz [tx ty tz] (N, "
                                "N m); give its names in info.json")
    return name, tuple(range(size))


def _pose(ds: DatasetFolder, asked: str | None, how: dict[str, str]) -> tuple[str | None, tuple[int, ...]]:
    if asked == NONE:
        how["pose"] = "left out"
        return None, ()
    if asked is None:
        # Only a state that says it is a pose (x y z qx qy qz qw, as our export writes it): a robot's
        # state is often joint angles, which are no camera pose.
        named = [k for k, f in ds.features.items() if feature_names(f) is not None and
                 tuple(n.lower() for n in feature_names(f)) == STATE_NAMES]
        if len(named) != 1:
            how["pose"] = "none (name it with --topics pose=FEATURE)"
            return None, ()
        asked, how["pose"] = named[0], "auto-detected (names x y z qx qy qz qw)"
    else:
        how["pose"] = "given"
    feature = _numeric(ds, asked, "pose")
    names = [n.lower() for n in feature_names(feature) or ()]
    if set(STATE_NAMES) <= set(names):
        return asked, tuple(names.index(n) for n in STATE_NAMES)
    if feature["shape"][0] != 7:
        raise InputError(ds.info_path, f"pose feature {asked} has {feature['shape'][0]} values: an ECM pose is x y z "
                                       "(m) qx qy qz qw; give these names in info.json")
    return asked, tuple(range(7))
