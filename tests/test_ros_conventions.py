"""ROS conventions of the files: the ECM pose also on /tf (world -> ecm), byte for byte what a ROS 2
TFMessage of that pose is; a recording without a pose has no /tf."""

from __future__ import annotations

import numpy as np
from rawfixtures import make_raw

from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.recording import Recording, layout
from vfdata.recording.inspect import check_file
from vfdata.recording.messages import TFMessage, TransformStamped, encode_tf_batch


def test_tf_batch_is_what_tfmessage_encodes():
    stamps = np.array([1_700_000_000_123_456_789, 5, 2**31 * 10**9 - 1], np.int64)
    values = np.random.default_rng(0).normal(size=(3, 7))
    table = encode_tf_batch(stamps, "world", "ecm", values)
    for i in range(3):
        message = TFMessage([TransformStamped(int(stamps[i]), "world", "ecm", tuple(values[i, :3]),
                                              tuple(values[i, 3:]))])
        assert bytes(table[i]) == message.encode()


def test_the_ecm_pose_is_on_tf(tmp_path):
    options = ConvertOptions(progress=False)
    out = convert_raw_folder(make_raw(tmp_path / "rec", n=6), tmp_path / "rec.mcap", options=options)
    assert check_file(out) == []
    rec = Recording.open(out)
    pose = rec.ecm_pose
    tf = [message.transforms[0] for _, message in rec.messages(layout.TF)]
    assert len(tf) == len(pose.times_ns)
    assert all(t.frame_id == layout.WORLD_FRAME and t.child_frame_id == layout.ECM_FRAME for t in tf)
    np.testing.assert_array_equal([t.stamp_ns for t in tf], pose.times_ns)
    np.testing.assert_allclose([(*t.translation, *t.rotation) for t in tf],
                               np.concatenate([pose.position_m, pose.quaternion_xyzw], axis=1))
    bare = convert_raw_folder(make_raw(tmp_path / "bare", n=6, pose=False), tmp_path / "bare.mcap",
                              options=ConvertOptions(progress=False))
    assert layout.TF not in Recording.open(bare).topics
