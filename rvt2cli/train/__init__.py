"""Training: keyframe samples from episode files -> a trained RVT-2 checkpoint."""
