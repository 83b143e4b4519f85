"""The ``inpaint`` stage: remove hands from a clip's first frame."""
