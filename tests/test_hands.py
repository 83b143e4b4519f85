"""hands: the given backend and the two filters (duplicates, temporal spikes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from egosim.pipeline.clip_io import row_from_clip, write_clips
from egosim.pipeline.execute import run_shard_task
from egosim.pipeline.shards import open_shard
from egosim.pipeline.stage import ClipRejected
from egosim.schemas.hands import HANDS
from egosim.stages.hands.filters import (
    Detections,
    box_iou,
    deduplicate,
    temporal_outliers,
    to_hands,
)
from egosim.stages.hands.stage import HandsConfig, HandsStage
from egosim.world.camera_path import camera_path
from egosim.world.clip import hand_joints, render_clip
from egosim.world.config import WorldConfig
from egosim.world.interaction import script_interaction
from egosim.world.scene import build_scene
from tests.conftest import make_clip, one_shard_task, write_poses

FPS = 16.0
K = np.array([300.0, 300.0, 208.0, 120.0])  # 416x240 pinhole


@pytest.fixture(scope="module")
def tracks() -> list[tuple[np.ndarray, np.ndarray]]:
    """GT joints (T, 2, 21, 3) and poses (T, 4, 4) of two 61-frame synthetic clips."""
    out = []
    for seed, mode in ((3, "tabletop"), (4, "wild")):
        scene = build_scene(seed, False)
        joints = hand_joints(script_interaction(scene, seed, 61, False))
        out.append((joints, camera_path(seed, mode, 61, FPS)))
    return out


def _detections(joints: np.ndarray) -> Detections:
    t = len(joints)
    return Detections(
        joints=joints.astype(np.float64),
        side=np.tile([0, 1], (t, 1)),
        confidence=np.full((t, 2, 21), 0.9),
        present=np.ones((t, 2), dtype=bool),
    )


def _add_duplicates(det: Detections, rng: np.random.Generator) -> tuple[Detections, np.ndarray]:
    """Append two slots per frame: a jittered copy of a real hand, less confident, some with the
    wrong side label. Returns the new detections and the (T, 4) mask of injected slots."""
    t = det.present.shape[0]
    joints = np.concatenate([det.joints, det.joints + rng.normal(0, 0.003, det.joints.shape)], 1)
    side = np.concatenate([det.side, rng.integers(0, 2, (t, 2))], 1)
    conf = np.concatenate([det.confidence, np.full((t, 2, 21), 0.5)], 1)
    present = np.concatenate([det.present, rng.random((t, 2)) < 0.5], 1)
    injected = np.zeros((t, 4), dtype=bool)
    injected[:, 2:] = present[:, 2:]
    return Detections(joints, side, conf, present), injected


def test_box_iou() -> None:
    assert box_iou(np.array([0, 0, 2, 2]), np.array([1, 1, 3, 3])) == pytest.approx(1 / 7)
    assert box_iou(np.array([0, 0, 1, 1]), np.array([2, 2, 3, 3])) == 0.0


def test_duplicates_removed_real_hands_kept(tracks) -> None:
    rng = np.random.default_rng(0)
    for joints, poses in tracks:
        det, injected = _add_duplicates(_detections(joints), rng)
        kept, removed = deduplicate(det, poses, K, iou_threshold=0.5)
        assert removed == injected.sum()
        assert not np.any(kept.present & injected)
        np.testing.assert_array_equal(kept.present[:, :2], True)
        out, valid, _ = to_hands(kept)
        np.testing.assert_array_equal(out, joints)
        assert valid.all()


def test_spikes_removed_few_clean_frames_dropped(tracks) -> None:
    rng = np.random.default_rng(1)
    clean_dropped = clean_total = 0
    for joints, poses in tracks:
        valid = np.ones((len(joints), 2), dtype=bool)
        clean = temporal_outliers(joints, valid, poses, FPS, max_speed=2.5)
        clean_dropped += int(clean.sum())
        clean_total += clean.size
        spiked = joints.copy()
        frames = np.arange(2, len(joints) - 2, 4)  # isolated spikes, never at the ends
        hands = rng.integers(0, 2, len(frames))
        offsets = rng.normal(size=(len(frames), 3))
        offsets *= 0.3 / np.linalg.norm(offsets, axis=1, keepdims=True)  # 30 cm jumps
        spiked[frames, hands] += offsets[:, None, :]
        found = temporal_outliers(spiked, valid, poses, FPS, max_speed=2.5)
        assert found[frames, hands].all()
        others = found.copy()
        others[frames, hands] = False
        assert others.sum() <= 0.01 * others.size
    assert clean_dropped <= 0.01 * clean_total


def test_invalid_neighbours_are_not_tested() -> None:
    t = 5
    joints = np.zeros((t, 2, 21, 3))
    joints[..., 2] = 0.5
    joints[2, 0] += 1.0
    poses = np.tile(np.eye(4), (t, 1, 1))
    valid = np.ones((t, 2), dtype=bool)
    assert temporal_outliers(joints, valid, poses, FPS)[2, 0]
    valid[1, 0] = False
    assert not temporal_outliers(joints, valid, poses, FPS).any()


def hands_row(out_dir: Path, inputs: dict[str, Path], params: dict, name: str = "hands") -> dict:
    """Run the hands stage with ``params`` as one shard over ``inputs`` (one clip), writing
    ``out_dir/<name>.parquet``; check that it kept the clip and return the clip's hands row."""
    task = one_shard_task("hands", out_dir, inputs, name, params)
    result = run_shard_task(task)
    assert result.rows == 1 and result.rejected == 0
    with open_shard(task.output, HANDS) as reader:
        return next(reader.iter_rows())


