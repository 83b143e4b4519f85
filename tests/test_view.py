"""``egosim view``: a run's clip as a Foxglove MCAP, read back with ``mcap`` + the Foxglove schemas.

One tiny dataset run (synthetic world, 48x64, 9 frames, every step of ``workflows/dataset.yaml``)
is exported; the file is read back and compared with the shards it came from: every topic and
schema, message times against the clip's timestamps, transforms against the poses, calibration
against the intrinsics minus the 0.5 pixel-centre offset, clouds against the scene cloud, masks
and the first frame exactly, the 3D skeleton against the hand joints.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from typer.testing import CliRunner

from egosim.pipeline import media
from egosim.pipeline.cli import EXIT_USER_ERROR, app
from egosim.pipeline.clip_io import clip_from_row
from egosim.pipeline.export import foxglove as fx
from egosim.pipeline.export.run_index import ExportError, RunIndex
from egosim.pipeline.export.view import ViewConfig, write_run_view
from egosim.pipeline.geometry import make_se3, matrix_from_quat, pixel_grid, project_points
from egosim.pipeline.runner import IN_PROCESS, run_workflow
from egosim.pipeline.stage import ConfigError
from egosim.pipeline.workflow import load_workflow
from egosim.schemas import CLIPS, DEPTH_CAMERA, POSES
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER
from egosim.schemas.state import STATE
from egosim.stages.ingest.mcap_source import read_mcap_clip

REPO = Path(__file__).resolve().parents[1]
TINY = ["height=48", "width=64", "num_frames=9", "fps=8", "synthetic_count=1"]
POSE_ATOL = 1e-9  # metres / rotation-matrix entries after a float64 quaternion round trip
MIN_JPEG_PSNR_DB = 30.0  # JPEG q90 of the (already H.264) frames; measured 36-40 dB here
EXPECTED_TOPICS = {
    "/camera/image": "foxglove.CompressedImage",
    "/camera/calibration": "foxglove.CameraCalibration",
    "/tf": "foxglove.FrameTransform",
    "/camera/trajectory": "foxglove.PosesInFrame",
    "/camera_raw/trajectory": "foxglove.PosesInFrame",
    "/scene/image": "foxglove.CompressedImage",
    "/scene/visible": "foxglove.CompressedImage",
    "/hands/skeleton_image": "foxglove.CompressedImage",
    "/hands/mask": "foxglove.CompressedImage",
    "/inpaint/first_frame": "foxglove.CompressedImage",
    "/scene/cloud": "foxglove.PointCloud",
    "/hands/skeleton": "foxglove.SceneUpdate",
}
PER_FRAME = ("/camera/image", "/camera/calibration", "/scene/image", "/scene/visible")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A one-clip dataset run with every step (about 6 s in this process)."""
    overrides = [f"ingest.{kv}" for kv in TINY] + ["pack.frame_stride=1"]
    wf = load_workflow(REPO / "workflows" / "dataset.yaml", overrides)
    out = tmp_path_factory.mktemp("view") / "run"
    summary = run_workflow(wf, out, scheduler=IN_PROCESS)
    assert summary.rejected == 0
    return out


