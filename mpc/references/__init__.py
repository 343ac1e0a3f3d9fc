"""References: flat trajectories, minimum-snap paths and the model's own feed-forward."""