def test_stage_end_to_end(tmp_path: Path) -> None:
    clip = render_clip(WorldConfig(seed=2, mode="tabletop", height=48, width=80, num_frames=6))
    good = clip.hand_joints.copy()
    clip.hand_joints[3, 1] += 0.8  # one spike, right hand, frame 3 (12.8 m/s both ways)
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    params = {"backend": "given", "max_speed": 6.0}  # 6 frames: a fast script
    row = hands_row(tmp_path, {"clips": clips}, params)
    with open_shard(clips) as reader:
        clip_row = next(reader.iter_rows())
    valid = np.asarray(row["hand_valid"])
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(6, 2, 21, 3)
    assert row["num_outliers_removed"] == 1 and not valid[3, 1]
    assert np.isnan(joints[3, 1]).all()
    keep = valid.copy()
    np.testing.assert_allclose(joints[keep], good[keep], atol=1e-6)
    # Given joints are 3D: every kept hand is lifted, the de-spiked one is not.
    np.testing.assert_array_equal(np.asarray(row["hand_lifted"]), valid)

    # Poses that no shard writer accepts still reach process() from other callers: reject them.
    for damage in ("nan", "scale"):
        bad = dict(clip_row)
        poses = np.asarray(bad["world_from_cam"], dtype=np.float64).copy()
        poses[2, 0] = np.nan if damage == "nan" else 1.5
        bad["world_from_cam"] = poses.tolist()
        with pytest.raises(ClipRejected, match=clip.clip_id):
            HandsStage().process({"clips": bad})


def test_stage_projects_with_connected_poses(tmp_path: Path) -> None:
    clip = render_clip(WorldConfig(seed=2, mode="tabletop", height=48, width=80, num_frames=6))
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    # Cleaned poses whose camera leaps 0.8 m at frame 3 and back: in camera space both hands
    # leap too (12.8 m/s both ways), so the speed test must drop them; the clip's poses do not.
    leap = clip.world_from_cam.copy()
    leap[3, :3, 3] += [0.8, 0.0, 0.0]
    poses = write_poses(tmp_path / "poses.parquet", clip, leap)

    def run(inputs: dict[str, Path], name: str) -> dict:
        return hands_row(tmp_path, inputs, {"backend": "given", "max_speed": 6.0}, name)

    own = run({"clips": clips}, "own")
    cleaned = run({"clips": clips, "poses": poses}, "cleaned")
    assert own["num_outliers_removed"] == 0
    assert cleaned["num_outliers_removed"] == 2
    assert not np.asarray(cleaned["hand_valid"])[3].any()
    # The given backend's world joints themselves do not depend on the camera.
    keep = np.asarray(cleaned["hand_valid"])  # (T, 2)
    joints = {
        k: np.asarray(r["hand_joints"]).reshape(6, 2, 21, 3)
        for k, r in [("c", cleaned), ("o", own)]
    }
    np.testing.assert_array_equal(joints["c"][keep], joints["o"][keep])