@pytest.fixture(scope="module")
def exported(run: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The run's clip as an MCAP, read back: channels, messages by topic, metadata."""
    (path,) = write_run_view(run, tmp_path_factory.mktemp("mcap") / "clip.mcap")
    messages: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            messages.setdefault(channel.topic, []).append((message.log_time, decoded))
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return {"path": path, "topics": topics, "messages": messages, "metadata": metadata}


def _rows(run: Path) -> dict:
    index = RunIndex.open(run)
    (cid,) = index.clip_ids(CLIPS)
    schemas = (CLIPS, DEPTH_CAMERA, POSES, HANDS, HAND_MASK, INPAINT, SCENE_CLOUD, SCENE_RENDER)
    return {s.name: index.row(s, cid) for s in schemas}


def _matrix(tf) -> np.ndarray:
    q, t = tf.rotation, tf.translation
    return make_se3(matrix_from_quat([q.w, q.x, q.y, q.z]), np.array([t.x, t.y, t.z]))


def _ns(stamp) -> int:
    return stamp.seconds * 1_000_000_000 + stamp.nanos


def _image(msg) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img if img.ndim == 2 else img[..., ::-1]


def test_every_topic_with_its_foxglove_schema(exported: dict) -> None:
    assert exported["topics"] == EXPECTED_TOPICS
    counts = {t: len(m) for t, m in exported["messages"].items()}
    assert all(counts[t] == 9 for t in (*PER_FRAME, "/hands/skeleton", "/camera/trajectory"))
    assert counts["/tf"] == 3 * 9  # camera, camera_raw, camera_source each frame
    assert counts["/inpaint/first_frame"] == counts["/scene/cloud"] == 1
    meta = exported["metadata"]["egosim"]
    assert meta["camera_from"] == "poses" and meta["prompt"]


def test_message_times_are_the_clip_timestamps(run: Path, exported: dict) -> None:
    clip = clip_from_row(_rows(run)["clips"])
    want = [round(t * 1e9) for t in clip.timestamps]
    for topic in (*PER_FRAME, "/hands/skeleton"):
        got = [t for t, _ in exported["messages"][topic]]
        assert got == want, topic
    stamps = [_ns(m.timestamp) for _, m in exported["messages"]["/camera/image"]]
    assert stamps == want  # header stamps agree with log times
    for topic in ("/camera/trajectory", "/camera_raw/trajectory"):
        messages = exported["messages"][topic]
        assert [t for t, _ in messages] == want, topic
        assert [_ns(m.timestamp) for _, m in messages] == want, topic  # restamped every frame
    assert [t for t, _ in exported["messages"]["/scene/cloud"]] == want[:1]


def test_transforms_equal_the_raw_cleaned_and_source_poses(run: Path, exported: dict) -> None:
    rows = _rows(run)
    want = {
        "camera": np.asarray(rows["poses"]["world_from_cam"]).reshape(-1, 4, 4),
        "camera_raw": np.asarray(rows["depth_camera"]["world_from_cam"]).reshape(-1, 4, 4),
        "camera_source": np.asarray(rows["clips"]["world_from_cam"]).reshape(-1, 4, 4),
    }
    got: dict[str, list] = {}
    for _, tf in exported["messages"]["/tf"]:
        assert tf.parent_frame_id == "world"
        got.setdefault(tf.child_frame_id, []).append(_matrix(tf))
    assert set(got) == set(want)
    for frame, poses in want.items():
        np.testing.assert_allclose(np.stack(got[frame]), poses, atol=POSE_ATOL, err_msg=frame)
    (_, path) = exported["messages"]["/camera/trajectory"][4]
    assert [p.position.x for p in path.poses] == pytest.approx(want["camera"][:, 0, 3], abs=1e-12)


def test_calibration_is_the_intrinsics_minus_half_a_pixel(run: Path, exported: dict) -> None:
    fx_, fy, cx, cy = _rows(run)["depth_camera"]["intrinsics"]
    for _, calib in exported["messages"]["/camera/calibration"]:
        assert (calib.width, calib.height, calib.frame_id) == (64, 48, "camera")
        assert list(calib.K) == pytest.approx([fx_, 0, cx - 0.5, 0, fy, cy - 0.5, 0, 0, 1])
        assert list(calib.P)[:7] == pytest.approx([fx_, 0, cx - 0.5, 0, 0, fy, cy - 0.5])
    # Read back through ingest's MCAP source: the convention is undone there, so the round trip
    # gives egosim's intrinsics and the cleaned poses.
    clip = read_mcap_clip(exported["path"], image_topic="/camera/image", camera_frame="camera")
    np.testing.assert_allclose(clip.intrinsics, [fx_, fy, cx, cy], atol=1e-12)
    poses = np.asarray(_rows(run)["poses"]["world_from_cam"]).reshape(-1, 4, 4)
    np.testing.assert_allclose(clip.world_from_cam, poses, atol=1e-6)


def test_pixel_centre_convention_on_a_hand_built_camera() -> None:
    """A point seen at the centre of pixel (i, j) lands on (i, j) exactly with Foxglove's K."""
    intrinsics = np.array([100.0, 120.0, 32.0, 24.0])  # egosim: centres at integer + 0.5
    calib = fx.calibration_message(0, "camera", intrinsics, 64, 48)
    k = np.asarray(calib.K).reshape(3, 3)
    centre = pixel_grid(48, 64)[10, 7]  # egosim (u, v) of pixel column 7, row 10
    assert centre.tolist() == [7.5, 10.5]
    point = np.array([(centre[0] - 32.0) / 100.0, (centre[1] - 24.0) / 120.0, 1.0]) * 2.0
    uv, _ = project_points(point[None], intrinsics)
    np.testing.assert_allclose(uv[0], centre, atol=1e-12)
    ros = k @ point
    np.testing.assert_allclose(ros[:2] / ros[2], [7.0, 10.0], atol=1e-12)
    np.testing.assert_allclose(fx.intrinsics_from_k(calib.K), intrinsics, atol=1e-12)


def test_cloud_masks_first_frame_and_skeleton_equal_the_shards(run: Path, exported: dict) -> None:
    rows = _rows(run)
    cloud_row = rows["scene_cloud"]
    n = cloud_row["num_points"]
    ((_, cloud),) = exported["messages"]["/scene/cloud"]
    assert cloud.frame_id == "world" and len(cloud.data) == n * cloud.point_stride
    record = np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4), ("c", "u1")])
    assert len(record) == n
    np.testing.assert_array_equal(
        record["xyz"].ravel(), np.frombuffer(cloud_row["points_xyz"], "<f4")
    )
    np.testing.assert_array_equal(
        record["rgba"][:, :3].ravel(), np.frombuffer(cloud_row["points_rgb"], "u1")
    )
    np.testing.assert_array_equal(record["c"], np.frombuffer(cloud_row["point_confidence"], "u1"))

    visible = media.decode_lossless_video(rows["scene_render"]["visible"])
    got = np.stack([_image(m) for _, m in exported["messages"]["/scene/visible"]])
    np.testing.assert_array_equal(got, (visible > 0) * 255)
    hand = media.decode_lossless_video(rows["hand_mask"]["hand_mask"])
    got = np.stack([_image(m) for _, m in exported["messages"]["/hands/mask"]])
    np.testing.assert_array_equal(got, (hand > 0) * 255)
    ((_, first),) = exported["messages"]["/inpaint/first_frame"]
    np.testing.assert_array_equal(_image(first), media.decode_png(rows["inpaint"]["first_frame"]))

    clip = clip_from_row(rows["clips"])
    for frame, (_, msg) in zip(clip.frames, exported["messages"]["/camera/image"], strict=True):
        mse = np.mean((_image(msg).astype(float) - frame) ** 2)
        assert 10 * np.log10(255**2 / max(mse, 1e-9)) >= MIN_JPEG_PSNR_DB

    joints = np.asarray(rows["hands"]["hand_joints"], dtype=np.float64).reshape(-1, 2, 21, 3)
    valid = np.asarray(rows["hands"]["hand_valid"], dtype=bool)
    assert valid.any()
    for i, (_, update) in enumerate(exported["messages"]["/hands/skeleton"]):
        shown = {e.id: e for e in update.entities}
        assert set(shown) == {fx.HAND_NAMES[h] for h in range(2) if valid[i, h]}
        for h in range(2):
            if valid[i, h]:
                pts = [[p.x, p.y, p.z] for p in shown[fx.HAND_NAMES[h]].lines[0].points]
                bones = [joints[i, h, j] for a, b in fx.HAND_BONES for j in (a, b)]
                np.testing.assert_allclose(pts, bones, atol=1e-6)  # float32 joints


