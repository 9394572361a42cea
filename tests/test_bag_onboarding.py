"""A lab's own bags, onboarded: `vfdata convert BAG OUT --meta KEY=VALUE` sets what a bag lacks (gravity-up,
orientation, tissue, prompt, the sensor-to-object rotation), a manifest entry carries the same keys and
the bag's topic names, and such a dataset goes from bags to Table I through `vfdata experiment`."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from bagfixtures import BagSpec, write_bag
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vfdata.cli import main
from vfdata.clips.decode import force_at
from vfdata.errors import InputError
from vfdata.manifest import load_manifest
from vfdata.recording import Recording, layout

LAB = {"left": "/lab/stereo/left/image/compressed", "right": "/lab/stereo/right/image/compressed",
       "force": "/lab/ati_ft/wrench", "pose": "/lab/psm3/ecm_pose"}


def lab_bag(tmp_path: Path) -> tuple[Path, BagSpec]:
    spec = write_bag(tmp_path / "lab.bag", BagSpec(left="/lab/cam/left", right="/lab/cam/right",
                                                   force_topics=("/lab/ft",)))
    return tmp_path / "lab.bag", spec


def test_convert_meta_sets_what_a_bag_lacks(tmp_path, capsys):
    bag, spec = lab_bag(tmp_path)
    out = tmp_path / "rec.mcap"
    assert main(["convert", str(bag), str(out), "--quiet", "--left-topic", "/lab/cam/left", "--right-topic",
                 "/lab/cam/right", "--meta", "gravity_up=0,-1,0", "--meta", "orientation_deg=90", "--meta",
                 "tissue=porcine liver", "--meta", "prompt=box:5,5,40,30", "--meta",
                 "sensor_to_object=xyz_deg:0,0,90", "--meta", "operator=ab"]) == 0
    meta = Recording.open(out).metadata
    assert meta.gravity_up_world == (0.0, -1.0, 0.0) and meta.orientation_deg == 90.0
    assert meta.tissue == "porcine liver" and meta.extra["prompt"] == "box:5,5,40,30"
    assert meta.extra["operator"] == "ab" and "gravity_up_assumed" not in meta.extra
    np.testing.assert_allclose(json.loads(meta.extra["sensor_to_object"]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
                               atol=1e-12)


def test_the_force_label_is_turned_into_the_object_frame(tmp_path):
    """sensor_to_object turns the sensor's force into the object frame: 90 degrees about z takes the
    sensor's (fx, fy, fz) to (-fy, fx, fz)."""
    bag, spec = lab_bag(tmp_path)
    plain, turned = tmp_path / "plain.mcap", tmp_path / "turned.mcap"
    remap = ["--left-topic", "/lab/cam/left", "--right-topic", "/lab/cam/right", "--quiet"]
    assert main(["convert", str(bag), str(plain), *remap]) == 0
    assert main(["convert", str(bag), str(turned), *remap, "--meta", "sensor_to_object=0,-1,0,1,0,0,0,0,1"]) == 0
    entries = []
    for mcap in (plain, turned):
        manifest = tmp_path / f"{mcap.stem}.manifest.yaml"
        manifest.write_text(yaml.safe_dump({"recordings": [{"id": mcap.stem, "split": "train"}]}))
        entries.append(load_manifest(manifest).entries[0])
    times = Recording.open(plain).frame_times_ns
    sensor, obj = force_at(entries[0], times), force_at(entries[1], times)
    np.testing.assert_allclose(obj, np.stack([-sensor[:, 1], sensor[:, 0], sensor[:, 2]], axis=1), atol=1e-5)


def test_without_gravity_up_the_bag_says_so(tmp_path):
    bag, _ = lab_bag(tmp_path)
    out = tmp_path / "rec.mcap"
    assert main(["convert", str(bag), str(out), "--quiet", "--left-topic", "/lab/cam/left", "--right-topic",
                 "/lab/cam/right"]) == 0
    from vfdata.rig import camera_up

    rec = Recording.open(out)
    assert rec.metadata.extra["gravity_up_assumed"] == "true" and camera_up(rec) is None


@pytest.mark.parametrize("pair, problem", [
    ("orientation_deg", "KEY=VALUE"),
    ("gravity_up=0,0", "gravity_up_world"),
    ("sensor_to_object=1,2,3,4,5,6,7,8,9", "not a rotation"),
    ("sensor_to_object=xyz_deg:90", "sensor_to_object"),
    ("prompt=circle:3", "prompt"),
    ("prompt_box=1,2,3", "prompt_box"),
])
def test_bad_meta_is_one_line_and_writes_nothing(tmp_path, capsys, pair, problem):
    bag, _ = lab_bag(tmp_path)
    out = tmp_path / "rec.mcap"
    code = main(["convert", str(bag), str(out), "--quiet", "--left-topic", "/lab/cam/left", "--right-topic",
                 "/lab/cam/right", "--meta", pair])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and problem in err, err
    assert not out.exists()


