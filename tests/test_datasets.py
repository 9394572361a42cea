"""ForceClipDataset / ForceDataModule on small MCAPs written here with the recording layer: the clip
cutter at recording ends and across gaps, features and frames, force interpolation, the disk cache,
DataLoader workers, and clear errors for bad manifests."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from clip_fixtures import single_thread  # noqa: F401 - autouse fixture
from torch.utils.data import DataLoader

from vfdata.clips.datamodule import ForceDataModule
from vfdata.clips.dataset import ForceClipDataset, collate_clips
from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import clip_starts, point_features, segments, tilt_about, tilt_tokens, velocities
from vfdata.confidence import Confidence
from vfdata.errors import InputError, VisionForceError
from vfdata.manifest import load_manifest
from vfdata.recording import McapWriter, layout
from vfdata.recording.messages import PointCloud2, WrenchStamped

PERIOD = 33_333_333  # ns, 30 frames/s
T0 = 1_700_000_000_000_000_000
ROTATION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # object axes in the camera frame
ORIGIN = np.array([5.0, -3.0, 80.0])  # mm


def frame_times(frames: int, gap_after: int | None = None) -> np.ndarray:
    t = T0 + np.arange(frames, dtype=np.int64) * PERIOD
    if gap_after is not None:
        t[gap_after + 1:] += 10 * PERIOD
    return t


def points_at(t_s: np.ndarray, n: int = 20) -> np.ndarray:
    """(F, n, 3) object-frame mm: a grid at heights 0..n-1 moving along x at 6 mm/s."""
    base = np.stack([np.zeros(n), np.linspace(-5, 5, n), np.arange(n, dtype=float)], axis=1)
    return base[None] + np.array([6.0, 0.0, 0.0])[None, None] * t_s[:, None, None]


def tracks_cloud(points_mm: np.ndarray, visible: np.ndarray, stamp_ns: int) -> PointCloud2:
    """A /tracking/points message as files before derived_version 2 hold it (object frame, mm)."""
    array = np.zeros(len(points_mm), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("visible", "u1")])
    for k, axis in enumerate("xyz"):
        array[axis] = points_mm[:, k]
    array["visible"] = visible
    return PointCloud2(stamp_ns, layout.OBJECT_FRAME, array)


def clips(entries, cache_dir=None, **spec) -> ForceClipDataset:
    return ForceClipDataset(entries, ClipSpec(**spec), cache_dir, progress=False)


def write_recording(root: Path, rid: str, times: np.ndarray, tracks: bool = True, hidden: tuple = (),
                    tracker: str | None = None, doubtful: tuple[str, ...] = ()) -> None:
    """<rid>.mcap with a 1 kHz force ramp fx = t (s), fy = 2, fz = -t; <rid>.processed.mcap with tracks
    (and, with `doubtful` reasons, the verdict `vfdata process` writes for them)."""
    t_force = np.arange(times[0] - 5 * PERIOD, times[-1] + 5 * PERIOD, 1_000_000, dtype=np.int64)
    with McapWriter(root / f"{rid}.mcap", separate_topics=(layout.WRENCH,)) as w:
        for t in t_force:
            s = (t - T0) / 1e9
            w.write(layout.WRENCH, WrenchStamped(int(t), layout.SENSOR_FRAME, (s, 2.0, -s), (0.0, 0.0, 0.0)))
    with McapWriter(root / f"{rid}.processed.mcap") as w:
        if tracks:
            pts = points_at((times - T0) / 1e9)
            for i, t in enumerate(times):
                visible = np.ones(len(pts[i]), bool)
                for frame, point in hidden:
                    if frame == i:
                        visible[point] = False
                w.write(layout.TRACKING_POINTS, tracks_cloud(pts[i], visible, int(t)))
        frame = {"rotation": ROTATION.tolist(), "origin": ORIGIN.tolist()}
        names = {"tracker": tracker} if tracker else {}
        if doubtful:
            names.update(Confidence(list(doubtful)).metadata())
        w.add_metadata(layout.DERIVED_METADATA, {"object_frame": json.dumps(frame), **names})


def write_manifest(root: Path, recordings: list[dict]) -> Path:
    path = root / "test.manifest.yaml"
    path.write_text(yaml.safe_dump({"name": "test", "root": ".", "recordings": recordings}))
    return path


@pytest.fixture
def dataset_root(tmp_path):
    write_recording(tmp_path, "a", frame_times(40, gap_after=19), hidden=((5, 3),))
    write_recording(tmp_path, "b", frame_times(23))
    write_recording(tmp_path, "c", frame_times(18))
    manifest = write_manifest(tmp_path, [
        {"id": "a", "orientation_deg": 0, "split": "train"},
        {"id": "b", "orientation_deg": 0, "split": "val"},
        {"id": "c", "orientation_deg": 45, "split": "test"},
    ])
    return tmp_path, manifest


# ---- pure functions ------------------------------------------------------------------------------


def test_segments_split_at_gaps():
    assert segments(frame_times(40, gap_after=19)) == [(0, 20), (20, 40)]
    assert segments(frame_times(5)) == [(0, 5)]
    assert segments(np.array([], dtype=np.int64)) == []


def test_clip_starts_cover_the_ends_and_skip_short_runs():
    # 23 frames, T 16, stride 4: 0, 4, then one ending on the last frame (7)
    assert clip_starts([(0, 23)], 16, 4).tolist() == [0, 4, 7]
    assert clip_starts([(0, 24)], 16, 4).tolist() == [0, 4, 8]
    assert clip_starts([(0, 16)], 16, 4).tolist() == [0]
    assert clip_starts([(0, 15)], 16, 4).tolist() == []
    # never across a gap: runs 0-19 and 20-39
    assert clip_starts([(0, 20), (20, 40)], 16, 4).tolist() == [0, 4, 20, 24]


def test_velocities_central_one_sided_at_ends_and_gaps():
    p = np.array([0.0, 1.0, 4.0, 9.0, 100.0, 101.0])[:, None, None] * np.ones((1, 1, 3))
    v = velocities(p, [(0, 4), (4, 6)], fps=2.0)[:, 0, 0]
    # central: fps/2 (p[t+1] - p[t-1]); ends one-sided; the jump 9 -> 100 is a gap, never differenced
    np.testing.assert_allclose(v, [2.0, 4.0, 8.0, 10.0, 2.0, 2.0])


# ---- the dataset ---------------------------------------------------------------------------------


def test_clips_force_and_features(dataset_root):
    root, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)
    ds = clips(entries[:1])
    assert len(ds) == 4  # two gap-free runs of 20 frames: starts 0, 4 and 20, 24
    item = ds[2]
    assert item["tokens"].shape == (16, 20, 6) and item["valid"].shape == (16, 20)
    assert item["frame_index"].tolist() == list(range(20, 36))
    assert item["recording"] == "a" and float(item["orientation_deg"]) == 0.0
    # force interpolated from the 1 kHz ramp at each frame time
    t_s = (item["frame_time_ns"].numpy() - T0) / 1e9
    np.testing.assert_allclose(item["force"].numpy(), np.stack([t_s, np.full_like(t_s, 2), -t_s], 1), atol=1e-5)
    # positions in the object frame; velocity 6 mm/s along x everywhere (also at the run's ends)
    np.testing.assert_allclose(item["tokens"][..., :3].numpy(), points_at(t_s), atol=1e-4)
    ok = item["valid"].numpy()
    np.testing.assert_allclose(item["tokens"][..., 3].numpy()[ok], 6.0, atol=1e-2)
    np.testing.assert_allclose(item["tokens"][..., 4:].numpy()[ok], 0.0, atol=1e-2)


def test_canonical_side_mirrors_a_recording_seen_from_its_other_flank(tmp_path):
    """With canonical_side, a recording whose first frame shows only its y < 0 points is mirrored: the
    y and vy of its tokens and its Fy negated, `side` -1; one showing its y > 0 points is unchanged."""
    times = frame_times(20)
    write_recording(tmp_path, "neg", times, hidden=tuple((0, i) for i in range(10, 20)))  # y > 0 hidden
    write_recording(tmp_path, "pos", times, hidden=tuple((0, i) for i in range(10)))
    manifest = write_manifest(tmp_path, [{"id": "neg", "orientation_deg": 180, "split": "test"},
                                         {"id": "pos", "orientation_deg": 0, "split": "test"}])
    entries = list(load_manifest(manifest).entries)
    plain = clips(entries)
    mirrored = clips(entries, canonical_side=True)
    flip = torch.tensor([1.0, -1.0, 1.0, 1.0, -1.0, 1.0])
    neg, pos = 0, 2  # first clips of each recording (starts 0 and 4 in each)
    assert float(mirrored[neg]["side"]) == -1.0 and float(plain[neg]["side"]) == 1.0
    torch.testing.assert_close(mirrored[neg]["tokens"], plain[neg]["tokens"] * flip)
    torch.testing.assert_close(mirrored[neg]["force"], plain[neg]["force"] * flip[:3])
    assert float(mirrored[pos]["side"]) == 1.0
    torch.testing.assert_close(mirrored[pos]["tokens"], plain[pos]["tokens"])
    with pytest.raises(VisionForceError, match="object frame"):
        clips(entries, frame="camera", canonical_side=True)
    for _ in range(2):  # written to the cache, then read from it
        cached = clips(entries, canonical_side=True, cache_dir=tmp_path / "cache")
        assert float(cached[neg]["side"]) == -1.0
        torch.testing.assert_close(cached[neg]["force"], mirrored[neg]["force"])
    # Predictions are turned back to the sensor's Fy: a "model" that predicts the (mirrored) training
    # target exactly gives the sensor's force as both prediction and truth.
    from types import SimpleNamespace

    from vfmodels.training.prediction_writer import PredictionCollector
    from vfmodels.training.regressor import ForceRegressor

    collector = PredictionCollector()
    trainer = SimpleNamespace(world_size=1, is_global_zero=True)
    loader = torch.utils.data.DataLoader(mirrored, batch_size=4, collate_fn=collate_clips)
    for batch in loader:
        sensor = ForceRegressor.unmirror(batch["force"], batch)
        collector.write_on_batch_end(trainer, None, {"force_n": sensor, "true_n": sensor,
                                                     "recording": batch["recording"],
                                                     "frame_time_ns": batch["frame_time_ns"],
                                                     "orientation_deg": batch["orientation_deg"]}, None, batch, 0)
    collector.on_predict_end(trainer, None)
    predictions = collector.frames
    assert float(mirrored[neg]["force"][0, 1]) == -2.0  # the fixture's sensor Fy is 2 N throughout
    assert len(predictions["true"]) == 40  # every frame of both recordings once
    np.testing.assert_allclose(predictions["true"][:, 1], 2.0)


def test_hidden_point_is_invalid_with_its_velocity_neighbours(dataset_root):
    _, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)
    item = clips(entries[:1])[0]
    valid = item["valid"].numpy()
    assert not valid[5, 3] and not valid[4, 3] and not valid[6, 3]  # hidden at 5; 4 and 6 difference it
    assert valid[3, 3] and valid[7, 3] and valid[5, 2]
    assert (item["tokens"][5, 3] == 0).all()
    # positions alone only lose the hidden sample
    pos = clips(entries[:1], features="pos")[0]
    assert pos["tokens"].shape[-1] == 3 and not pos["valid"][5, 3] and pos["valid"][4, 3]


def test_camera_frame_and_top_bottom(dataset_root):
    _, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)
    obj = clips(entries[:1], features="pos")[0]
    cam = clips(entries[:1], features="pos", frame="camera")[0]
    ok = obj["valid"].numpy()
    np.testing.assert_allclose(cam["tokens"].numpy()[ok], obj["tokens"].numpy()[ok] @ ROTATION.T + ORIGIN, atol=1e-4)
    assert (cam["tokens"].numpy()[~ok] == 0).all()
    tb = clips(entries[:1], features="pos", subset="top_bottom_20")[0]["tokens"]
    assert tb.shape == (16, 8, 3)  # 20% of 20 points at each end by z (heights 0..19)
    assert sorted(tb[0, :, 2].tolist()) == [0, 1, 2, 3, 16, 17, 18, 19]


def test_disk_cache_skips_decoding(dataset_root):
    root, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)
    cache = root / "cache"
    first = clips(entries[:1], cache_dir=cache)
    assert len(list(cache.glob("a-*.npz"))) == 1
    # Spoil the MCAPs but keep their size and time stamp: only a cache hit can still load them.
    for name in ("a.mcap", "a.processed.mcap"):
        path = root / name
        stat = path.stat()
        path.write_bytes(b"\0" * stat.st_size)
        os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    second = clips(entries[:1], cache_dir=cache)
    torch.testing.assert_close(first[3]["tokens"], second[3]["tokens"])
    with pytest.raises(Exception):  # noqa: B017 - without the cache the spoiled file is read
        clips(entries[:1])


def test_loader_with_workers(dataset_root):
    _, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)
    ds = clips(entries[:1])
    batches = list(DataLoader(ds, batch_size=3, num_workers=2, collate_fn=collate_clips))
    assert [len(b["recording"]) for b in batches] == [3, 1]
    assert batches[0]["tokens"].shape == (3, 16, 20, 6) and batches[0]["frame_time_ns"].dtype == torch.int64


def test_datamodule_splits_and_training_statistics(dataset_root):
    _, manifest = dataset_root
    dm = ForceDataModule(str(manifest), batch_size=2, progress=False)
    dm.setup("fit")
    dm.setup("test")
    assert len(dm.datasets["train"]) == 4 and len(dm.datasets["val"]) == 3 and len(dm.datasets["test"]) == 2
    train_force = np.concatenate([d.force_n for d in dm.datasets["train"].recordings])
    np.testing.assert_allclose(dm.normalisation["force_mean"].numpy(), train_force.mean(0), rtol=1e-5, atol=1e-6)
    assert dm.spec.fps == pytest.approx(30.0, rel=1e-3)
    batch = next(iter(dm.test_dataloader()))
    assert batch["recording"] == ["c", "c"] and batch["orientation_deg"].tolist() == [45.0, 45.0]


# ---- errors --------------------------------------------------------------------------------------


def test_manifest_naming_a_missing_recording(tmp_path):
    write_recording(tmp_path, "a", frame_times(20))
    manifest = write_manifest(tmp_path, [{"id": "a", "split": "train"}, {"id": "ghost", "split": "val"}])
    dm = ForceDataModule(str(manifest), progress=False)
    with pytest.raises(InputError, match="ghost.processed.mcap: derived recording not found"):
        dm.setup("fit")


def test_recording_without_tracks(tmp_path):
    write_recording(tmp_path, "a", frame_times(20), tracks=False)
    manifest = write_manifest(tmp_path, [{"id": "a", "split": "train"}])
    entries = list(load_manifest(manifest).entries)
    with pytest.raises(InputError, match="no tracks"):
        clips(entries)


def test_bad_manifests(tmp_path):
    with pytest.raises(InputError, match="manifest not found"):
        load_manifest(tmp_path / "none.yaml")
    bad = write_manifest(tmp_path, [{"id": "a", "split": "holdout"}])
    with pytest.raises(InputError, match="needs an id and a split"):
        load_manifest(bad)
    with pytest.raises(VisionForceError, match="features"):
        ClipSpec(features="acceleration")
    with pytest.raises(TypeError, match="from_manifest"):
        ForceClipDataset("x.manifest.yaml")


def test_ground_truth_source(tmp_path):
    raw = tmp_path / "g"
    (raw / "ground_truth").mkdir(parents=True)
    times = frame_times(20)
    (raw / "frames.csv").write_text("frame,timestamp_ns\n" + "".join(f"{i},{t}\n" for i, t in enumerate(times)))
    obj = points_at((times - T0) / 1e9, n=30)
    np.save(raw / "ground_truth" / "points.npy", (obj @ ROTATION.T + ORIGIN).astype(np.float32))
    np.save(raw / "ground_truth" / "force.npy", np.tile([1.0, 2.0, 3.0], (20, 1)).astype(np.float32))
    (raw / "ground_truth" / "object_frame.json").write_text(
        json.dumps({"rotation": ROTATION.tolist(), "origin_mm": ORIGIN.tolist()}))
    entries = list(load_manifest(write_manifest(tmp_path, [{"id": "g", "split": "train"}])).entries)
    ds = clips(entries, source="ground_truth", num_points=10)
    item = ds[0]
    assert item["tokens"].shape == (16, 10, 6)
    np.testing.assert_allclose(item["tokens"][..., 3].numpy(), 6.0, atol=1e-2)  # object-frame x velocity
    np.testing.assert_allclose(item["force"].numpy(), np.tile([1.0, 2.0, 3.0], (16, 1)))
    cloud = clips(entries, source="ground_truth", input="cloud", cloud_points=50)[0]
    assert cloud["tokens"].shape == (16, 50, 3) and cloud["valid"].all()


def test_rgb_clips_need_only_the_recording(tmp_path):
    from rawfixtures import make_raw

    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder

    convert_raw_folder(make_raw(tmp_path / "raw", n=20), tmp_path / "a.mcap", options=ConvertOptions(progress=False))
    manifest = write_manifest(tmp_path, [{"id": "a", "split": "train"}])  # no a.processed.mcap
    entries = list(load_manifest(manifest).entries)
    rgb = clips(entries, input="rgb", image_size=32, clip_frames=8)
    clip = rgb[0]
    assert clip["images"].shape == (8, 3, 32, 32) and clip["force"].shape == (8, 3)


def test_mirror_augmentation_flips_training_clips_only(dataset_root):
    _, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)[:1]
    spec = ClipSpec(features="disp_vel", mirror_augment=True)
    plain = ForceClipDataset(entries, spec, progress=False)
    torch.manual_seed(0)
    augmented = ForceClipDataset(entries, spec, progress=False, augment=True)
    sides = []
    for _ in range(20):
        item, reference = augmented[1], plain[1]
        side = float(item["side"])
        sides.append(side)
        torch.testing.assert_close(item["tokens"][..., 1::3], side * reference["tokens"][..., 1::3])
        torch.testing.assert_close(item["tokens"][..., 0::3], reference["tokens"][..., 0::3])
        torch.testing.assert_close(item["force"][:, 1], side * reference["force"][:, 1])
    assert set(sides) == {1.0, -1.0}
    assert all(float(plain[1]["side"]) == 1.0 for _ in range(5))  # without augment: never mirrored
    dm = ForceDataModule(str(manifest), spec=spec, progress=False)
    dm.setup("fit")
    assert dm.datasets["train"].augment and not dm.datasets["val"].augment


def test_tilted_tokens_are_those_of_the_points_in_the_tilted_frame():
    # the same points expressed in a frame tilted about the tissue's free end: the tokens recomputed
    # from them and the tokens tilted after the fact agree (the place along Z to within the shift of
    # the 98th-percentile tip, which is recomputed on the tilted points)
    rng = np.random.default_rng(0)
    th, z = rng.uniform(0, 2 * np.pi, 60), rng.uniform(0, 60, 60)
    start = np.stack([10 * np.cos(th), 10 * np.sin(th), z], axis=-1)
    points = np.stack([start + k * 0.3 * rng.normal(size=start.shape) for k in range(6)])
    valid, runs = np.ones(points.shape[:2], bool), [(0, 6)]
    rotation = tilt_about(0.7, np.radians(6.0))
    tip = np.array([0.0, 0.0, np.percentile(z, 98)])
    tokens, _ = point_features(points, valid, runs, 30.0, "polar_z_disp_vel")
    expected, _ = point_features((points - tip) @ rotation + tip, valid, runs, 30.0, "polar_z_disp_vel")
    tilted = tilt_tokens(tokens, "polar_z_disp_vel", rotation)
    np.testing.assert_allclose(np.delete(tilted, 5, axis=-1), np.delete(expected, 5, axis=-1), atol=1e-4)
    np.testing.assert_allclose(tilted[..., 5], expected[..., 5], atol=1.0)
    assert np.abs(tilted - tokens).max() > 1.0  # a 6 degree tilt moves the far points by mm
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.degrees(np.arccos(rotation[2, 2])), 6.0)
    zero = np.zeros((2, 12), np.float32)
    assert not tilt_tokens(zero, "polar_z_disp_vel", rotation).any()  # invalid points stay zero
    with pytest.raises(VisionForceError, match="cannot be tilted"):
        tilt_tokens(tokens, "polar_disp_vel", rotation)
    with pytest.raises(VisionForceError, match="tilt_augment_deg"):
        ClipSpec(features="polar_disp_vel", tilt_augment_deg=5.0)


def test_tilt_augmentation_moves_training_tokens_not_the_force(dataset_root):
    _, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)[:1]
    spec = ClipSpec(features="polar_z_disp_vel", tilt_augment_deg=10.0)
    plain = ForceClipDataset(entries, spec, progress=False)
    torch.manual_seed(0)
    augmented = ForceClipDataset(entries, spec, progress=False, augment=True)
    item, reference = augmented[1], plain[1]
    torch.testing.assert_close(item["force"], reference["force"])
    assert not torch.allclose(item["tokens"], reference["tokens"])
    # displacements keep their length under a rotation
    torch.testing.assert_close(item["tokens"][..., 6:9].norm(dim=-1), reference["tokens"][..., 6:9].norm(dim=-1),
                               atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(ForceClipDataset(entries, spec, progress=False)[1]["tokens"], reference["tokens"])


def test_rotation_augmentation_turns_tokens_and_force_together(dataset_root):
    """Each training clip is turned about the object's Z axis by a random angle: every token 3-vector
    and the force by the same rotation (z kept), so norms in the XY plane and z are unchanged, and the
    turned force follows the turned displacement; statistics have zero x/y means and one x/y spread."""
    _, manifest = dataset_root
    entries = list(load_manifest(manifest).entries)[:1]
    spec = ClipSpec(features="polar_disp_vel", rotate_augment=True)
    plain = ForceClipDataset(entries, spec, progress=False)
    torch.manual_seed(0)
    augmented = ForceClipDataset(entries, spec, progress=False, augment=True)
    angles = []
    for _ in range(10):
        item, reference = augmented[1], plain[1]
        xy, xy_ref = item["tokens"].reshape(16, -1, 3, 3), reference["tokens"].reshape(16, -1, 3, 3)
        torch.testing.assert_close(xy[..., 2], xy_ref[..., 2])
        torch.testing.assert_close(xy[..., :2].norm(dim=-1), xy_ref[..., :2].norm(dim=-1), atol=1e-4, rtol=1e-4)
        # the angle of the rotation, read off the force, turns the reference force into the item's
        f, f_ref = item["force"][0, :2], reference["force"][0, :2]
        angle = float(torch.atan2(f[1], f[0]) - torch.atan2(f_ref[1], f_ref[0]))
        c, s = np.cos(angle), np.sin(angle)
        turned = reference["tokens"].reshape(16, -1, 3, 3)[..., :2] @ torch.tensor([[c, s], [-s, c]],
                                                                                  dtype=torch.float32)
        torch.testing.assert_close(xy[..., :2], turned, atol=1e-3, rtol=1e-3)
        angles.append(angle % (2 * np.pi))
    assert np.ptp(angles) > 1.0  # not one fixed turn
    stats = augmented.normalisation()
    assert torch.all(stats["input_mean"][0::3] == 0) and torch.all(stats["input_mean"][1::3] == 0)
    torch.testing.assert_close(stats["input_std"][0::3], stats["input_std"][1::3])
    assert float(stats["force_mean"][0]) == 0.0 and float(stats["force_mean"][1]) == 0.0
    assert not torch.all(plain.normalisation()["input_mean"][1::3] == 0)  # plain statistics without augment


def test_polar_features_place_each_point_around_the_axis():
    from vfdata.clips.tokens import point_features

    ref = np.array([[10.0, 0.0, 5.0], [0.0, -20.0, 7.0]])
    points = np.stack([ref, ref + [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]]])
    tokens, ok = point_features(points, np.ones((2, 2), bool), [(0, 2)], 30.0, "polar_disp_vel")
    assert tokens.shape == (2, 2, 9) and ok.all()
    np.testing.assert_allclose(tokens[1, 0, :3], [1.0, 0.0, 10.0], atol=1e-6)  # th0 = 0 (up), r0 = 10 mm
    np.testing.assert_allclose(tokens[1, 1, :3], [0.0, -1.0, 20.0], atol=1e-6)  # th0 = -90 deg
    np.testing.assert_allclose(tokens[1, 0, 3:6], [1.0, 2.0, 3.0], atol=1e-6)  # displacement, mm


def test_polar_z_counts_the_place_along_z_from_the_tip_whatever_the_origin():
    from vfdata.clips.tokens import point_features, transform_tokens, turn_about_z

    rng = np.random.default_rng(3)
    ref = np.column_stack([rng.normal(0, 8, 40), rng.normal(0, 8, 40), rng.uniform(0, 60, 40)])
    points = np.stack([ref, ref + rng.normal(0, 1, ref.shape)])
    visible = np.ones((2, 40), bool)
    visible[:, 5] = False  # never seen: no place, no token
    tokens, ok = point_features(points, visible, [(0, 2)], 30.0, "polar_z_disp_vel")
    assert tokens.shape == (2, 40, 12) and not ok[:, 5].any()
    along = tokens[0, :, 3:6]
    seen = np.arange(40) != 5
    tip = np.percentile(ref[seen, 2], 98)
    np.testing.assert_allclose(along[seen, 2], ref[seen, 2] - tip, atol=1e-4)
    assert np.abs(along[:, :2]).max() == 0.0
    # An origin 20 mm further along Z (a view that cut the clamped end off) changes no token.
    shifted, _ = point_features(points + [0.0, 0.0, 20.0], visible, [(0, 2)], 30.0, "polar_z_disp_vel")
    np.testing.assert_allclose(shifted, tokens, atol=1e-4)
    # The tube's symmetries act on it as on every other channel: the tokens of turned and mirrored
    # points are the turned and mirrored tokens.
    m = turn_about_z(0.7, mirror=True)
    moved, _ = point_features(points @ m.T, visible, [(0, 2)], 30.0, "polar_z_disp_vel")
    np.testing.assert_allclose(moved[:, seen], transform_tokens(tokens, m)[:, seen], atol=1e-4)


def test_radius_tissue_gives_r0_in_tissue_radii_whatever_the_axis_offset():
    """A tube whose axis was set off its centre looks wider about it: in mm every r0 grows (what a model
    trained at one view read as force); in tissue radii the points on the surface stay near 1, and a
    few points off the tissue do not move the scale."""
    from vfdata.clips.tokens import track_tokens

    rng = np.random.default_rng(5)
    theta = rng.uniform(-1.2, 1.2, 60)  # the flank the camera sees
    ref = np.column_stack([12.0 * np.cos(theta), 12.0 * np.sin(theta), rng.uniform(-100, 0, 60)])
    ref[:4, :2] *= 2.5  # off the tissue: the bed beside it
    points = np.stack([ref, ref + [0.0, 0.0, 0.5], ref + [0.0, 0.0, 1.0]])
    visible = np.ones((3, 60), bool)
    spec = ClipSpec(features="polar_z_disp_vel", radius="tissue")
    tokens, valid, _ = track_tokens(spec, points, visible)
    np.testing.assert_allclose(tokens[1, 4:, 2], 1.0, atol=1e-5)
    np.testing.assert_allclose(tokens[1, :4, 2], 2.5, atol=1e-5)
    in_mm, _, _ = track_tokens(ClipSpec(features="polar_z_disp_vel"), points, visible)
    np.testing.assert_allclose(in_mm[1, 4:, 2], 12.0, atol=1e-4)
    np.testing.assert_array_equal(np.delete(tokens, 2, axis=-1), np.delete(in_mm, 2, axis=-1))
    # The same tube about an axis 1.5 times its radius away from where the view sees it scales every
    # r0 in mm, and none in tissue radii.
    wide = points * [1.5, 1.5, 1.0]
    assert np.median(track_tokens(ClipSpec(features="polar_z_disp_vel"), wide, visible)[0][1, :, 2]) > 17.9
    np.testing.assert_allclose(track_tokens(spec, wide, visible)[0][..., 2], tokens[..., 2], atol=1e-5)


@pytest.mark.parametrize("options", [dict(features="disp_vel"), dict(features="polar_z_disp_vel", frame="camera"),
                                     dict(features="polar_z_disp_vel", tilt_augment_deg=5.0)])
def test_radius_tissue_is_refused_where_r0_is_not_polar_in_the_object_frame(options):
    with pytest.raises(VisionForceError, match="radius 'tissue'"):
        ClipSpec(radius="tissue", **options)


def test_the_one_line_ways_in_and_denormalise(dataset_root):
    """from_manifest for the dataset and the data module; a network's output to N with the training
    split's statistics, as ForceRegressor does it."""
    import vfdata
    from vfmodels import ForceRegressor, SetTransformerLSTM

    _, manifest = dataset_root
    train = vfdata.ForceClipDataset.from_manifest(manifest, split="train", progress=False)
    assert {e.split for e in train.entries} == {"train"}
    assert [e.id for e in train.entries] == [e.id for e in vfdata.load_manifest(manifest).split("train")]
    module = vfdata.ForceDataModule.from_manifest(manifest, batch_size=2, progress=False)
    module.setup("fit")
    with pytest.raises(TypeError):
        vfdata.ForceDataModule(vfdata.load_manifest(manifest))
    stats = module.normalisation
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6))
    regressor.set_normalisation(**stats)
    regressor.eval()
    batch = next(iter(module.train_dataloader()))
    with torch.no_grad():
        out = regressor.model(vfdata.normalise_input(batch["tokens"], stats), batch.get("valid"))
        torch.testing.assert_close(vfdata.denormalise_force(out, stats), regressor.denormalise_force(out))
        torch.testing.assert_close(vfdata.denormalise_force(vfdata.normalise_force(batch["force"], stats), stats),
                                   batch["force"], equal_nan=True)
        torch.testing.assert_close(vfdata.normalise_input(batch["tokens"], stats),
                                   regressor.normalise_input(batch["tokens"]))


