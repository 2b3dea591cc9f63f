from bumps_jax.cli import main

main()
