"""The fixed target distances (m) of the two evaluations outside the meta-test tasks: the
held-out set (`heldout`, reporting only) and the development set (`dev`, design choices). Both
were drawn once and are written here, never redrawn, so that every run is scored on the same ones.
"""

# 60 held-out targets (m): numpy.random.default_rng(2222).uniform(7, 18), rounded to 3 decimals,
# a draw within 0.005 m of the 0.1 m grid rejected, the first 60 kept. Off the grid of the meta-test
# tasks and the filter's contexts; fixed here so that every run is scored on the same ones.
HELDOUT_TARGETS = (
    10.023, 8.649, 11.981, 10.512, 16.969, 14.137, 14.509, 11.635, 17.767, 15.541, 16.057, 12.994,
    16.615, 7.46, 15.916, 10.653, 8.442, 8.75, 8.468, 13.14, 12.987, 11.056, 17.863, 13.479,
    13.165, 17.183, 13.251, 17.248, 15.754, 8.149, 17.52, 9.884, 13.229, 15.22, 8.206, 11.318,
    10.649, 14.37, 17.263, 13.754, 16.452, 10.338, 14.592, 13.407, 15.578, 15.439, 8.121, 16.521,
    11.153, 7.159, 8.236, 8.574, 9.47, 9.56, 7.261, 16.828, 15.066, 17.259, 9.526, 10.958,
)  # fmt: skip


# Development targets (`evaluate --dev`): 40 draws from U[7, 18] m (numpy default_rng(20261123)),
# rounded to the millimetre, off the 0.1 m grid and apart from every held-out target. Design
# choices are compared on these and `dev.seed`, never on the held-out set or the meta-test seed.
DEV_TARGETS = (
    7.485, 7.725, 11.762, 15.049, 12.678, 12.857, 7.861, 16.306, 7.137, 12.657, 14.017, 17.274,
    15.718, 12.167, 17.826, 7.844, 17.115, 8.475, 7.94, 11.416, 14.351, 8.159, 17.924, 11.516,
    9.892, 9.214, 7.973, 17.636, 15.21, 15.956, 7.638, 9.478, 16.512, 17.761, 16.85, 15.105,
    12.963, 17.629, 11.394, 14.617,
)  # fmt: skip
