"""The model: rays, encodings, samplers, fields, the renderer, the mixture and MixNeRF itself."""
