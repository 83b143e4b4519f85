"""The ``simulate`` stage: generate a clip from a state (scene, first frame) and an action."""
