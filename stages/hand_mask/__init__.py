"""The ``hand_mask`` stage: hand-and-arm masks per frame from keypoints, colour or SAM."""