def test_detecting_backends_get_frames_depth_and_labels_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The executor reads what the backends use (frames, depth, labels, camera), not the clip's
    static video, masks or object poses; a stand-in MediaPipe returning the labels as
    detections gives the given backend's joints."""
    clip = make_clip("m", num_frames=6)  # every optional column filled
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    seen = []

    def labels_as_detections(decoded, params):  # the mediapipe backend's signature
        seen.append(decoded)
        t = decoded.num_frames
        joints, conf = decoded.hand_joints, decoded.hand_confidence
        side = np.tile([0, 1], (t, 1))
        return Detections(
            joints.astype(np.float64), side, conf.astype(np.float64), decoded.hand_valid
        )

    monkeypatch.setattr("egosim.stages.hands.stage.mediapipe_detections", labels_as_detections)
    outputs = {}
    for backend in ("mediapipe", "given"):
        params = {"backend": backend, "despike": False}
        outputs[backend] = hands_row(tmp_path / backend, {"clips": clips}, params)
    (decoded,) = seen
    assert decoded.frames.shape == (6, 24, 32, 3)
    np.testing.assert_allclose(decoded.depth, clip.depth, atol=1e-3)  # the lift uses it
    np.testing.assert_allclose(decoded.world_from_cam, clip.world_from_cam, atol=1e-12)
    for unread in ("static_frames", "hand_mask", "object_mask", "first_frame_clean"):
        assert getattr(decoded, unread) is None, unread
    assert decoded.object_poses is None and decoded.text is None
    for name in ("hand_joints", "hand_valid"):
        np.testing.assert_array_equal(outputs["mediapipe"][name], outputs["given"][name], name)


def test_a_clip_without_poses_gets_the_shared_reject() -> None:
    row = row_from_clip(make_clip("np", num_frames=4))
    row["world_from_cam"] = None
    with pytest.raises(ClipRejected) as info:
        HandsStage().process({"clips": row})
    assert str(info.value) == "clip 'np': no camera poses (world_from_cam is null)"


def test_auto_backend_uses_labels_when_the_clip_has_them() -> None:
    from egosim.pipeline.clip_io import row_from_clip
    from egosim.stages.hands.stage import HandsConfig, resolved_backend
    from tests.conftest import make_clip

    row = row_from_clip(make_clip())
    assert resolved_backend(row, HandsConfig(backend="auto")) == "given"
    row["hand_joints"] = None
    assert resolved_backend(row, HandsConfig(backend="auto")) == "mediapipe"


def _rotate_about_centre(hand: np.ndarray, angle_deg: float, axis: np.ndarray) -> np.ndarray:
    """``hand (21, 3)`` rotated by ``angle_deg`` about ``axis (3,)`` through its joints' mean."""
    axis = axis / np.linalg.norm(axis)
    a = np.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k  # Rodrigues
    centre = hand.mean(axis=0)
    return (hand - centre) @ rot.T + centre