def test_view_refuses_unknown_clips_and_bad_options(run: Path, tmp_path: Path) -> None:
    with pytest.raises(ExportError, match=r"no clip \['nope'\]"):
        write_run_view(run, tmp_path / "x.mcap", ["nope"])
    with pytest.raises(ConfigError, match=r"jpeg_quality must be in 1\.\.100, got 0"):
        ViewConfig(jpeg_quality=0)
    with pytest.raises(ExportError, match="not a run folder"):
        write_run_view(tmp_path / "missing", tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists()


def test_cli_view_writes_one_file_per_clip(run: Path, tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["view", str(run), "--out", str(tmp_path / "views")])
    assert result.exit_code == 0, result.output
    (path,) = sorted((tmp_path / "views").glob("*.mcap"))
    assert path.name == "synth-tabletop-00000.mcap" and f"wrote {path}" in result.output
    bad = CliRunner().invoke(app, ["view", str(run), "--out", "x.mcap", "--set", "nope=1"])
    assert bad.exit_code == EXIT_USER_ERROR and "nope" in bad.output


@pytest.mark.slow
def test_state_cloud_of_a_state_run(tmp_path: Path) -> None:
    """``workflows/state.yaml`` on one tiny clip (about 20 s): the state as a point cloud."""
    wf = load_workflow(REPO / "workflows" / "state.yaml", [f"ingest.{kv}" for kv in TINY])
    run_workflow(wf, tmp_path / "run", scheduler=IN_PROCESS)
    (path,) = write_run_view(tmp_path / "run", tmp_path / "state.mcap")
    index = RunIndex.open(tmp_path / "run")
    (cid,) = index.clip_ids(CLIPS)
    state = index.row(STATE, cid)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        clouds = [m for _, c, _, m in reader.iter_decoded_messages() if c.topic == "/state/cloud"]
    (cloud,) = clouds
    n = state["num_points"]
    record = np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4), ("s", "u1")])
    assert len(record) == n and cloud.fields[-1].name == "source"
    np.testing.assert_array_equal(record["xyz"].ravel(), np.frombuffer(state["points_xyz"], "<f4"))
    np.testing.assert_array_equal(record["s"], np.frombuffer(state["point_source"], "u1"))


def test_the_3d_skeleton_shows_only_hands_whose_3d_is_trusted(run: Path) -> None:
    """``/hands/skeleton`` is a 3D topic: a hand the hands step trusts in 2D only (``hand_lifted``
    False, its depth a guess) is left out there (the skeleton image still draws it)."""
    from egosim.pipeline.export.view import _ClipView, _gather_hands

    rows = _rows(run)
    valid = np.asarray(rows["hands"]["hand_valid"], dtype=bool)
    lifted = valid.copy()
    lifted[: len(lifted) // 2, 0] = False  # the left hand's first half: 2D only
    hands = {**rows["hands"], "hand_lifted": lifted.tolist()}
    view = _ClipView(
        clip_from_row(rows["clips"]), rows["clips"], {"hands": hands}, {"hands": "hands"}, {}
    )
    _gather_hands(view)
    np.testing.assert_array_equal(view.valid, lifted)
    assert view.used == {"/hands/skeleton": "hands"} and (valid & ~lifted).any()
