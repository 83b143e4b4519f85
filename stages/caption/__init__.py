"""The ``caption`` stage: a text prompt per clip."""