def test_rotation_spikes_caught(tracks) -> None:
    """Harness: isolated 60-150 degree turns of one hand about its own centre (the centre barely
    moves, so the position test alone misses them) are caught >= 90%; clean frames stay."""
    rng = np.random.default_rng(2)
    caught = total = 0
    for joints, poses in tracks:
        valid = np.ones((len(joints), 2), dtype=bool)
        spiked = joints.astype(np.float64).copy()
        frames = np.arange(3, len(joints) - 2, 5)
        hands = rng.integers(0, 2, len(frames))
        for f, s in zip(frames, hands, strict=True):
            angle = rng.uniform(60.0, 150.0)
            spiked[f, s] = _rotate_about_centre(spiked[f, s], angle, rng.normal(size=3))
        found = temporal_outliers(spiked, valid, poses, FPS, max_speed=2.5)
        position_only = temporal_outliers(
            spiked, valid, poses, FPS, max_speed=2.5, max_angular_speed=np.inf
        )
        caught += int(found[frames, hands].sum())
        total += len(frames)
        assert position_only[frames, hands].mean() < 0.5  # the old test misses most of them
        others = found.copy()
        others[frames, hands] = False
        assert others.sum() <= 0.01 * others.size
        assert not temporal_outliers(joints, valid, poses, FPS).any()  # clean: nothing dropped
    assert caught >= 0.9 * total, f"{caught} of {total} rotation spikes caught"


def test_hands_trusted_in_2d_only_are_not_lifted(monkeypatch: pytest.MonkeyPatch) -> None:
    """A backend's withheld 3D (``Detections.lifted`` False) reaches the row's ``hand_lifted``
    by side, the hand staying valid; a despiked hand is neither valid nor lifted; the schema
    refuses a lifted hand that is not valid."""
    import egosim.stages.hands.stage as hands_stage

    clip = render_clip(WorldConfig(seed=2, mode="tabletop", height=48, width=80, num_frames=6))
    t = clip.num_frames
    det = _detections(clip.hand_joints[:, ::-1])  # slot 0 holds the right hand: sides swapped
    det = Detections(det.joints, det.side[:, ::-1].copy(), det.confidence, det.present)
    det.lifted = np.ones((t, 2), dtype=bool)
    det.lifted[1:3, 0] = False  # slot 0 = the right hand, frames 1-2: 2D only
    monkeypatch.setattr(hands_stage, "_detections", lambda *args: det)
    row = HandsStage().process({"clips": row_from_clip(clip)})
    valid, lifted = np.asarray(row["hand_valid"]), np.asarray(row["hand_lifted"])
    assert valid.all()
    want = np.ones((t, 2), dtype=bool)
    want[1:3, 1] = False
    np.testing.assert_array_equal(lifted, want)
    assert HANDS.row_problems(row) == []
    bad = {**row, "hand_valid": np.zeros((t, 2), dtype=bool).tolist()}
    assert "hand_lifted True where hand_valid is False" in HANDS.row_problems(bad)
    short = {**row, "hand_lifted": [[True, True]] * t + [[True, True]]}
    assert any("hand_lifted has" in p for p in HANDS.row_problems(short))


def test_the_spike_test_leaves_hands_trusted_in_2d_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """A hand whose 3D the backend withheld has a guessed depth: the spike test neither drops it
    (its 2D stays valid for masks and skeletons) nor takes it as a neighbour; the same jump on
    a lifted hand is dropped."""
    import egosim.stages.hands.stage as hands_stage

    clip = render_clip(WorldConfig(seed=2, mode="tabletop", height=48, width=80, num_frames=6))
    t = clip.num_frames
    joints = clip.hand_joints.copy()
    joints[3, 1] += 0.8  # a 0.8 m jump both ways at frame 3, right hand (12.8 m/s at 16 fps)
    for trusted in (True, False):
        det = _detections(joints)
        det.lifted = np.ones((t, 2), dtype=bool)
        det.lifted[3, 1] = trusted
        monkeypatch.setattr(hands_stage, "_detections", lambda *args, d=det: d)
        row = HandsStage(HandsConfig(max_speed=6.0)).process({"clips": row_from_clip(clip)})
        valid, lifted = np.asarray(row["hand_valid"]), np.asarray(row["hand_lifted"])
        assert valid[3, 1] != trusted and not lifted[3, 1]
        assert row["num_outliers_removed"] == int(trusted)
        others = np.ones((t, 2), dtype=bool)
        others[3, 1] = False
        assert valid[others].all() and lifted[others].all()