def test_a_checkpoint_remembers_the_tracker_of_the_training_recordings(tmp_path):
    """The data module's state (Lightning saves it in every checkpoint) names the tracker of the training
    recordings' derived files, so prediction can track the same way (nothing when they do not say), and
    the recordings trained and validated on, and those of them judged doubtful (`vfdata model-info`)."""
    write_recording(tmp_path, "a", frame_times(40), tracker="klt")
    write_recording(tmp_path, "b", frame_times(23), tracker="geometry")
    write_recording(tmp_path, "c", frame_times(18))
    manifest = write_manifest(tmp_path, [
        {"id": "a", "orientation_deg": 0, "split": "train"},
        {"id": "b", "orientation_deg": 0, "split": "val"},
        {"id": "c", "orientation_deg": 45, "split": "test"},
    ])
    assert ForceDataModule.from_manifest(manifest, progress=False).state_dict() == {
        "tracker": "klt", "recordings": {"train": ["a"], "val": ["b"]}}
    shuffled = ForceDataModule.from_manifest(manifest, progress=False, random_split=0.2)
    assert shuffled.state_dict()["recordings"] == {"shuffled": ["a", "b", "c"]}
    write_recording(tmp_path, "d", frame_times(20), tracker="klt", doubtful=("end",))
    judged = write_manifest(tmp_path, [{"id": "a", "orientation_deg": 0, "split": "train"},
                                       {"id": "d", "orientation_deg": 0, "split": "val"}])
    assert ForceDataModule.from_manifest(judged, progress=False).state_dict()["doubtful"] == {"d": ["end"]}
    unnamed = write_manifest(tmp_path, [{"id": "c", "orientation_deg": 0, "split": "train"}])
    assert ForceDataModule.from_manifest(unnamed, progress=False).state_dict() == {
        "recordings": {"train": ["c"], "val": []}}


def test_the_training_lean_leaves_doubtful_tissues_out(tmp_path, monkeypatch):
    """The training tissues' lean (every checkpoint keeps it) is the range of the training recordings that
    `vfdata process` did not doubt: a doubtful one's frame, so its lean, may be wrong."""
    import vfdata.clips.datamodule as datamodule

    leans = {"a": 4.0, "b": 5.0, "c": 6.0, "d": 20.0}
    for rid in leans:
        write_recording(tmp_path, rid, frame_times(20), tracker="klt", doubtful=("axis",) if rid == "d" else ())
    monkeypatch.setattr(datamodule, "recording_lean", lambda meta, frame, mcap: leans[Path(mcap).stem])
    manifest = write_manifest(tmp_path, [{"id": rid, "orientation_deg": 0, "split": "train"} for rid in leans])
    module = ForceDataModule.from_manifest(manifest, progress=False)
    assert module.training_lean_deg == [4.0, 6.0] and module.doubtful_recordings == {"d": ["axis"]}
