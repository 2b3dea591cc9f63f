"""bumps_jax: Bottom-Up Meta-Policy Search on a simulated NAO, trained end to end in JAX and MuJoCo MJX."""
