"""Training: the objective, the schedules, the state and its step, data parallelism."""
