"""stages/common/cameras.resolve_cameras: which camera a stage uses, read through the records.

Covers: the priority (cleaned poses, then estimated cameras, then the clip's own; intrinsics
from the cameras row, else the clip's); records as the executor hands them (only the declared
``CAMERA_COLUMNS``: the poses and cameras roles carry no ``num_frames``) and plain mappings
resolve alike; the values returned are copies of the records' parsed values; a role whose
frame count disagrees with the clip is rejected naming the clip and the role.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from egosim.pipeline import media
from egosim.pipeline.clip_io import row_from_clip
from egosim.pipeline.records import ClipsRecord, DepthCameraRecord, PosesRecord
from egosim.pipeline.stage import ClipRejected, UndeclaredColumnError
from egosim.schemas import CLIPS
from egosim.schemas.depth_camera import DEPTH_CAMERA
from egosim.schemas.poses import POSES
from egosim.stages.common.cameras import (
    CAMERA_COLUMNS,
    first_frame_confidence,
    resolve_cameras,
)
from tests.conftest import make_clip, translated

T = 4
CLIP = make_clip("c", num_frames=T)
CLEANED = translated(CLIP.world_from_cam, np.array([1.0, 0.0, 0.0]))  # (T, 4, 4)
ESTIMATED = translated(CLIP.world_from_cam, np.array([0.0, 2.0, 0.0]))  # (T, 4, 4)
K_EST = np.array([30.0, 31.0, 15.5, 11.5])  # estimated fx, fy, cx, cy


def _rows() -> dict[str, dict[str, Any]]:
    """The three roles as plain mappings (as tests and library callers pass them)."""
    flat = {"poses": CLEANED.reshape(T, 16).tolist(), "cameras": ESTIMATED.reshape(T, 16).tolist()}
    return {
        "clips": row_from_clip(CLIP),
        "poses": {"clip_id": "c", "num_frames": T, "world_from_cam": flat["poses"]},
        "cameras": {
            "clip_id": "c",
            "num_frames": T,
            "intrinsics": K_EST.tolist(),
            "world_from_cam": flat["cameras"],
        },
    }


def _declared(rows: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``rows`` as the executor hands them: each role's record holding only CAMERA_COLUMNS."""
    kinds = {"clips": (ClipsRecord, CLIPS), "poses": (PosesRecord, POSES)}
    kinds["cameras"] = (DepthCameraRecord, DEPTH_CAMERA)
    out = {}
    for role, row in rows.items():
        record, schema = kinds[role]
        kept = {k: row[k] for k in ("clip_id", *CAMERA_COLUMNS[role])}
        out[role] = record(kept, "test", role, schema.column_names)
    return out


@pytest.mark.parametrize("as_records", [False, True])
def test_cleaned_poses_beat_estimated_cameras_beat_the_clip(as_records: bool) -> None:
    rows = _rows()
    cases = [
        (("clips", "poses", "cameras"), "poses", CLEANED, K_EST),
        (("clips", "cameras"), "cameras", ESTIMATED, K_EST),
        (("clips", "poses"), "poses", CLEANED, CLIP.intrinsics),
        (("clips",), "clips", CLIP.world_from_cam, CLIP.intrinsics),
    ]
    for roles, source, poses, intrinsics in cases:
        given = {role: rows[role] for role in roles}
        cams = resolve_cameras(_declared(given) if as_records else given)
        assert cams.source == source, roles
        np.testing.assert_allclose(cams.world_from_cam, poses, atol=1e-12)
        np.testing.assert_allclose(cams.intrinsics, intrinsics, atol=1e-12)
        assert cams.world_from_cam.shape == (T, 4, 4) and cams.intrinsics.shape == (4,)
    clip = dict(rows["clips"], world_from_cam=None)
    cams = resolve_cameras({"clips": clip})
    assert cams.source == "none" and cams.world_from_cam is None


def test_the_records_parse_is_kept_and_copies_are_returned() -> None:
    records = _declared(_rows())
    poses = records["poses"]
    with pytest.raises(UndeclaredColumnError):  # num_frames is not declared for this role ...
        _ = poses.world_from_cam
    cams = resolve_cameras(records)  # ... resolve_cameras needs only the clip's
    cams.world_from_cam[:] = 0.0  # a caller changing its poses in place ...
    cams.intrinsics[:] = 0.0
    again = resolve_cameras(records)  # ... changes neither the records nor the next answer
    np.testing.assert_allclose(again.world_from_cam, CLEANED, atol=1e-12)
    np.testing.assert_allclose(again.intrinsics, K_EST)
    np.testing.assert_allclose(records["cameras"].intrinsics, K_EST)
    # The stage reading the same record gets resolve_cameras' parse, not a second one: with the
    # raw column gone, the parsed value is still there.
    dict.__setitem__(poses, "world_from_cam", None)
    parsed = poses.array("world_from_cam", np.float64, (T, 4, 4))
    np.testing.assert_allclose(parsed, CLEANED, atol=1e-12)


@pytest.mark.parametrize("as_records", [False, True])
def test_a_role_with_another_frame_count_is_rejected(as_records: bool) -> None:
    rows = _rows()
    rows["poses"]["world_from_cam"] = rows["poses"]["world_from_cam"][:3]
    rows["poses"]["num_frames"] = 3
    given = _declared(rows) if as_records else rows
    with pytest.raises(ClipRejected) as info:
        resolve_cameras(given)
    assert str(info.value) == "clip 'c': poses has poses of shape (3, 16), expected (4, 16)"
    rows = _rows()
    rows["cameras"]["world_from_cam"] = [m[:12] for m in rows["cameras"]["world_from_cam"]]
    del rows["poses"]
    with pytest.raises(ClipRejected) as info:
        resolve_cameras(_declared(rows) if as_records else rows)
    assert str(info.value) == "clip 'c': cameras has poses of shape (4, 12), expected (4, 16)"


def test_first_frame_confidence_reads_the_cameras_row_and_rejects_another_size() -> None:
    """confidence0 comes back as [0, 1] floats exactly as encoded; none without a cameras row
    or its column; a size other than depth0's rejects the clip, naming it."""
    conf = np.arange(24 * 32, dtype=np.uint8).reshape(1, 24, 32)  # (1, H, W)
    rows: dict[str, Any] = {
        "clips": {"clip_id": "c7"},
        "cameras": {"confidence0": media.encode_lossless_video(conf)},
    }
    got = first_frame_confidence(rows, (24, 32))
    assert got is not None and got.dtype == np.float32
    np.testing.assert_array_equal(got, conf[0] / np.float32(255.0))
    assert first_frame_confidence({"clips": rows["clips"]}, (24, 32)) is None
    none_row = {"clips": rows["clips"], "cameras": {"confidence0": None}}
    assert first_frame_confidence(none_row, (24, 32)) is None
    with pytest.raises(ClipRejected, match=r"c7.*confidence0 \(24, 32\) != depth0 \(48, 64\)"):
        first_frame_confidence(rows, (48, 64))
