"""Helpers that several stages share (not a stage; stages may import it)."""
