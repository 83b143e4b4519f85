"""encode: precompute the frozen encoders' outputs (VAE latents, text and image features) from pack shards."""
