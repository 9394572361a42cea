"""`vfdata live`: a replayed recording served over the Foxglove WebSocket protocol, read by a client of
the protocol (the `websockets` package), against offline `predict` on the same recording and
checkpoint; the --record file; a clean stop; the errors a user can hit."""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import struct
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

pytest.importorskip("foxglove", reason="the live extra (foxglove-sdk) is not installed")
websockets = pytest.importorskip("websockets")

from test_predict import _regressor, _save_checkpoint  # noqa: E402

from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder  # noqa: E402
from vfdata.errors import InputError, OutputError, OutputExistsError  # noqa: E402
from vfdata.foxglove_server import FoxgloveServer  # noqa: E402
from vfdata.recording import Recording, layout  # noqa: E402
from vfdata.recording.derived import (  # noqa: E402
    DerivedRecording,
    read_force_band,
    read_force_estimate,
    read_force_unlike,
)
from vfdata.recording.inspect import check_file  # noqa: E402
from vfdata.recording.messages import WrenchStamped, decode  # noqa: E402
from vfdata.sim import synthesize  # noqa: E402
from vfmodels.commands import live  # noqa: E402
from vfmodels.evaluation.band import BandCalibration  # noqa: E402
from vfmodels.inference import predict  # noqa: E402

FRAMES = 8
SUBPROTOCOL = "foxglove.sdk.v1"


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    synthesize("mini", root, seed=3, frames=FRAMES, workers=1, progress=False)
    return convert_raw_folder(root / "mini_002", root / "mini_002.mcap", options=ConvertOptions(progress=False))


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    """An untrained model with a band calibration (as training leaves it) and a training range around 0 N."""
    regressor = _regressor()
    regressor.band_calibration = BandCalibration((0.2, 0.3, 0.4), (5.0, 5.0, 5.0), (0.5, 0.5, 0.5), 0.9, 300,
                                                 (-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), distance_limit=4.0)
    regressor.embedding_reference = (torch.zeros(32, dtype=torch.float64), torch.eye(32, dtype=torch.float64))
    return _save_checkpoint(regressor, tmp_path_factory.mktemp("ckpt") / "m.ckpt",
                            {"spec": {"input": "tracks", "fps": 30.0}})


def _args(source, ckpt, **extra) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    live.register(parser.add_subparsers())
    argv = ["live", str(source), "--ckpt", str(ckpt), "--port", "0", "--window", "8", "--quiet"]
    for key, value in extra.items():
        flag = "--" + key.replace("_", "-")
        argv += [flag] if value is True else [flag, str(value)]
    return parser.parse_args(argv)


class Client:
    """A Foxglove WebSocket client in a thread: subscribes to `topics`, keeps (topic, log time,
    payload) of every message until the server closes the connection."""

    def __init__(self, url: str, topics: tuple[str, ...], on_message=None):
        self.url, self.topics, self.on_message = url, topics, on_message
        self.messages: list[tuple[str, int, bytes]] = []
        self.advertised: dict[str, dict] = {}
        self.closed_cleanly = False
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self.thread.start()

    async def _run(self) -> None:
        subscriptions: dict[int, str] = {}
        async with websockets.connect(self.url, subprotocols=[SUBPROTOCOL]) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            try:
                async for message in ws:
                    if isinstance(message, str):
                        op = json.loads(message)
                        if op["op"] == "advertise":
                            wanted = []
                            for channel in op["channels"]:
                                self.advertised[channel["topic"]] = channel
                                if channel["topic"] in self.topics:
                                    subscriptions[len(subscriptions) + 1] = channel["topic"]
                                    wanted.append({"id": len(subscriptions), "channelId": channel["id"]})
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": wanted}))
                    elif message[0] == 1:  # message data: opcode, subscription id, log time, payload
                        sub, log_time = struct.unpack_from("<IQ", message, 1)
                        self.messages.append((subscriptions[sub], log_time, bytes(message[13:])))
                        if self.on_message is not None:
                            self.on_message()
                self.closed_cleanly = True
            except websockets.ConnectionClosedOK:
                self.closed_cleanly = True

    def of(self, topic: str) -> list[tuple[int, bytes]]:
        return [(t, p) for name, t, p in self.messages if name == topic]


