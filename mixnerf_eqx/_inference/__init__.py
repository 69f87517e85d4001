"""Using a trained model: rendering and scoring views, empty-space skipping, camera paths, video."""
