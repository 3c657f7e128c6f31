"""Training and playing entry points (rsl-rl)."""
