"""bumps_jax: Bottom-Up Meta-Policy Search on a simulated NAO, end to end in JAX and MuJoCo MJX."""
