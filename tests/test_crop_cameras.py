"""Cameras of a clip cut off-centre by ingest's crop anchor: its principal point, mapped from
the source's, can lie outside the image (above it for the bottom band of a portrait video);
the cameras schema accepts that within a bound, so the rotation and static models, which copy
the clip's intrinsics, are not refused for it."""

from __future__ import annotations

import numpy as np

from egosim.schemas.depth_camera import DEPTH_CAMERA, PRINCIPAL_POINT_REACH


def test_cameras_schema_takes_a_principal_point_outside_the_image() -> None:
    row = {"width": 832, "height": 480, "world_from_cam": [np.eye(4).ravel().tolist()]}
    check = DEPTH_CAMERA.validators[1]  # _check_camera
    # The hands band (anchor y 0.875) of a 1080x1920 video in 832x480: cy = -134.5.
    assert check({**row, "intrinsics": [594.0, 594.0, 416.0, -134.5]}) == []
    assert check({**row, "intrinsics": [594.0, 594.0, 416.0, 240.0]}) == []
    assert PRINCIPAL_POINT_REACH == 2.0
    for cx, cy in [(416.0, -960.5), (416.0, 1440.5), (-1664.5, 240.0), (2496.5, 240.0)]:
        (problem,) = check({**row, "intrinsics": [594.0, 594.0, cx, cy]})
        assert f"principal point ({cx}, {cy}) lies more than 2 image sizes outside" in problem
    (problem,) = check({**row, "intrinsics": [594.0, 594.0, 416.0, float("nan")]})
    assert "intrinsics must be finite" in problem
