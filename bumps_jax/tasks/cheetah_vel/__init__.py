"""HalfCheetah-Vel: the half-cheetah runs at a target velocity."""