def _serve(args, topics) -> tuple[int, Client]:
    clients = []
    code = live.run(args, ready=lambda server: clients.append(Client(server.url(), topics)))
    clients[0].thread.join(timeout=10)
    assert not clients[0].thread.is_alive()
    return code, clients[0]


def _port_is_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_live_serves_the_offline_forces_and_records_them(recording, ckpt, tmp_path):
    cv2.setRNGSeed(0)  # the colortrack mask (GrabCut) draws from OpenCV's RNG: the same seed for both runs
    offline = predict.predict_recording(recording, ckpt, tmp_path / "offline", window=8, video=False, progress=False)
    times, forces = read_force_estimate(offline.force_mcap)

    cv2.setRNGSeed(0)
    record = tmp_path / "live.mcap"
    # The whole image's depth, as offline processing (the live default's region of interest: below).
    args = _args(recording, ckpt, record=record, wait_for_client=20, speed=1.0, depth_roi_margin=0)
    code, client = _serve(args, (layout.FORCE_ESTIMATE, layout.TRACKING_POINTS, layout.FORCE_BAND,
                                 layout.FORCE_BEYOND, layout.FORCE_UNLIKE))
    assert code == 0 and client.closed_cleanly
    channel = client.advertised[layout.FORCE_ESTIMATE]
    assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == \
        ("cdr", "geometry_msgs/msg/WrenchStamped", "ros2msg")
    assert set(client.advertised) == set(layout.LIVE_TOPICS)

    received = client.of(layout.FORCE_ESTIMATE)
    assert len(received) == FRAMES
    wrenches = [decode("geometry_msgs/msg/WrenchStamped", payload) for _, payload in received]
    assert all(isinstance(w, WrenchStamped) and w.frame_id == layout.OBJECT_FRAME for w in wrenches)
    np.testing.assert_array_equal([t for t, _ in received], times)
    np.testing.assert_array_equal([w.stamp_ns for w in wrenches], times)
    np.testing.assert_allclose(np.array([w.force for w in wrenches]), forces, rtol=1e-4, atol=1e-4)
    assert len(client.of(layout.TRACKING_POINTS)) == FRAMES
    assert not client.of(layout.LEFT_IMAGE)  # not subscribed: not sent
    # beside each force its band and its distance beyond training, as `vfdata predict` writes them
    _, offline_band, offline_beyond = read_force_band(offline.force_mcap)
    for topic, expected in ((layout.FORCE_BAND, offline_band), (layout.FORCE_BEYOND, offline_beyond)):
        served = [decode("geometry_msgs/msg/WrenchStamped", payload) for _, payload in client.of(topic)]
        np.testing.assert_array_equal([w.stamp_ns for w in served], times)
        np.testing.assert_allclose(np.array([w.force for w in served]), expected, rtol=1e-4, atol=1e-4)
    assert (offline_band >= [0.2, 0.3, 0.4]).all() and (offline_beyond != 0).any()
    # and how unlike training's each frame's input is, a bare number logged at the estimate's stamp
    assert client.advertised[layout.FORCE_UNLIKE]["schemaName"] == "std_msgs/msg/Float64"
    served = client.of(layout.FORCE_UNLIKE)
    np.testing.assert_array_equal([t for t, _ in served], times)
    offline_unlike = read_force_unlike(offline.force_mcap)[1]
    assert np.isfinite(offline_unlike).all() and (offline_unlike > 0).all()
    np.testing.assert_allclose([decode("std_msgs/msg/Float64", p).data for _, p in served], offline_unlike, rtol=1e-4)

    # The recording holds everything served, in the files' layout, and reads as a force file.
    rec_times, rec_forces = read_force_estimate(record)
    np.testing.assert_array_equal(rec_times, times)
    np.testing.assert_array_equal(rec_forces, np.array([w.force for w in wrenches]))
    assert check_file(record) == []  # `vfdata check` knows a live record's topics
    with Recording.open(record) as rec:
        stereo_topics = [t for t in layout.LIVE_TOPICS if t not in (layout.DEPTH_IMAGE, layout.DEPTH_INFO)]  # RGB-D's
        assert {t: info.count for t, info in rec.topics.items()} == dict.fromkeys(stereo_topics, FRAMES)
        _, image = next(rec.messages(layout.LEFT_IMAGE))
        _, info = next(rec.messages(layout.LEFT_INFO))
        assert cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR).shape[:2] == (
            info.height, info.width)
        with Recording.open(recording) as source:
            np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), source.camera.K)
    with DerivedRecording.open(record) as derived:
        assert derived.meta.get("stage") == "live"
        np.testing.assert_allclose(derived.object_frame.origin, read_tracks_origin(offline.processed), atol=1e-9)
    assert not list(tmp_path.glob(".live.mcap*"))
    assert _port_is_free(int(client.url.rsplit(":", 1)[1]))


