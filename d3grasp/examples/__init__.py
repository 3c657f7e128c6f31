"""Runnable one-file examples: ``python -m d3grasp.examples.<name>`` (each ``--help`` says more).

- ``rule_grasp``: the rule-based controller grasping in four worlds, the pads' forces printed.
- ``train_short``: a short PPO run of the asymmetric LSTM actor-critic, its checkpoint read back.
- ``import_plan_eval``: a mesh of your own imported, its grasps planned and the rule evaluated on it.

Each has a ``run(...)`` function that its test calls with small sizes (``tests/test_examples.py``).
"""
