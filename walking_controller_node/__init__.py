"""walking_controller: footstep plans -> joint trajectories (see node.py)."""
