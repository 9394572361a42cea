"""The dataset card (README.md) of an export: Hugging Face's front matter as LeRobot writes it, then the
sections of Open-H's dataset template (`templates/dataset_template.md` of open-h-embodiment/
data-collection) filled with what the recordings say, and "not recorded" where they say nothing."""

from __future__ import annotations

import json

from vfdata.lerobot import features as names

NOT_RECORDED = "not recorded in the recordings: fill in"


def dataset_card(name: str, info: dict, episodes: list[dict], sensor_hz: float, task: str,
                 license_id: str | None) -> str:
    """README.md text. `episodes`: per episode its recording id, split, study, tissue, orientation,
    frames and whether it was simulated."""
    frames = sum(e["frames"] for e in episodes)
    hours = frames / info["fps"] / 3600
    simulated = all(e["synthetic"] for e in episodes)
    view = info["features"][names.LEFT]["shape"]
    front = ["---", *([f"license: {license_id}"] if license_id else []), "task_categories:", "- robotics", "tags:",
             "- LeRobot", "- surgical-robotics", "- force-torque", "- Open-H", "- VisionForce", "configs:",
             "- config_name: default", "  data_files: data/*/*.parquet", "---", ""]
    kind = "[x] Digital Simulation" if simulated else f"{NOT_RECORDED} (Clinical, Ex-Vivo, Table-Top Phantom, ...)"
    state = info["features"].get(names.STATE)
    lines = [
        f"# {name}", "",
        "## At a Glance", "",
        f"Stereo endoscopic video with a force/torque sensor at its own rate ({sensor_hz:.0f} Hz), exported by "
        f"VisionForce (`vfdata export --lerobot`) from {len(episodes)} recording(s).", "",
        "## Dataset Overview", "",
        "| | |", "| :--- | :--- |",
        f"| **Total Trajectories** | {len(episodes)} |",
        f"| **Total Hours** | {hours:.4f} ({frames} frames at {info['fps']} frames/s) |",
        f"| **Data Type** | {kind} |",
        f"| **License** | {license_id or NOT_RECORDED} |",
        f"| **LeRobot format** | {info['codebase_version']} |", "",
        "## Tasks & Domain", "",
        "- [x] **Surgical Robotics**", "",
        f"Demonstrated skill: {task}.", "",
        "## Data Collection Details", "",
        f"Collection method: {'programmatic (the VisionForce simulator)' if simulated else NOT_RECORDED}. "
        f"Operator details, collection period: {NOT_RECORDED}.", "",
        "## Equipment & Setup", "",
        "| Type | Model/Details |", "| :--- | :--- |",
        f"| **Primary Camera** | stereo endoscope, {view[1]}x{view[0]} @ {info['fps']} fps "
        f"(`{names.LEFT}`, `{names.RIGHT}`; calibration: `meta/calibration.yaml`, OpenCV FileStorage) |",
        f"| **Force/Torque Sensor** | {sensor_hz:.0f} Hz, frame `{_sensor(info)}` (model {NOT_RECORDED}) |", "",
        "## Action & State Space Representation", "",
        "No `action` feature: the recordings hold what the cameras saw and the sensor measured, no commands.", "",
    ]
    if state:
        lines += [f"`{names.STATE}`: [x, y, z, qx, qy, qz, qw]: the endoscope (ECM) camera pose in the robot's world "
                  "frame, metres and a unit quaternion (absolute Cartesian, robot base frame).", ""]
    lines += [
        "## Data Synchronization Approach", "",
        f"Every stream keeps its acquisition stamps (ROS `header.stamp`, ns since the epoch). `{names.STAMP}` is "
        "each frame's stamp; `timestamp` is LeRobot's clock (frame_index / fps). "
        f"`{names.FORCE}` is the force/torque interpolated linearly at the frame's stamp (N, N m, sensor frame); "
        f"`{names.SAMPLES}` holds every sensor sample stamped after the previous frame and up to this one "
        f"(oldest first; `{names.SAMPLE_STAMPS}` their stamps, `{names.SAMPLE_COUNT}` how many rows are "
        "samples, the rest zero). Offsets between the camera and sensor clocks: as recorded.", "",
        "## Features", "",
        "| feature | dtype | shape | meaning |", "| :--- | :--- | :--- | :--- |",
        *[f"| `{key}` | {f['dtype']} | {list(f['shape'])} | {_MEANING.get(key, '')} |"
          for key, f in info["features"].items()], "",
        "## Episodes", "",
        "| episode | recording | split | study | tissue | orientation (deg) | frames |",
        "| ---: | :--- | :--- | :--- | :--- | ---: | ---: |",
        *[f"| {i} | {e['id']} | {e['split'] or '-'} | {e['study'] or '-'} | {e['tissue'] or '-'} | "
          f"{e['orientation_deg']:g} | {e['frames']} |" for i, e in enumerate(episodes)], "",
        "Each episode's recording metadata (VisionForce's `visionforce.recording` record, JSON) is in the episode "
        "records of `meta/`. `vfdata convert` turns this dataset back into the recordings (docs/lerobot.md).", "",
        "## Attribution & Contact", "",
        f"Dataset lead, institution, contact, citation: {NOT_RECORDED}.", "",
        "## Dataset Structure", "",
        "[meta/info.json](meta/info.json):", "```json", json.dumps(info, indent=4), "```", "",
    ]
    return "\n".join(front + lines)


def _sensor(info: dict) -> str:
    return (info["features"][names.FORCE].get("info") or {}).get("sensor", "force_sensor")


_MEANING = {
    names.LEFT: "left view of the stereo endoscope (as recorded, not rectified)",
    names.RIGHT: "right view",
    names.STATE: "ECM camera pose: x y z (m), qx qy qz qw",
    names.FORCE: "force/torque at the frame's stamp: fx fy fz (N), tx ty tz (N m), sensor frame",
    names.SAMPLES: "the sensor's samples since the previous frame, oldest first, zero-padded (N, N m)",
    names.SAMPLE_STAMPS: "their stamps, ns since the epoch (0 in padding)",
    names.SAMPLE_COUNT: "how many rows of the samples are samples",
    names.STAMP: "the frame's acquisition stamp, ns since the epoch",
    names.TRACKS: "tracked tissue points (`vfdata process`), object frame, mm",
    names.TRACKS_VISIBLE: "whether each tracked point is seen in the frame",
    names.FORCE_ESTIMATE: "estimated force (`vfdata predict`), object frame, N; NaN where none",
    "timestamp": "LeRobot's clock: frame_index / fps, s",
    "frame_index": "frame of the episode", "episode_index": "episode", "index": "frame of the dataset",
    "task_index": "task (meta/tasks)",
}
