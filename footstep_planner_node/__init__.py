"""footstep_planner: contact patches, cost grid and receding-horizon footstep plans."""
