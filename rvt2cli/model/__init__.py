"""The RVT-2 network: multi-view transformer, convex-upsampling heatmaps, two stages, 3D argmax,
location-conditioned rotation; named configurations and the instruction encoder."""