def read_tracks_origin(processed: Path) -> np.ndarray:
    with DerivedRecording.open(processed) as derived:
        return derived.object_frame.origin


def test_a_stop_ends_the_session_cleanly_and_keeps_what_was_served(recording, ckpt, tmp_path):
    stop = threading.Event()
    args = _args(recording, ckpt, record=tmp_path / "stopped.mcap", wait_for_client=20)
    clients = []

    def ready(server):  # stop once the client has the first force
        clients.append(Client(server.url(), (layout.FORCE_ESTIMATE,), on_message=stop.set))

    assert live.run(args, stop=stop, ready=ready) == 0
    clients[0].thread.join(timeout=10)
    assert clients[0].closed_cleanly
    served = clients[0].of(layout.FORCE_ESTIMATE)
    assert 0 < len(served) < FRAMES
    assert len(read_force_estimate(tmp_path / "stopped.mcap")[0]) == len(served)
    assert not [t for t in threading.enumerate() if t.name.startswith(("vf-replay", "vf-image"))]


def test_live_errors_are_one_line_and_leave_nothing(recording, ckpt, tmp_path):
    with pytest.raises(InputError, match="needs --calibration"):
        live.run(_args("0", ckpt, prompt="box:1,2,3,4"))
    with pytest.raises(InputError, match="--right, --side-by-side"):
        live.run(_args(recording, ckpt, side_by_side=True))
    with pytest.raises(InputError, match="recording not found"):
        live.run(_args(tmp_path / "missing.mcap", ckpt))
    existing = tmp_path / "kept.mcap"
    existing.write_bytes(b"mine")
    with pytest.raises(OutputExistsError):
        live.run(_args(recording, ckpt, record=existing))
    assert existing.read_bytes() == b"mine"
    blocker = FoxgloveServer(port=0)
    try:
        with pytest.raises(OutputError, match="cannot serve"):
            live.run(_args(recording, ckpt, record=tmp_path / "r.mcap", port=blocker.port))
    finally:
        blocker.close()
    assert not list(tmp_path.glob("*r.mcap*"))


def test_a_side_by_side_video_source_gives_rectified_pairs(recording, tmp_path):
    from vfdata.sources import VideoStereo

    with Recording.open(recording) as rec:
        raw = Path(rec.metadata.source)
        pairs = [rec.rectified_frame(i) for i in range(4)]
    left = cv2.imread(str(raw / "left" / "000000.jpg"))
    h, w = left.shape[:2]
    video = tmp_path / "stereo.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (2 * w, h))
    for i in range(4):
        writer.write(np.hstack([cv2.imread(str(raw / side / f"{i:06d}.jpg")) for side in ("left", "right")]))
    writer.release()
    source = VideoStereo(str(video), None, raw / "calibration.yaml", side_by_side=True)
    try:
        frames = list(source)
    finally:
        source.close()
    assert len(frames) + source.dropped == 4 and len(frames) >= 1
    for frame in frames:  # the same rectified views as the recording's, up to the video's compression
        expected = pairs[frame.index]
        assert frame.left.shape == expected.left.shape and frame.right.shape == expected.right.shape
        assert np.abs(frame.left.astype(int) - expected.left.astype(int)).mean() < 6
    with pytest.raises(InputError, match="--side-by-side"):
        VideoStereo(str(video), None, raw / "calibration.yaml")
    with pytest.raises(InputError, match="cannot be opened"):
        VideoStereo(str(tmp_path / "none.avi"), None, raw / "calibration.yaml", side_by_side=True)


