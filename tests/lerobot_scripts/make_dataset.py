"""Run with LeRobot's own Python (its own virtual environment): a LeRobot dataset made by LeRobot's
API from raw recording folders (docs/raw_layout.md), as a lab would make one from its recordings and
as Open-H's converters do: the stereo views as videos, the force/torque interpolated at each frame
(Open-H's `observation.meta.force_torque`), the ECM pose as `observation.state`, splits in info.json.

    python make_dataset.py OUT RAW_FOLDER:SPLIT ...
"""

import csv
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.utils import write_info
from PIL import Image


def table(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """force.csv or ecm_pose.csv: stamps (ns) and values."""
    with open(path) as f:
        rows = list(csv.reader(f))[1:]
    return np.array([int(r[0]) for r in rows], dtype=np.int64), np.array([[float(v) for v in r[1:]] for r in rows])


def frame_stamps(path: Path) -> np.ndarray:
    """frames.csv: frame,timestamp_ns."""
    with open(path) as f:
        return np.array([int(r[1]) for r in list(csv.reader(f))[1:]], dtype=np.int64)


def main(out: str, *sources: str) -> None:
    folders = [(Path(s.split(":")[0]), s.split(":")[1]) for s in sources]
    first = sorted((folders[0][0] / "left").iterdir())[0]
    width, height = Image.open(first).size
    video = {"dtype": "video", "shape": (height, width, 3), "names": ["height", "width", "channels"]}
    features = {
        "observation.images.endoscope.left": video,
        "observation.images.endoscope.right": dict(video),
        "observation.state": {"dtype": "float32", "shape": (7,),
                              "names": ["ecm_x", "ecm_y", "ecm_z", "ecm_qx", "ecm_qy", "ecm_qz", "ecm_qw"]},
        "observation.meta.force_torque": {"dtype": "float32", "shape": (6,),
                                          "names": ["fx", "fy", "fz", "tx", "ty", "tz"],
                                          "info": {"sensor": "ati_nano17", "units": "N + N m"}},
    }
    ds = LeRobotDataset.create("lab/made_by_lerobot", fps=30, root=out, features=features, use_videos=True,
                               robot_type="dvrk")
    splits = {}
    for episode, (folder, split) in enumerate(folders):
        frame_ns = frame_stamps(folder / "frames.csv")
        force_ns, wrench = table(folder / "force.csv")
        pose_ns, pose = table(folder / "ecm_pose.csv")
        force = np.stack([np.interp(frame_ns, force_ns, wrench[:, j]) for j in range(6)], axis=1)
        state = np.stack([np.interp(frame_ns, pose_ns, pose[:, j]) for j in range(7)], axis=1)
        lefts, rights = sorted((folder / "left").iterdir()), sorted((folder / "right").iterdir())
        for k in range(len(frame_ns)):
            ds.add_frame({"observation.images.endoscope.left": np.asarray(Image.open(lefts[k]).convert("RGB")),
                          "observation.images.endoscope.right": np.asarray(Image.open(rights[k]).convert("RGB")),
                          "observation.state": state[k].astype(np.float32),
                          "observation.meta.force_torque": force[k].astype(np.float32), "task": "press the tissue"})
        ds.save_episode()
        start = splits.get(split, (episode, episode))[0]
        splits[split] = (start, episode + 1)
    ds.finalize()
    ds.meta.info["splits"] = {name: f"{a}:{b}" for name, (a, b) in splits.items()}  # as Open-H's converters do
    write_info(ds.meta.info, ds.root)


if __name__ == "__main__":
    main(*sys.argv[1:])
