"""A point mass reaches a goal position on a disc: a small task with a 2-D context."""