def test_depth_roi_is_the_mask_box_grown_and_aligned():
    from vfdata.engine import depth_roi

    mask = np.zeros((100, 200), bool)
    mask[31:60, 81:120] = True
    assert depth_roi(mask, 10, 40) == (20, 70, 70, 130, 30)  # even starts; the match band to the left
    assert depth_roi(mask, 100, 40) == (0, 100, 0, 200, 0)  # clipped to the image
    assert depth_roi(mask, 10, None)[4] == 0  # unknown disparity range: matched from column 0
    assert depth_roi(np.zeros((100, 200), bool), 10, 40) == (0, 100, 0, 200, 0)


def test_the_depth_region_of_interest_keeps_the_tissue_depth(recording):
    from vfdata.engine import EngineOptions, depth_roi
    from vfdata.rig import rig_for

    runs = {}
    with Recording.open(recording) as rec:
        rig = rig_for(rec, recording)
        frames = list(rig.frames(3))
        for margin in (0, 24):
            cv2.setRNGSeed(0)
            engine = rig.engine(EngineOptions(depth_roi_margin_px=margin), rig.prompt(None))
            runs[margin] = [engine.step(i, *f) for i, f in enumerate(frames)]
    whole, roi = runs[0][2], runs[24][2]
    y0, y1, x0, x1, _ = depth_roi(runs[24][1].mask, 24, None)
    outside = np.ones(roi.depth_mm.shape, bool)
    outside[y0:y1, x0:x1] = False
    assert np.isnan(roi.depth_mm[outside]).all() and np.isfinite(roi.depth_mm[~outside]).mean() > 0.99
    tissue = whole.mask & roi.mask
    assert tissue.sum() > 0.95 * whole.mask.sum()
    assert np.nanmedian(np.abs(roi.depth_mm - whole.depth_mm)[tissue]) < 0.2  # mm
    assert np.linalg.norm(roi.points_mm - whole.points_mm, axis=1).mean() < 1.0  # mm


def test_a_replay_at_its_rate_keeps_every_frame_or_skips_like_a_camera(recording):
    import time

    from vfdata.sources import RecordingReplay

    for like_camera in (False, True):
        source = RecordingReplay(recording, speed=1.0, like_camera=like_camera)
        taken, lag = [], []
        try:
            for frame in source:
                taken.append(frame)
                lag.append(time.perf_counter() - frame.arrival_s)  # arrival: when the frame was due
                time.sleep(0.1)  # a consumer at 10 frames/s, slower than the recording's 30
        finally:
            source.close()
        indices = [f.index for f in taken]
        assert indices == sorted(indices) and len(taken) + source.dropped == FRAMES
        if like_camera:
            assert source.dropped > 0 and indices[-1] == FRAMES - 1
        else:
            assert indices == list(range(FRAMES)) and source.dropped == 0
            assert taken[-1].arrival_s - taken[0].arrival_s == pytest.approx((FRAMES - 1) / 30.0, abs=0.02)
            assert min(lag) >= 0 and lag[-1] - lag[1] > 0.3  # falling behind, ~67 ms a frame: it shows


