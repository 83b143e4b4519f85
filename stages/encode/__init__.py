"""encode: precompute the frozen encoders' outputs (latents, text, image features) from packs."""