def test_manifest_entries_carry_conversion_keys(tmp_path):
    path = tmp_path / "m.manifest.yaml"
    path.write_text(yaml.safe_dump({"recordings": [
        {"id": "a", "split": "train", "raw": "a.bag", "orientation_deg": 30, "prompt": "box:1,2,30,40",
         "gravity_up": [0, 0, 1], "tissue": "liver", "sensor_to_object": "xyz_deg:0,0,90", "topics": LAB}]}))
    entry = load_manifest(path).entries[0]
    assert entry.topics == LAB
    assert entry.conversion_meta() == {"orientation_deg": 30.0, "gravity_up": [0, 0, 1], "tissue": "liver",
                                       "sensor_to_object": "xyz_deg:0,0,90", "prompt": "box:1,2,30,40"}
    path.write_text(yaml.safe_dump({"recordings": [{"id": "a", "split": "train", "topics": {"camera": "/x"}}]}))
    with pytest.raises(InputError, match="topics"):
        load_manifest(path)


# ---- a simulated dataset as a lab's ROS 2 bags, through `vfdata experiment` --------------------------


def raw_folder_as_bag(raw: Path, bag: Path) -> None:
    """A simulated raw folder (docs/raw_layout.md) written as a ROS 2 bag on the lab's topic names:
    compressed stereo images, the force sensor's WrenchStamped and the ECM PoseStamped; no CameraInfo
    (the calibration file is given to the conversion, as a lab with a calibration.yaml would)."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def header(stamp: int, frame: str):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9,
                                                                               nanosec=stamp % 10**9), frame_id=frame)

    def rows(name: str) -> list[list[str]]:
        with open(raw / name) as handle:
            return list(csv.reader(handle))[1:]

    messages = []
    for frame, stamp in rows("frames.csv"):
        for side in ("left", "right"):
            data = np.frombuffer((raw / side / f"{int(frame):06d}.jpg").read_bytes(), dtype=np.uint8)
            messages.append((int(stamp), LAB[side], T["sensor_msgs/msg/CompressedImage"](
                header=header(int(stamp), side), format="jpeg", data=data)))
    vec = T["geometry_msgs/msg/Vector3"]
    for row in rows("force.csv"):
        stamp, w = int(row[0]), [float(v) for v in row[1:]]
        messages.append((stamp, LAB["force"], T["geometry_msgs/msg/WrenchStamped"](
            header=header(stamp, "ati"), wrench=T["geometry_msgs/msg/Wrench"](force=vec(*w[:3]), torque=vec(*w[3:])))))
    for row in rows("ecm_pose.csv"):
        stamp, v = int(row[0]), [float(x) for x in row[1:]]
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=v[0], y=v[1], z=v[2]),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5],
                                                                                         w=v[6]))
        messages.append((stamp, LAB["pose"], T["geometry_msgs/msg/PoseStamped"](header=header(stamp, "ECM_base"),
                                                                                pose=pose)))
    messages.sort(key=lambda m: m[0])
    with Writer2(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for _, topic, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=ts)
        for stamp, topic, msg in messages:
            writer.write(connections[topic], stamp, ts.serialize_cdr(msg, msg.__msgtype__))


@pytest.mark.slow
def test_a_labs_bags_go_to_table_one_with_no_hand_edits(tmp_path):
    """Bags with a lab's own topic names, a manifest naming them as raw: with the keys a bag lacks, and
    `vfdata experiment`: conversion, processing, training, test and Table I, nothing edited by hand."""
    from vfdata.sim import synthesize

    sim = load_manifest(synthesize("mini", tmp_path / "sim", seed=0, progress=False, frames=40))
    lab = tmp_path / "lab"
    lab.mkdir()
    recordings = []
    for e in sim.entries:
        raw_folder_as_bag(e.raw, lab / f"{e.id}_bag")
        meta = yaml.safe_load((e.raw / "meta.yaml").read_text())
        recordings.append({"id": e.id, "split": e.split, "orientation_deg": e.orientation_deg,
                           "raw": f"{e.id}_bag", "calibration": str(e.raw / "calibration.yaml"),
                           "prompt": "box:" + ",".join(str(v) for v in meta["prompt_box"]),
                           "gravity_up": [0, 0, 1], "tissue": "glove", "topics": LAB})
    manifest = lab / "lab.manifest.yaml"
    manifest.write_text(yaml.safe_dump({"name": "lab", "root": ".", "recordings": recordings}))
    assert main(["experiment", str(manifest), "--out", str(tmp_path / "results"), "--variants", "proposed",
                 "--seeds", "1", "--epochs", "1", "--quiet"]) == 0
    table = (tmp_path / "results" / "table1_force.md").read_text()
    assert "Proposed" in table
    test = Recording.open(lab / "mini_002.mcap").metadata
    assert test.orientation_deg == 90.0 and test.tissue == "glove" and "gravity_up_assumed" not in test.extra
    assert json.loads(Recording.open(lab / "mini_002.processed.mcap").metadata_records[layout.DERIVED_METADATA][
        "up_known"]) is True
