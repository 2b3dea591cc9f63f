"""The algorithm: PPO, behaviour cloning, rollouts, filtering, evaluation and sharding. Imports no task."""
