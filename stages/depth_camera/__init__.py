"""The ``depth_camera`` stage: intrinsics, per-frame poses, first-frame depth with confidence."""
