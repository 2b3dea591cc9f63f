"""The config tree's schema: the stages' sections at their defaults, and their checks."""