def test_the_foxglove_layout_in_docs_is_the_generated_one_and_names_served_topics():
    import re

    from vfdata.foxglove_layout import layout_json

    docs = Path(__file__).resolve().parents[1] / "docs"
    for name, rgbd in (("foxglove_layout.json", False), ("foxglove_layout_rgbd.json", True)):
        text = (docs / name).read_text()
        # regenerate: python -m vfdata.foxglove_layout [--rgbd] > docs/foxglove_layout[_rgbd].json
        assert text == layout_json(rgbd), name
        named = set(re.findall(r'"(/[a-z_/]+)', text))
        assert named and {t.split(".")[0] for t in named} <= set(layout.LIVE_TOPICS)
        assert (layout.DEPTH_IMAGE in named) == rgbd and (layout.LEFT_IMAGE in named) != rgbd


def test_velocities_of_a_stream_that_skips_frames_stay_per_second():
    """Every second frame pushed (a camera the estimator could not keep up with): the model at 30
    frames/s gives what it gives on the same pushes at 15 frames/s, the rate they really came at."""
    from test_predict import _tracks

    from vfdata.clips.spec import ClipSpec
    from vfmodels.inference.live import StreamingForceModel, skipped_frame_rate

    assert skipped_frame_rate(30.0, np.array([0, 33_333_333, 66_666_667])) == 30.0
    assert skipped_frame_rate(30.0, np.array([0, 36_000_000, 70_000_000])) == 30.0  # jitter
    assert skipped_frame_rate(30.0, np.array([0, 100_000_000, 200_000_000])) == 10.0
    reg = _regressor(1)
    points, visible = _tracks(frames=24)
    stamps = np.arange(24) * 33_333_333
    results = {}
    for fps in (30.0, 15.0):
        stream = StreamingForceModel(reg, ClipSpec(fps=fps), np.eye(3), np.zeros(3), window=8)
        out = [stream.push(s, p, v) for s, p, v in zip(stamps[::2], points[::2], visible[::2], strict=True)]
        results[fps] = np.stack([r[1] for r in out[1:]] + [stream.flush()[1]])
    np.testing.assert_allclose(results[30.0], results[15.0], rtol=1e-6, atol=1e-7)


def test_live_on_an_rgbd_recording_serves_its_depth_and_the_offline_forces(ckpt, tmp_path):
    """An RGB-D recording replays as a live source: the sensor's depth replaces matching, the board
    frame and the plane mask are used as offline, and the depth camera's image is what is served."""
    from tests.rgbd_fixtures import make_rgbd
    from vfdata.conversion.raw_rgbd import convert_rgbd_folder
    from vfdata.processing import ProcessOptions

    src = make_rgbd(tmp_path / "rec", n=FRAMES, holes=False)
    recording = convert_rgbd_folder(src, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    offline = predict.predict_recording(recording, ckpt, tmp_path / "offline", ProcessOptions(tracker="geometry"),
                                        window=8, video=False, progress=False)
    times, forces = read_force_estimate(offline.force_mcap)
    record = tmp_path / "live.mcap"
    code, client = _serve(_args(recording, ckpt, record=record, wait_for_client=20, speed=0),
                          (layout.FORCE_ESTIMATE, layout.DEPTH_IMAGE))
    assert code == 0 and client.closed_cleanly
    wrenches = [decode("geometry_msgs/msg/WrenchStamped", p) for _, p in client.of(layout.FORCE_ESTIMATE)]
    np.testing.assert_array_equal([w.stamp_ns for w in wrenches], times)
    np.testing.assert_allclose(np.array([w.force for w in wrenches]), forces, rtol=1e-4, atol=1e-4)
    assert len(client.of(layout.DEPTH_IMAGE)) == FRAMES
    assert check_file(record) == []  # `vfdata check` knows a live record's topics
    with Recording.open(record) as rec:
        assert not rec.has(layout.LEFT_IMAGE)
        _, depth = next(rec.messages(layout.DEPTH_IMAGE))
        _, tf = next(rec.messages(layout.TF))
        meta = rec.metadata_records[layout.DERIVED_METADATA]
    assert (depth.encoding, depth.frame_id) == ("16UC1", layout.DEPTH_FRAME)  # mm, REP 118
    assert tf.transforms[0].frame_id == layout.DEPTH_FRAME
    assert meta["object_frame_kind"] == "board_plane" and meta["x_axis"].startswith("the image's right")
