"""What every contextual env shares: the base class and the physics under it."""
