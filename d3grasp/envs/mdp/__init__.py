"""The task's terms, one file each, as small functions of the environment's tensors (the way
Isaac Lab's ``mdp`` modules are laid out): how actions become joint targets, the observation
groups, the reward inputs, success scoring and terminations, and the reset events."""
