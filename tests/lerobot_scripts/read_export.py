"""Run with LeRobot's own Python: load a dataset with `LeRobotDataset` (PyAV decoding), read every
frame's force with a `delta_timestamps` window of the two frames before and the frame itself, and the
native-rate samples, and write them (and one decoded image) to an .npz for the test to compare.

    python read_export.py DATASET OUT.npz
"""

import sys

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset


def main(root: str, out: str) -> None:
    deltas = [-2 / 30, -1 / 30, 0.0]
    ds = LeRobotDataset("local/export", root=root, video_backend="pyav",
                        delta_timestamps={"observation.meta.force_torque": deltas})
    samples, counts, stamps, episode, windows = [], [], [], [], []
    for i in range(len(ds)):
        row = ds.hf_dataset[i]
        episode.append(int(row["episode_index"]))
        stamps.append(int(row["observation.meta.stamp_ns"]))
        samples.append(np.asarray(row["observation.meta.force_torque_samples"], dtype=np.float64))
        counts.append(int(row["observation.meta.force_torque_samples_count"]))
    for i in range(0, len(ds), 7):
        item = ds[i]
        windows.append((i, item["observation.meta.force_torque"].numpy(),
                        item["observation.meta.force_torque_is_pad"].numpy()))
    last = ds[len(ds) - 1]
    np.savez(out, episode=np.array(episode), stamp_ns=np.array(stamps), samples=np.stack(samples),
             counts=np.array(counts), window_index=np.array([w[0] for w in windows]),
             window_force=np.stack([w[1] for w in windows]), window_pad=np.stack([w[2] for w in windows]),
             last_left=(last["observation.images.endoscope.left"].numpy() * 255).round().astype(np.uint8),
             fps=ds.fps, total=len(ds))


if __name__ == "__main__":
    main(*sys.argv[1:])
