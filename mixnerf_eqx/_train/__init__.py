"""Training: the objective, schedules, the state and step, checkpoints, the loop, sweeps."""
