"""The studies built on sweeps: the main job, the zoo, versus, learning, real data, bounds."""
